"""The targets of issue 12, asserted at reduced size with the functions of the validation
suite (``benchmarks/validation.py``; the full-size numbers are in docs/validation.md).

Targets not met today are ``xfail(strict=True)`` with the number measured here, so that
they turn red (XPASS) once the cause is fixed and the mark must go."""

import math
import pathlib
import re
import sys
import warnings

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks import validation  # noqa: E402

#: The default fit weight, whose rows the report's unnamed targets read, and the other one,
#: whose rows are named for it: the tests below hold under either default.
DEFAULT_WEIGHT = validation.DEFAULT_FIT_WEIGHT
OTHER_WEIGHT, = (w for w in validation.FIT_WEIGHTS if w != DEFAULT_WEIGHT)


def test_slump_theory_is_the_1d_analysis():
    # h/H0 = S (1 - ln S): 1 at S = 1 (nothing yields), the plug S alone as S -> 0.
    assert validation.slump_theory(1.0) == pytest.approx(1.0)
    assert validation.slump_theory(0.2) == pytest.approx(0.2 * (1.0 + math.log(5.0)))
    assert validation.slump_theory(1e-6) < 2e-5


def test_the_pile_profile_reads_a_lattice_cylinder_and_a_uniform_squash_exactly():
    # A cylinder on the lattice: every band's top and every axis layer where it was built;
    # squashed to 0.6 of its height (volume kept, radius x 1/sqrt(0.6)), the tops read the
    # new height and each layer sits at 0.6 of its initial height.
    from warp_esph.meshes import lattice_points

    H0, R0, n = 0.1, 0.05, 8
    dx = 2 * R0 / n
    x0 = lattice_points(np.array([-R0, 0.0, -R0]), np.array([R0, H0, R0]), dx)
    x0 = x0[np.hypot(x0[:, 0], x0[:, 2]) <= R0]
    depth0 = H0 - x0[:, 1]
    plastic = np.where(depth0 > 0.5 * H0, 2.0, 0.0)
    ratio = np.full(len(x0), 0.5)
    bands, layers = validation.pile_profile(x0, x0, depth0, plastic, ratio, R0, dx, H0)
    assert len(bands) == 4 and np.allclose(bands, 1.0)
    assert len(layers) == n
    assert np.allclose([L["y_over_H0"] for L in layers], [1.0 - L["depth0_over_H0"] for L in layers])
    assert [L["never_yielded_fraction"] for L in layers] == [1.0] * (n // 2) + [0.0] * (n // 2)
    assert np.allclose([L["plastic_mean_yield_strains"] for L in layers], [0.0] * (n // 2) + [2.0] * (n // 2))
    q = 0.6
    x = x0 * np.array([q**-0.5, q, q**-0.5])
    bands, layers = validation.pile_profile(x0, x, depth0, plastic, ratio, R0, q * dx, H0)
    # Wider by 1/sqrt(0.6) = 1.29: the outermost columns (0.95 R0 out) reach the fifth band,
    # and no column lands in the second (the innermost four move from 0.18 to 0.23 R0, the
    # next from 0.40 to 0.51 R0).
    assert bands[1] is None and len(bands) == 5
    assert np.allclose([b for b in bands if b is not None], q)
    assert np.allclose([L["y_over_H0"] for L in layers], [q * (1.0 - L["depth0_over_H0"]) for L in layers])


def _plug_row(plugs, mpm=None, floor="particles"):
    """The report's plug target over made slump rows ``{(S, resolution): (fraction below
    0.99 Y, plastic strain in yield strains)}`` on ``floor``, the other fields those of a pile
    at rest, with the continuum's (MPM) rows ``mpm`` if given."""
    from benchmarks.validation_report import _slump_targets

    rows = [{"case": "slump", "S": S, "resolution": n, "elastic_force": "variational", "floor": floor,
             "fit_weight": DEFAULT_WEIGHT, "theory_h_over_H0": 0.5, "thickness_over_H0": 0.5, "top_rate_pct_H0_per_s": 0.0, "kinetic_over_MgH0": 0.0,
             "at_rest": True, "duration": 8.0, "plug_particles": 24, "plug_unyielded_fraction": f,
             "plug_plastic_strain": e, "run": 0} for (S, n), (f, e) in plugs.items()]
    return next(t for t in _slump_targets(rows, floor, mpm=mpm) if t[0].startswith("an unyielded plug"))


def test_the_plug_target_is_read_for_each_yield_stress_on_its_own():
    # A 3-D pile keeps the 1-D plug only above S = 0.29 (docs/validation.md, the plug): the
    # report says for which S it holds rather than one verdict over all.
    _, got, verdict, _ = _plug_row({(0.3, 16): (0.48, 2.9), (0.5, 16): (1.0, 0.0), (0.5, 24): (0.94, 0.03)})
    assert verdict == "no (S = 0.3; held: S = 0.5)", verdict
    assert "S = 0.5 at 16/24: 94-100 % of it below 0.99 Y, 0-0.03 yield strains" in got, got
    assert _plug_row({(0.5, 16): (1.0, 0.0), (0.5, 24): (0.95, 0.5)})[2] == "yes"
    assert _plug_row({(0.5, 16): (0.95, 1.2)})[2] == "no (S = 0.5; held: none)"


def test_the_plug_target_says_where_the_continuum_misses_it_too():
    """The continuum (MPM) read by the same plug criterion (``validation.plug_measures``) on
    the base the particle floor is judged against (the slip floor that only pushes): where it
    keeps no plug either, its numbers are shown beside the piles' (docs/validation.md, the
    plug), but the verdict stays "no" without naming it a shared miss, since the particle
    floor grips and that continuum does not (as the height's, ``SAME_WALL``); on the ghost
    floor, whose no-slip continuum runs its wall law, the verdict names it. An MPM on another
    base (no-slip under the particle floor, or the slip floor that pulled, which here keeps
    the S = 0.3 plug), a coarser-only reading, or one that keeps its plug changes nothing."""
    slip = "slip"

    def mpm(S, cells, f, e, floor=slip):
        return {"S": S, "aspect": 1.0, "plasticity": "Bingham (Perzyna)", "floor": floor, "res_cells_per_H0": cells,
                "at_rest": True, "duration": 8.0, "plug_particles": 448, "plug_unyielded_fraction": f,
                "plug_plastic_strain": e, "thickness_over_H0": 0.5}

    plugs = {(0.2, 24): (0.02, 21.0), (0.3, 24): (0.19, 4.0), (0.5, 24): (0.94, 0.03)}
    continuum = {"slumps": [mpm(0.2, 12, 0.0, 22.0), mpm(0.3, 12, 0.36, 3.4), mpm(0.3, 16, 0.3, 3.0),
                            mpm(0.5, 12, 1.0, 0.0), mpm(0.3, 24, 0.95, 0.2, floor="pulling slip")]}
    _, got, verdict, _ = _plug_row(plugs, continuum)
    assert verdict == "no (S = 0.2, S = 0.3; held: S = 0.5)", verdict
    assert f"the continuum (MPM, {slip} base) by the same criterion: S = 0.2 at H0 / 12: 0 % of it below 0.99 Y, 22 yield strains" in got, got
    assert "S = 0.3 at H0 / 12/16: 30-36 % of it below 0.99 Y, 3-3.4 yield strains" in got and "H0 / 12/16/24" not in got, got
    bare = _plug_row(plugs)
    assert bare[2] == "no (S = 0.2, S = 0.3; held: S = 0.5)" and "continuum" not in bare[1], bare
    # The continuum keeps the plug at S = 0.3: nothing to say for it.
    kept = _plug_row(plugs, {"slumps": [mpm(0.3, 12, 0.95, 0.2)]})
    assert kept[2] == "no (S = 0.2, S = 0.3; held: S = 0.5)", kept
    # One grid keeps it and another does not: the continuum can, so nothing is named.
    mixed = _plug_row(plugs, {"slumps": [mpm(0.3, 12, 0.36, 3.4), mpm(0.3, 16, 0.95, 0.2)]})
    assert mixed[2] == "no (S = 0.2, S = 0.3; held: S = 0.5)", mixed
    # Only on the other base: not the continuum this floor stands for.
    other = _plug_row(plugs, {"slumps": [mpm(0.3, 12, 0.36, 3.4, floor="sticky")]})
    assert other[2] == "no (S = 0.2, S = 0.3; held: S = 0.5)", other
    assert "continuum" not in other[1], other
    # The ghost floor's continuum (no-slip, the MPM's "sticky") runs its wall law: named there.
    sticky = {"slumps": [dict(r, floor="sticky") for r in continuum["slumps"] if r["floor"] == slip]}
    _, got, verdict, _ = _plug_row(plugs, sticky, floor="ghost_particles")
    assert verdict == "no (S = 0.2, S = 0.3; held: S = 0.5; the continuum on a no-slip base misses it too: S = 0.2, S = 0.3)", verdict
    assert "the continuum (MPM, no-slip base) by the same criterion: S = 0.2 at H0 / 12" in got, got


def test_the_yield_stress_a_slump_fit_recovers_inverts_the_measured_piles():
    """``slump_yield_ratio``: on piles that rest at a fixed share of the 1-D height the fit of
    a height recovers the S whose pile has it exactly (bisection to 1e-12), in either
    interpolation; a height no S in [0.02, 0.95] reaches is nan; a ratio that varies with S
    is followed between the measured piles."""
    from benchmarks.validation_report import one_d_height, slump_yield_ratio

    assert one_d_height(0.2) == pytest.approx(0.2 * (1.0 + math.log(5.0)))
    piles = {S: 0.9 * one_d_height(S) for S in (0.1, 0.2, 0.3, 0.5)}
    for S, true in ((0.2, 0.2), (0.2, 0.26), (0.3, 0.15), (0.5, 0.45)):
        for log_s in (False, True):
            assert slump_yield_ratio(piles, 0.9 * one_d_height(true), S, log_s) == pytest.approx(true / S, rel=1e-9)
    # Read against the 1-D height itself the fit must ask for a stronger material.
    assert slump_yield_ratio(piles, one_d_height(0.2), 0.2) > 1.1
    assert math.isnan(slump_yield_ratio(piles, 1.5, 0.2)) and math.isnan(slump_yield_ratio(piles, 0.01, 0.2))
    varying = {0.1: 1.0 * one_d_height(0.1), 0.3: 0.8 * one_d_height(0.3)}  # 0.9 at S = 0.2 by interpolation
    assert slump_yield_ratio(varying, 0.9 * one_d_height(0.2), 0.2) == pytest.approx(1.0, rel=1e-9)


def test_the_report_judges_the_recovered_yield_stress_against_the_continuum_on_its_base(tmp_path):
    """The report's row "a yield stress fitted to a slump is the continuum's": the finest
    resolution of the particle floor's piles against the MPM's finest grid at rest on the slip
    floor that only pushes (a finer grid not at rest is passed over, and so is the slip floor
    that pulled, "pulling slip", finer and at another height here); the section lists each
    floor against its base."""
    import json

    from benchmarks import validation_report
    from benchmarks.validation_report import continuum_slumps, one_d_height

    def pile(S, n, share, floor="particles"):
        return {"case": "slump", "S": S, "resolution": n, "elastic_force": "variational", "floor": floor,
                "fit_weight": DEFAULT_WEIGHT, "theory_h_over_H0": one_d_height(S), "h_over_H0": share * one_d_height(S),
                "thickness_over_H0": share * one_d_height(S), "top_rate_pct_H0_per_s": 0.0, "kinetic_over_MgH0": 0.0,
                "at_rest": True, "duration": 8.0, "particles": 100 * n, "ratio_to_theory": 1.0, "fraction_at_yield": 0.5,
                "plug_particles": 0, "plug_unyielded_fraction": float("nan"), "radius_over_R0": 2.0,
                "radius_over_spread_theory": 0.9, "time_history": [0.0, 8.0], "h_history": [1.0, share], "run": 0}

    slip = "slip"

    def mpm(S, cells, share, floor=slip, at_rest=True):
        return {"S": S, "aspect": 1.0, "plasticity": "Bingham (Perzyna)", "floor": floor, "res_cells_per_H0": cells,
                "thickness_over_H0": share * one_d_height(S), "at_rest": at_rest, "duration": 8.0}

    continuum = {"slumps": [mpm(S, 16, 0.85) for S in (0.1, 0.2, 0.3)] + [mpm(0.2, 32, 0.5, at_rest=False)]
                 + [mpm(S, 24, 0.95, floor="pulling slip") for S in (0.1, 0.2, 0.3)]}
    assert continuum_slumps(continuum)[slip][0.2] == (16, pytest.approx(0.85 * one_d_height(0.2)), True)
    (tmp_path / "mpm_slump.json").write_text(json.dumps(continuum))
    for coarse, fine, verdict in ((0.80, 0.85, "yes"), (0.85, 0.95, "no")):
        rows = [pile(S, 8, coarse) for S in (0.1, 0.2, 0.3)] + [pile(S, 12, fine) for S in (0.1, 0.2, 0.3)]
        doc = {"runs": [{"command": "rows", "machine": "x86_64", "python": "3.11", "wall_s": 1.0}], "results": rows}
        md, _ = validation_report.write(rows, tmp_path, doc)
        text = md.read_text()
        target = next(line for line in text.splitlines() if line.startswith("| a yield stress fitted to a slump"))
        assert f"| {verdict} | R1 |" in target and "S = 0.2 at 12 across" in target, target
        if verdict == "yes":
            assert "S = 0.2 at 12 across 1.000" in target, target
        assert "## The yield stress a slump fit recovers" in text
        assert f"| particles | {DEFAULT_WEIGHT} | 8 | 0.2 |" in text and "| slip, H0 / 16 |" in text
        assert "pulling slip, H0" not in text and "particles against slip; ghost_particles against sticky" in text


def _tresca_pile(S, n, share, floor="tresca_images", plug=(float("nan"), float("nan"))):
    """A made slump row of a pile at rest resting at ``share`` of the 1-D height."""
    from benchmarks.validation_report import one_d_height

    return {"case": "slump", "S": S, "resolution": n, "elastic_force": "variational", "floor": floor,
            "fit_weight": DEFAULT_WEIGHT, "theory_h_over_H0": one_d_height(S), "h_over_H0": share * one_d_height(S),
            "thickness_over_H0": share * one_d_height(S), "top_rate_pct_H0_per_s": 0.0, "kinetic_over_MgH0": 0.0,
            "at_rest": True, "duration": 8.0, "particles": 100 * n, "ratio_to_theory": 1.0, "fraction_at_yield": 0.5,
            "plug_particles": 0 if plug[0] != plug[0] else 24, "plug_unyielded_fraction": plug[0],
            "plug_plastic_strain": plug[1], "radius_over_R0": 2.0, "radius_over_spread_theory": 0.9, "run": 0}


def _continuum_pile(S, cells, share, floor, f=1.0, e=0.0):
    """A made MPM row (``docs/mpm_slump.json``) at rest on ``floor``, at ``share`` of the 1-D height."""
    from benchmarks.validation_report import one_d_height

    return {"S": S, "aspect": 1.0, "plasticity": "Bingham (Perzyna)", "floor": floor, "res_cells_per_H0": cells,
            "thickness_over_H0": share * one_d_height(S), "at_rest": True, "duration": 8.0, "plug_particles": 448,
            "plug_unyielded_fraction": f, "plug_plastic_strain": e}


def test_the_tresca_ground_is_judged_against_the_1d_height_beside_the_tresca_continuum():
    """The Tresca ground's piles (floor "tresca_images", the suite's floor) get the slump's
    targets, in rows named for no floor: heights against the 1-D theory, within 10 % at
    the finest resolution and converging; the continuum beside them is the MPM on the Tresca
    floor gripping up to tau_y ("Tresca 1 tau_y"), not the slip, no-slip or half-cap one, and
    it is named in the verdict where it misses the 1-D height too, on the same side."""
    from benchmarks.validation_report import _slump_targets

    tresca = "Tresca 1 tau_y"
    # Shares of the 1-D height converging as 1 - 0.04 - 0.4 / n: -6.5 % at 16 across.
    rows = [_tresca_pile(S, n, 0.96 - 0.4 / n) for S in (0.1, 0.2, 0.3, 0.5) for n in (8, 12, 16)]
    continuum = {"slumps": [_continuum_pile(S, 16, 0.97, tresca) for S in (0.2, 0.3)]
                 + [_continuum_pile(S, 12, 1.12, tresca) for S in (0.1,)]
                 + [_continuum_pile(S, 16, 0.7, "slip") for S in (0.1, 0.2, 0.3, 0.5)]
                 + [_continuum_pile(S, 16, 0.8, "Tresca 0.5 tau_y") for S in (0.1, 0.2, 0.3, 0.5)]}

    def height(rows, mpm=continuum):
        targets = _slump_targets(rows, "tresca_images", mpm=mpm)
        return next(t for t in targets if t[0].startswith("slump height")), targets

    (name, got, verdict, _), targets = height(rows)
    assert name.endswith("at the finer resolution, converging"), name
    assert [t[0].split(":")[0] for t in targets[1:]] == [
        "every slumped top at rest at the finer resolution",
        "an unyielded plug where the run resolves one"], targets
    assert verdict == "within 10 %: yes; converging: yes", verdict
    assert "16 across (centre thickness): S = 0.1 -6.5 %" in got, got
    assert (f"the continuum (MPM, {tresca} base, its finest grid at rest): S = 0.1 +12.0 % at H0 / 12, "
            "S = 0.2 -3.0 % at H0 / 16, S = 0.3 -3.0 % at H0 / 16") in got, got
    assert "-30.0 %" not in got and "-20.0 %" not in got, got
    # S = 0.1 over the band at 16 across (+15 %), converging to it: named, and the Tresca
    # continuum over it too (+12 %) is named beside it; under it (-12 %) it is not.
    high = [r for r in rows if r["S"] != 0.1] + [_tresca_pile(0.1, n, 1.13 + 0.32 / n) for n in (8, 12, 16)]
    assert height(high)[0][2] == (f"within 10 %: no (S = 0.1; the continuum on a {tresca} base misses it too: "
                                  "S = 0.1); converging: yes"), height(high)[0][2]
    under = {"slumps": [_continuum_pile(0.1, 12, 0.88, tresca)]}
    assert height(high, under)[0][2] == "within 10 %: no (S = 0.1); converging: yes"
    assert height(high, None)[0][2] == "within 10 %: no (S = 0.1); converging: yes"
    # The other floors read their own rows: none here.
    assert _slump_targets(rows, "particles", mpm=continuum) == []
    # The particle floor grips while its continuum (slip) does not: a slip continuum missing
    # the height on the same side is shown beside its piles but not named as a shared miss.
    slip = {"slumps": [_continuum_pile(0.1, 16, 1.2, "slip")]}
    particles = [dict(r, floor="particles") for r in high]
    (_, got, verdict, _) = next(t for t in _slump_targets(particles, "particles", mpm=slip)
                                if t[0].startswith("slump height"))
    assert "the continuum (MPM, slip base, its finest grid at rest): S = 0.1 +20.0 % at H0 / 16" in got, got
    assert verdict == "within 10 %: no (S = 0.1); converging: yes", verdict


def test_a_height_row_names_as_shared_only_the_piles_it_misses_and_says_where_its_continuum_is_near_rest():
    """A height the piles meet is no shared miss, however far the continuum beside it misses on
    the same side: the verdict names a continuum's miss only at an S the piles miss too. And a
    continuum height read from a grid not at rest (no finer one at rest) says so beside it."""
    from benchmarks.validation_report import _slump_targets

    tresca = "Tresca 1 tau_y"
    # S = 0.1 at +15 % (out of the band), S = 0.2 at +5 % (in it); the continuum +12 % at both.
    rows = ([_tresca_pile(0.1, n, 1.13 + 0.32 / n) for n in (8, 12, 16)]
            + [_tresca_pile(0.2, n, 1.03 + 0.32 / n) for n in (8, 12, 16)])
    continuum = {"slumps": [_continuum_pile(0.1, 16, 1.12, tresca),
                            # S = 0.2: its finest grid still moving, the coarser one at rest.
                            dict(_continuum_pile(0.2, 16, 1.12, tresca), at_rest=False),
                            _continuum_pile(0.2, 12, 1.15, tresca),
                            # S = 0.3's only grid still moving: read there, said so.
                            dict(_continuum_pile(0.3, 16, 1.12, tresca), at_rest=False)]}
    rows += [_tresca_pile(0.3, n, 1.03 + 0.32 / n) for n in (8, 12, 16)]
    _, got, verdict, _ = next(t for t in _slump_targets(rows, "tresca_images", mpm=continuum)
                              if t[0].startswith("slump height"))
    assert verdict.startswith(f"within 10 %: no (S = 0.1; the continuum on a {tresca} base misses it too: S = 0.1); "), \
        verdict
    assert (f"the continuum (MPM, {tresca} base, its finest grid at rest): S = 0.1 +12.0 % at H0 / 16, "
            "S = 0.2 +15.0 % at H0 / 12, S = 0.3 +12.0 % at H0 / 16 (near rest)") in got, got


def test_the_tresca_grounds_plug_names_the_tresca_continuum():
    """The plug target on the Tresca ground: where the MPM on the Tresca 1 tau_y floor keeps no
    plug either it is the one named; the slip continuum's rows, which would also miss, are not."""
    from benchmarks.validation_report import _slump_targets

    tresca = "Tresca 1 tau_y"
    rows = [_tresca_pile(S, n, 0.95, plug=plug) for S, plug in ((0.3, (0.5, 2.9)), (0.5, (1.0, 0.0)))
            for n in (8, 12)]
    continuum = {"slumps": [_continuum_pile(0.3, 8, 0.98, tresca, f=0.5, e=2.8),
                            _continuum_pile(0.3, 12, 0.98, "slip", f=0.3, e=9.0)]}
    _, got, verdict, _ = next(t for t in _slump_targets(rows, "tresca_images", mpm=continuum)
                              if t[0].startswith("an unyielded plug"))
    assert verdict == f"no (S = 0.3; held: S = 0.5; the continuum on a {tresca} base misses it too: S = 0.3)", verdict
    assert (f"the continuum (MPM, {tresca} base) by the same criterion: S = 0.3 at H0 / 8: 50 % of it below 0.99 Y, "
            "2.8 yield strains") in got and "H0 / 12" not in got, got


def test_the_headline_counts_the_tresca_grounds_rows_and_names_the_particle_floors_apart():
    """The suite's slump floor is the Tresca ground (``validation_report.SUITE_FLOOR``, since
    2026-12-07): its rows are named for no floor and counted in the page's headline, its
    recovered yield stress fitted to the Tresca continuum's piles; the particle floor's rows,
    whose wall law no continuum runs, are named "on the particle floor" and counted apart,
    their recovered yield stress against the slip continuum. The page's opening says why in the
    rows' numbers. Seen failing with ``SUITE_FLOOR = "particles"`` (nothing counted apart)."""
    from benchmarks.validation_report import _suite_floor_said, _summary, _targets

    tresca = "Tresca 1 tau_y"
    ground = [_tresca_pile(S, n, 0.95) for S in (0.1, 0.2, 0.3) for n in (8, 12, 16)]
    # The particle floor's piles at 0.9 - 0.1 / n of the height (-10.6 % at 16 across: outside the band).
    particles = [_tresca_pile(S, n, 0.9 - 0.1 / n, floor="particles") for S in (0.1, 0.2, 0.3) for n in (8, 12, 16)]
    continuum = {"slumps": [_continuum_pile(S, 12, 0.95, tresca) for S in (0.1, 0.2, 0.3)]
                 + [_continuum_pile(S, 12, 0.9 - 0.1 / 16, "slip") for S in (0.1, 0.2, 0.3)]}
    targets = _targets(ground + particles, continuum)
    apart = [t for t in targets if " on the particle floor" in t[0]]
    assert len(apart) == 4 and not any("Tresca ground" in t[0] for t in targets), [t[0] for t in targets]
    fitted = {t[0].split(":")[0]: t for t in targets if t[0].startswith("a yield stress fitted")}
    mine = fitted["a yield stress fitted to a slump is the continuum's"]
    assert f"(MPM, {tresca} base)" in mine[0] and mine[2] == "yes" and "S = 0.2 at 16 across 1.000" in mine[1], mine
    theirs = fitted["a yield stress fitted to a slump is the continuum's on the particle floor"]
    assert "(MPM, slip base)" in theirs[0] and "S = 0.2 at 16 across 1.000" in theirs[1], theirs
    # The headline counts the same rows with the particle floor's as without them.
    alone = _summary(_targets(ground, continuum))
    text = _summary(targets)
    headline = re.search(r"\*\*In short\*\*: (\d+) of the (\d+) rows", alone).groups()
    assert re.search(r"\*\*In short\*\*: (\d+) of the (\d+) rows", text).groups() == headline, (alone, text)
    assert int(headline[1]) == len(targets) - len(apart), headline
    assert "particle floor" not in alone and "(the 4 on the particle floor apart, below)" in text, text
    assert "the slump's and the spread's on the Tresca ground, the suite's floor" in text, text
    assert "On the particle floor (" in text and "3 of its 4 rows are met in full" in text, text
    assert "- slump height within 10 % of the 1-D theory, S in [0.1, 0.5], at the finer resolution, converging on the " \
           "particle floor: within 10 %: no (S = 0.1, S = 0.2, S = 0.3)" in text, text
    said = _suite_floor_said(ground + particles, continuum)
    assert ("At 16 across its piles rest at -5.0 / -5.0 / -5.0 % of the 1-D height at S = 0.1 / 0.2 / 0.3 and the "
            "particle floor's at -10.6 / -10.6 / -10.6 %: the Tresca ground's within 10 % at every S, the particle "
            "floor's outside 10 % at S = 0.1, S = 0.2, S = 0.3.") in said, said
    assert ("A yield stress fitted to its piles is that continuum's 1.000 / 1.000 / 1.000 x, where the particle "
            "floor's piles give 1.00-1.00 x of the slip continuum's") in said, said
    # The paragraph's case for the ground: its miss is its continuum's too where that continuum
    # misses on the same side, and only there; the particle floor's never (its slip continuum
    # does not run its wall law). S = 0.1 piles at +12 % on both floors.
    high = [_tresca_pile(0.1, n, 1.12) for n in (8, 12, 16)] + ground[3:]
    high += [_tresca_pile(0.1, n, 1.12, floor="particles") for n in (8, 12, 16)] + particles[3:]
    rest = continuum["slumps"][1:3] + continuum["slumps"][4:]

    def at_s01(share):
        return _suite_floor_said(high, {"slumps": [_continuum_pile(0.1, 12, share, f) for f in (tresca, "slip")] + rest})

    said = at_s01(1.13)
    assert ("the Tresca ground's outside 10 % at S = 0.1, where the continuum on its wall is too (+13.0 %), the "
            "particle floor's outside 10 % at S = 0.1, S = 0.2, S = 0.3.") in said, said
    assert "where the continuum" not in at_s01(0.87), at_s01(0.87)


def test_the_fitted_yield_row_names_the_finer_piles_it_cannot_fit():
    """The fit interpolates between one resolution's piles, so a resolution of fewer than three
    S is no curve for it and the row reads a coarser one: the Tresca ground's row read 16
    across while its S = 0.2 and 0.3 piles at 24 across (R101, R102) went unsaid, the row's
    "at the finer resolution" standing for them. They are named beside, not fitted, their run
    among the row's; a finer resolution with three S is the one read."""
    from benchmarks.validation_report import _fitted_yield_target

    tresca = "Tresca 1 tau_y"
    ground = [_tresca_pile(S, n, 0.95) for S in (0.1, 0.2, 0.3, 0.5) for n in (12, 16)]
    continuum = {"slumps": [_continuum_pile(S, 16, 0.95, tresca) for S in (0.1, 0.2, 0.3, 0.5)]}
    finer = [dict(_tresca_pile(S, 24, 0.9), run=1) for S in (0.2, 0.3)]
    (_, got, met, runs), = _fitted_yield_target(ground + finer, continuum, "tresca_images")
    assert runs == "R1, R2", runs  # the named piles' run too (it was left out: R1)
    # Each S read at 16 across (the continuum's piles where the particles' rest: 1.000).
    assert re.findall(r"S = (\S+) at (\d+) across 1\.000", got) == [(S, "16") for S in ("0.1", "0.2", "0.3", "0.5")], got
    assert got.endswith("; not fitted (finer piles at a resolution of fewer than three S, no curve to fit): "
                        "S = 0.2, S = 0.3 at 24 across"), got
    assert met == "yes", met
    assert "not fitted" not in _fitted_yield_target(ground, continuum, "tresca_images")[0][1]
    # A third S at 24 across makes it a curve: read there, nothing left unsaid.
    (_, got, _, _), = _fitted_yield_target(ground + finer + [_tresca_pile(0.5, 24, 0.9)], continuum, "tresca_images")
    assert "S = 0.2 at 24 across" in got and "not fitted" not in got, got


def test_the_convergence_verdict_recovers_a_power_law_and_refuses_what_is_not_one():
    # The report's "converging" (docs/validation.md): h(n) = h_inf + C n^-p through the last
    # three resolutions, 12/16/24 being equal steps in the spacing.
    from benchmarks.validation_report import convergence

    for p in (0.5, 1.0, 2.0, 3.0):
        for c in (0.7, -0.4):
            ns = [8, 12, 16, 24]
            law = convergence(ns, [0.5 + c * n ** -p for n in ns])
            assert law[0] == pytest.approx(p, rel=1e-6) and law[1] == pytest.approx(0.5, abs=1e-9)
    # Changes of alternating sign, or a last change larger than any converging law allows.
    assert convergence([12, 16, 24], [0.44, 0.45, 0.44]) is None
    assert convergence([12, 16, 24], [0.44, 0.45, 0.47]) is None
    # A last change too small for any order up to 6: settled at the last value.
    assert convergence([8, 12, 16], [1.0, 0.5, 0.5001]) == (math.inf, 0.5001)
    with pytest.raises(ValueError, match="increasing"):
        convergence([16, 12, 24], [1.0, 0.9, 0.8])


def test_bar_frequency_within_2_percent_at_4_across_variational():
    """Measured 0.9992 x c/(2L) (the paper's force: 0.879 x)."""
    r = validation.bar_frequency(resolution=4, elastic_force="variational")
    assert r["periods_measured"] >= 2
    assert r["ratio"] == pytest.approx(1.0, abs=0.02), r["ratio"]


def test_undamped_energy_is_kept_by_the_conservative_rest_fit_at_the_stable_step():
    """Undamped breathing 6^3 cube at large amplitude (peak strain 0.11-0.15), 10 periods at
    ``Model.stable_dt()``. The total is kinetic + sum V psi(F) + the hourglass control's energy
    (``drift_with_control``): the default runs for this elastic cube the curvature-corrected
    total fit with the control at 0.05 (``Model.auto_runs_rest``), a conservative spring whose
    energy the plain ``drift`` leaves out. Measured (poly6 / biweight fit weight): the
    variational force of the total fit against the rest neighbourhood (``deformation="rest"``,
    an energy of the positions alone, no control) drift +0.80 / +0.66 %, largest deviation
    1.3 / 1.4 % (the O(dt^2) offset of the sampled energy); the default +0.65 / +0.84 %, largest
    1.36 / 1.40 % (at dt / 2: 0.21 / 0.30 %, largest 0.32 / 0.34 %: the step's error), where the
    energy without the control's read +0.10 / -2.08 % (-0.36 / -2.41 % at dt / 2: not the step),
    and with the control at 0.2 +0.40 / +0.75 % against -3.1 / -8.0 % without its energy. The
    incremental composition ``F <- dF F`` with that fit and control (path dependent; the
    default before it ran the rest model) gains at the full wave limit, a gain that goes as
    dt^2 and does not stop (docs/physics.md, "The energy of undamped elastic bodies"): a
    premise measured with poly6, named so; with the biweight the gain runs away there. Its
    stable step is half that (``CORRECTED_INCREMENTAL_STEP``), the step this case runs.
    Measured at 13155696 (float32, the control's energy not counted, as asserted): poly6 +10.2 %
    at the stable step, largest deviation 13 % (+16.8 % counting the control's), and +59.5 %,
    largest 60 %, at the full wave limit; the biweight there passes 100 x its energy at 6.65
    periods, where the run stops (105 x at that sample). Read earlier: +8.1 % and +52.3 %, and
    1280 x with the biweight (the energy where a run stops is how far the jump had got). The
    rows above, re-measured at 13155696, read as given."""
    rest = validation.energy_drift(amplitude=validation.LARGE, periods=10.0, deformation="rest", fit="linear",
                                   hourglass=0.0)
    default = validation.energy_drift(amplitude=validation.LARGE, periods=10.0)
    stiff = validation.energy_drift(amplitude=validation.LARGE, periods=10.0, hourglass=0.2)
    for name, r in (("rest", rest), ("default", default), ("control 0.2", stiff)):
        assert not r["blew_up"]
        drift, largest = r["drift_with_control"], r["max_deviation_with_control"]
        assert abs(drift) < 0.02 and largest < 0.03, (name, drift, largest)
    assert rest["drift_with_control"] == rest["drift"]  # no control, nothing added
    # The control's energy is what the plain sum misses: it moves with the control's strength.
    assert stiff["drift"] < -0.02 < stiff["drift_with_control"], (stiff["drift"], stiff["drift_with_control"])
    incremental = validation.energy_drift(amplitude=validation.LARGE, periods=10.0, fit="curvature_corrected",
                                          hourglass=0.05, fit_weight="poly6")
    assert incremental["dt_factor"] == 1.0 and incremental["drift"] > 0.05, incremental["drift"]


def _large_incremental_corrected_breathing(dt_factor):
    """The 6^3 cube of the energy test above at large amplitude, 10 periods, the incremental
    composition with the curvature-corrected fit and the control at 0.05, the default fit
    weight, at ``dt_factor`` x ``Model.stable_dt()``. The cut rows' warning is that of the
    runaway itself (a neighbour row cut after the jump): the energy says it."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="a neighbour row was cut", category=RuntimeWarning)
        return validation.energy_drift(amplitude=validation.LARGE, periods=10.0, fit="curvature_corrected",
                                       hourglass=0.05, dt_factor=dt_factor)


def test_the_large_breathing_cube_on_the_corrected_incremental_fit_keeps_its_energy_at_the_stable_step():
    """The step ``Model.stable_dt(fit="curvature_corrected")`` gives (the wave limit x
    ``CORRECTED_INCREMENTAL_STEP``, 0.5, on the incremental composition) keeps the undamped
    cube's energy, the control's counted, within 2 x its start over 10 periods, as poly6 does
    at the full wave limit (1.70 x float32, 1.76 x float64 at 13155696; 1.63 / 1.78 x when
    docs/physics.md measured it). Measured at 13155696 1.21 x over 10 periods in float32 and
    float64 (poly6 1.17 / 1.18 x; 1.23 x and 1.16 x before; docs/physics.md, "The biweight's
    incremental composition (measured)")."""
    r = _large_incremental_corrected_breathing(1.0)
    assert r["fit"] == "curvature_corrected" and r["hourglass"] == 0.05 and r["rest_model_steps"] == 0
    assert r["periods"] > 9.9 and not r["blew_up"], r["periods"]
    assert r["max_deviation_with_control"] < 1.0, r["max_deviation_with_control"]


def test_the_large_breathing_cube_on_the_corrected_incremental_fit_runs_away_at_twice_the_stable_step():
    """The factor is needed: at 2 x the stable step (the full wave limit, ``stable_dt``'s step
    before the factor) an interior-core mode of the corrected fit's step potential reaches
    ``omega dt`` 2.13 > 2 under compression in period 7 and the energy jumps (measured at
    13155696: past 100 x the start at 6.65 periods, float32 and float64, where the run stops,
    105 / 106 x at that sample; 1279 x read earlier: how far the jump had got where it stopped). The step warns
    that it is past the limit."""
    with pytest.warns(RuntimeWarning, match="the wave limit x 0.5 for the curvature-corrected fit"):
        r = _large_incremental_corrected_breathing(2.0)
    assert r["fit"] == "curvature_corrected" and r["rest_model_steps"] == 0
    assert r["blew_up"] or r["max_deviation_with_control"] > 1.0, (r["periods"], r["max_deviation_with_control"])


#: The rows of docs/validation.md outside the full plan, as their case functions take them, with
#: either weight: the quick plan's, the paper's force's slumps on the particle floor (the
#: suite's floor until 2026-12-07; the plan runs that force on the Tresca ground now), the
#: slumps on the slip ghost floor, the slumps and spread piles on the imaged ground, whose
#: floor images keep an elastic scene on the incremental composition
#: (``Model.scene_allows_rest``), and the fixed-width near-yield columns on the Tresca ground.
ROWS_OUTSIDE_THE_PLAN = [
    (case, kw | {"fit_weight": w}) for w in validation.FIT_WEIGHTS for case, kw in
    validation.plan(True)
    + [("slump", {"S": S, "resolution": res, "elastic_force": "paper", "duration": 8.0, "floor": "particles"})
       for res in (8, 12) for S in validation.SLUMP_S]
    + [("slump", {"S": S, "resolution": res, "floor": "slip_ghost_particles", "duration": 8.0})
     for res, Ss in ((8, (0.1, 0.2, 0.3)), (12, (0.2,))) for S in Ss]
    + [("slump", {"S": S, "resolution": res, "floor": "ground_images", "duration": 8.0})
       for res in (12, 16) for S in (0.1, 0.2, 0.3, 0.5)]
    + [("spread", {"resolution": res, "shallowness": 0.25, "duration": 14.0, "floor": "ground_images"}) for res in (3, 4)]
    + [("near_yield_column", {"resolution": res, "width": validation.NEAR_YIELD_WIDTH, "floor": validation.TRESCA})
       for res in (4, 6, 8)]]


def test_no_validation_row_runs_the_corrected_incremental_fit_so_none_was_measured_at_another_step():
    """``stable_dt`` keeps half the wave limit where the step runs the curvature-corrected fit on
    the incremental composition (``Model.corrected_incremental``), a rule newer than most rows of
    docs/validation.md. Every entry of the full plan and every row outside it
    (``ROWS_OUTSIDE_THE_PLAN``), built to its first step and not stepped
    (``validation.first_step``), runs the linear fit, the rest model or the rest deformation,
    and its stable ``dt`` is the whole wave limit, as when its row was measured: an entry moved
    onto that path (a fit, a floor, ``fit="auto"``'s choice) would run at half its row's ``dt``
    unseen, and its rows need measuring again. Measured: 464 scenes (the suite's floor's entries
    with them since 2026-12-07), none on the path, 25 s on the shared host.
    The breathing cube above, which runs the path, is read at half the wave limit."""
    runs = validation.plan(False) + ROWS_OUTSIDE_THE_PLAN
    halved = []
    for case, kwargs in runs:
        r = validation.first_step(case, kwargs)
        if r["corrected_incremental"] or r["stable_dt"] != r["full_dt"]:
            halved.append((case, kwargs, r["resolved_fit"], r["stable_dt"] / r["full_dt"]))
    assert not halved, halved
    cube = validation.first_step("energy_drift", {"amplitude": validation.LARGE, "fit": "curvature_corrected",
                                                  "hourglass": 0.05})
    assert cube["corrected_incremental"] and not cube["rest_model"], cube
    # Half, but for the control's own limit, which joins the sum 1 / dt^2 (measured 0.50027).
    assert cube["dt"] == cube["stable_dt"] == pytest.approx(0.5 * cube["full_dt"], rel=1e-3), cube
    # The stop it sets is lifted, also where a case fails before its first step: left on, every
    # later case of the process stopped at its first step (the breathing cube's solver here).
    with pytest.raises(TypeError):
        validation.first_step("energy_drift", {"no_such_option": 1})
    wp, we = validation._we()
    b = we.SceneBuilder(spacing=0.05)
    b.add_box((0.0, 0.101, 0.0), (0.1, 0.1, 0.1), we.Material.preset("dough"))
    model = b.finalize()
    a, out = model.state(), model.state()
    validation._solver(model).step(a, out, 1e-4)
    assert out.time == pytest.approx(1e-4)


def test_the_control_energy_energy_drift_adds_is_the_potential_of_the_control_force():
    """``drift_with_control`` adds ``_hourglass_energy``, the control's energy written again in
    numpy beside its force kernel (``warp_esph/sim/hourglass.py`` computes only the gradient,
    ``hourglass_pair_force``): were the two to differ (a factor, a weight, the sums), the total
    the test above asserts would not be the one the step conserves. Its central differences
    must be minus the kernel's force: a 4^3 cube in float64, every particle moved at random by
    up to 0.03 dx (no pair within the support at rest leaves the neighbour list), the
    curvature-corrected fit, the control at 0.05. Measured: within 7.4e-11 of the largest force
    (7.9e-2 N); with the energy's factor 1 / 2 dropped, off by 1.0 of it. 2 s."""
    wp, we = validation._we()
    from warp_esph.sim import hourglass

    dx, c = 0.02, 0.05
    b = we.SceneBuilder(spacing=dx, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (4 * dx,) * 3, we.Material.from_young(2.0e5, 0.3, density=1000.0, pressure_stiffness=0.0))
    m = b.finalize(dtype=wp.float64)
    solver = we.Solver(m, fit="curvature_corrected", hourglass=c)
    x = m.particle_x0 + np.random.default_rng(0).uniform(-0.03 * dx, 0.03 * dx, size=m.particle_x0.shape)
    state, out = m.state(), m.state()
    state.x.assign(x)
    solver.step(state, out, solver.stable_dt())  # out's neighbour list, of x
    out.force.zero_()
    hourglass.launch_hourglass_forces(m, state, out, solver._rest, c)
    force = out.force.numpy()
    energy = validation._hourglass_energy(m, c)
    step = 1e-6 * dx
    gradient = np.zeros_like(x)
    for i in range(len(x)):
        for k in range(3):
            e = np.zeros_like(x)
            e[i, k] = step
            gradient[i, k] = (energy(x + e) - energy(x - e)) / (2 * step)
    scale = np.abs(force).max()
    print(f"largest force {scale:.3e} N, minus the energy's gradient off by {np.abs(force + gradient).max() / scale:.2e} of it")
    assert scale > 0.0
    np.testing.assert_allclose(-gradient, force, rtol=0.0, atol=1e-8 * scale)


def test_energy_drift_says_which_force_conserves_the_energy_it_measures():
    """``energy_drift``'s total, kinetic + sum V psi(F), is what the variational force
    conserves (minus psi's gradient) up to the integration's error: a 4^3 breathing cube keeps
    it within 5 % over 3 periods (measured at 13155696: drift 1.6 %, largest deviation 2.9 %;
    1.8 % before). The paper's force is the gradient of no energy, and its row says so
    (``conservative``, the report's 'conserved by the force'), which is true of what it
    measures: the sum swings by most of itself and the swing does not shrink with the step as
    an integration error would (measured at 13155696 0.89 at dt, 0.86 at dt / 2, 0.85 at dt / 4;
    0.81 / 0.79 / 0.79 before; dt^2 would be 1/16). Before, the rows read alike."""
    variational = validation.energy_drift(amplitude=validation.SMALL, resolution=4, periods=3.0)
    assert variational["conservative"] and variational["energy"] == "St. Venant-Kirchhoff"
    assert abs(variational["drift"]) < 0.05 and variational["max_deviation"] < 0.05, variational["max_deviation"]
    paper = [validation.energy_drift(amplitude=validation.SMALL, elastic_force="paper", resolution=4, periods=3.0,
                                     dt_factor=f) for f in (1.0, 0.25)]
    assert not any(r["conservative"] for r in paper)
    assert paper[1]["max_deviation"] > 0.5 * paper[0]["max_deviation"] > 0.1, [r["max_deviation"] for r in paper]

def test_column_settles_by_rho_g_l2_over_2e():
    """A free-standing column 4 across and 20 tall on a frictionless ground, pressure off,
    relaxed dynamically (``validation.column_settlement``): the top settles by the continuum
    ``rho g L (L - dx) / (2 E)`` between the end layers' centres. Measured with the default
    (the rest model, the corotated stress of a linear material that cannot flow) 0.971 x,
    residual +8e-4 % of it per s, as at a tenth of the load (E 10 x: 0.971); 6 across: 0.981
    (docs/validation.md, R62; with eq. 9's stress, which softened the column by about its mean
    strain, 1.3 % at the base: 0.979, R52, the incremental composition 0.978; 6 across 0.993;
    the paper's force 1.31 / 1.25).
    An earlier form of this test ran the column damped by viscosity alone for 3000 steps
    (0.95 x over the second half, ringing 0.72-1.20 x): seven times the cost."""
    r = validation.column_settlement(resolution=4)
    assert abs(r["residual_rate_pct_per_s"]) < 0.2, r["residual_rate_pct_per_s"]
    assert r["ratio"] == pytest.approx(1.0, abs=0.05), r["ratio"]


def test_column_past_its_self_weight_buckling_length_leans_and_one_short_of_it_straightens():
    """Greenhill's heavy column (``validation.column_buckling_length``): a square column of
    height L leans under its own weight once L passes ``(7.837 E I / (rho g A))^(1/3)``. The
    4-across column (L 0.2 m) given a lean of a tenth of a spacing at its top, pressure off,
    on the frictionless ground, 3 axial periods: at E 1.5e5 (L 0.79 x the buckling length)
    the lean falls, at E 1e4 (1.96 x) it grows (measured: 0.67 / 27 x the initial lean; over
    6 / 12 periods at E 1.5e5 0.50 / 0.27 x, at E 2e4, 1.55 x the length, 14 / 162 x). The
    elastic column runs on the rest model, which measures against the straight rest
    positions, so the lean is a disturbance, not a built-in crookedness. The near-yield
    column (E 1.5e5, dx 0.01 m) is at this length at 8 across and past it at 10 and 12
    (docs/physics.md, "The near-yield column's late collapse")."""
    stiff = validation.column_settlement(resolution=4, E=1.5e5, tilt=0.1, periods=3.0)
    soft = validation.column_settlement(resolution=4, E=1.0e4, tilt=0.1, periods=3.0)
    assert stiff["length_over_buckling"] < 1.0 < soft["length_over_buckling"], (stiff, soft)
    assert stiff["lean"] < 0.1, stiff
    assert soft["lean"] > 0.3, soft


# Float32: the beams' readings are float64's to 5 digits (measured at 9b09e834, the biweight:
# 6 thick 1.0297870 x Timoshenko in both, residual -0.042 against -0.044 % per s; 4 thick
# 1.050818 / 1.050813, the linear fit 1.48807 / 1.4881, the corrected fit alone 1.05488 /
# 1.0549) at 0.68-0.72 x the CPU time of a float64 run (6 thick 14.1 against 20.8 s, 4 thick
# 1.98 against 2.75 s). The float64 step's own checks are the gradient tests'.
BEAM = {"elastic_force": "variational", "span_over_thickness": 5, "dtype": "float32"}


@pytest.fixture(scope="module")
def beam6(run_once):
    """The default solver (``fit="auto"``: for this elastic beam the rest-configuration model
    with the curvature-corrected total fit and the hourglass control at 0.05, docs/physics.md,
    "The default: the fit by material"), 6 thick; one run shared by the tests below."""
    return run_once("validation-beam6", lambda: validation.beam_deflection(resolution=6, **BEAM))


def test_beam_deflection_within_10_percent_at_6_thick_variational(beam6):
    """Float32 (``BEAM``; float64 reads the same ratio to 7 digits). Measured with the
    default solver (the rest model) 1.032 x Timoshenko, residual -0.043 % of it per s (the
    biweight at 9b09e834: 1.0298, -0.042 % per s; the linear fit in its place, the mutation,
    1.206 fails it), as the
    incremental composition with the same fit and control before it (1.033; the paper's
    linear fit, before the default chose by material: 1.159; the next test runs it at 4
    thick)."""
    r = beam6
    assert r["fit"] == "curvature_corrected" and r["hourglass"] > 0.0, (r["fit"], r["hourglass"])
    assert r["rest_model_steps"] > 0, r["rest_model_steps"]
    assert not r["blew_up"]
    assert abs(r["residual_rate_pct_per_s"]) < 0.2, r["residual_rate_pct_per_s"]
    assert r["ratio"] == pytest.approx(1.0, abs=0.10), r["ratio"]


@pytest.fixture(scope="module")
def beam4(run_once):
    """The default solver, 4 thick, over 1.5 periods of the relaxation (its tests read only the
    ratio: poly6 1.0576 x Timoshenko, 1.0569 over 2 periods, 1.0572 over 3; the biweight
    1.0508, 1.0503 over 2; over 1 period, still ringing, 1.0758 / 1.0693)."""
    return run_once("validation-beam4", lambda: validation.beam_deflection(resolution=4, periods=1.5, **BEAM))


def test_beam_with_the_papers_linear_fit_is_too_soft(beam4):
    """``Solver(fit="linear")``, the fit plastic models run: measured 1.357 x Timoshenko at 4
    thick against the default's 1.057 (6 thick: 1.159 against 1.033; docs/physics.md,
    "Bending stiffness": the one-sided fits at the free surfaces; poly6's numbers, the
    biweight's 1.488 against 1.050). Read after 1.5 periods of the relaxation, not 3: only the
    ratio is asserted, poly6 1.3605 there against 1.3578 at 2 and 1.3574 at 3 periods, the
    biweight 1.4881 against 1.4883 at 2 (the curvature-corrected fit in its place, the
    mutation, reads 1.062 / 1.055 at 1.5 periods and fails it)."""
    r = validation.beam_deflection(resolution=4, fit="linear", periods=1.5, **BEAM)
    assert not r["blew_up"] and r["fit"] == "linear" and r["rest_model_steps"] == 0
    assert r["ratio"] > 1.25, r["ratio"]
    assert r["ratio"] > beam4["ratio"] + 0.2, (r["ratio"], beam4["ratio"])


def test_beam_deflection_converges_with_thickness_variational(beam4, beam6):
    """4 and 6 particles thick, span 5 t, float32, the default solver: the error shrinks with
    resolution, both within 10 % (measured 1.057 and 1.033; the linear fit 1.357 and 1.159)."""
    r4, r6 = beam4, beam6
    assert not r4["blew_up"] and not r6["blew_up"]
    assert r4["ratio"] == pytest.approx(1.0, abs=0.10), r4["ratio"]
    assert abs(r6["ratio"] - 1.0) < abs(r4["ratio"] - 1.0), (r4["ratio"], r6["ratio"])


def test_beam_deflection_with_the_curvature_corrected_fit_alone():
    """``Solver(fit="curvature_corrected")`` without the control (an explicit fit runs no
    control unless asked): measured 1.061 at 4 thick (1.058 with the default's control), after
    2 periods of the relaxation as after 3 (1.0608, 1.0610); read after 1.5 periods: poly6
    1.0616, the biweight 1.0549 (1.0542 after 2; the linear fit in its place, the mutation,
    reads 1.361 / 1.488 and fails it)."""
    r = validation.beam_deflection(resolution=4, fit="curvature_corrected", periods=1.5, **BEAM)
    assert r["fit"] == "curvature_corrected" and r["hourglass"] == 0.0
    assert r["ratio"] == pytest.approx(1.0, abs=0.10), r["ratio"]


def test_float32_beam_of_the_conservative_rest_model_settles():
    """The rest model's variational force (``Material(deformation="rest")``, corrected fit,
    control 0.05) in float32, 4 thick, span 5 t, 3 periods (the beams' default): the beam
    settles. Measured 1.0572 x Timoshenko, residual -0.048 % of it per s (the relaxation's
    last ringing: +0.003 at 4.5 periods, +0.37 at 2.5). With the constitutive update
    rewriting an unflowed ``F_p`` as ``F_e^-1 (F F_p)`` every step again (the mutation: its
    round-off walks the rest shape) the beam creeps at -2.3 %/s at 3 periods (-2.1 at 4.5;
    -0.73 when first measured; at span 10 t, 9 periods: 1.004 at +8.6 %/s, now 1.0550 at
    -0.006 %/s; docs/physics.md, "The energy of undamped elastic bodies")."""
    r = validation.beam_deflection(resolution=4, span_over_thickness=5, dtype="float32",
                                   fit="curvature_corrected", hourglass=0.05, deformation="rest")
    assert not r["blew_up"]
    assert abs(r["residual_rate_pct_per_s"]) < 0.2, r["residual_rate_pct_per_s"]
    assert r["ratio"] == pytest.approx(1.0, abs=0.10), r["ratio"]


# The CI slumps stand on the suite's floor, the Tresca ground (``validation.TRESCA``: the
# frictionless imaged ground holding its base up to the material's shear yield stress, the
# continuum's Tresca floor; docs/physics.md, "The Tresca ground (built)"): no pinned layers to
# pay for (416 particles at 8 across, against 416 + 496 on the particle floor's disc of 2.2 R0),
# and no disc for a pile to outgrow. The particle floor keeps the one test that asserts its own
# property: the elastic particle floor's pile resting above the plastic one's.
SLUMP_FLOOR = {"floor": validation.TRESCA}
PARTICLE_FLOOR = {"floor": "particles", "floor_radius": 2.2}


@pytest.fixture(scope="module")
def slumped(run_once):
    """S = 0.2, 8 particles across H0, variational force, on the Tresca ground, 6.5 s (64 x
    sqrt(H0/g)). Read from 10 s (the biweight) and 8 s (poly6) runs' histories, the suite's
    verdict (``at_rest``) holds from 6.0 s for the biweight (top 0.093 % H0/s, kinetic energy
    5.8e-9 M g H0 over the last quarter) and from 5.5 s for poly6 (0.097, 4.0e-9); at 4.5 s
    neither is at rest (0.198 / 2.1e-8 and 0.127 % H0/s): whichever weight is the default, the
    pile is read at rest by the same bounds. 36 s of CPU (12791 steps)."""
    return run_once("validation-slumped", lambda: validation.slump(0.2, resolution=8, elastic_force="variational", duration=6.5,
                                                                    **SLUMP_FLOOR))


def test_slumped_cylinder_comes_to_rest(slumped):
    """Measured on the Tresca ground at 6.5 s: the biweight's top 0.075 % H0/s, kinetic energy
    8.9e-10 M g H0 at the end, 4.4e-9 at most over the last quarter (bounds 0.1 and 1e-8);
    poly6's 0.079 % H0/s and 2.6e-9 (read from its 8 s run's history). Both piles still creep
    at yield as a whole, slowing (docs/physics.md, "The coarse piles' settling, run longer"):
    the biweight's 0.030 % H0/s at 10 s. With the Tresca hold left out (``tresca_traction``
    returning at once, the frictionless imaged ground: the mutation) the pile still spreads at
    6.5 s, kinetic energy 5.9e-8 M g H0 at the end (its S = 0.5 pile 0.19 % H0/s at 2 s)."""
    assert slumped["finite"]
    assert abs(slumped["top_rate_pct_H0_per_s"]) < 0.1, slumped["top_rate_pct_H0_per_s"]
    assert slumped["kinetic_over_MgH0"] < 1e-8, slumped["kinetic_over_MgH0"]
    # The report's verdict (rate and the largest kinetic energy over the last quarter) agrees.
    assert slumped["at_rest"], (slumped["top_rate_pct_H0_per_s"], slumped["kinetic_last_quarter_over_MgH0"])


def test_the_plug_is_not_judged_where_the_run_cannot_resolve_it(slumped):
    """S = 0.2, 8 across: the 1-D plug (S H0 = 1.6 dx) is thinner than the support radius (2 dx): every top
    particle's fit reaches into flowing material, so this run cannot show a plug (docs/
    validation.md, the plug), on any floor. Measured on the Tresca ground: its top layer
    flowed 7.7 yield strains and rests at yield, coherently (layer-mean deviator 1.000 Y; on the
    particle floor 45 yield strains, 0.93 Y). With the plug read whatever its thickness
    (``resolved`` always true in ``slump``: the mutation) the run reports 12 plug particles."""
    assert slumped["plug_particles"] == 0
    assert math.isnan(slumped["plug_plastic_strain"])


@pytest.fixture(scope="module")
def slumped_stiff(run_once):
    """S = 0.5, 8 across, variational force, on the Tresca ground, 2 s: the 1-D plug is 4 dx
    thick, and its top half, which the sudden release leaves below yield, is 2 dx = one support
    radius: resolved (the top 2 layers near the axis, 24 particles). At rest by the suite's
    verdict from 1.25 s for the biweight (0.071 % H0/s, 3.8e-9 M g H0; read from a 4 s run's
    history) and from 2 s for poly6 (0.065 % H0/s, 7.3e-9; at 1.75 s 0.080 and 1.15e-8, not at
    rest); the height, plug and radius read at 2 s as at 4 s to 4e-4 H0 (R0). 7 s of CPU (3936 steps)."""
    return run_once("validation-slumped_stiff", lambda: validation.slump(0.5, resolution=8, elastic_force="variational",
                                                                          duration=2.0, **SLUMP_FLOOR))


def test_slumped_cylinder_keeps_an_unyielded_plug(slumped_stiff):
    """Where the plug is resolved it does not flow and rests below yield (docs/validation.md,
    the plug). Measured on the Tresca ground at 2 s: plastic strain 0 in the plug (mean and
    max; poly6 0 too) against 10.1 yield strains (poly6 9.5) more than a support radius below
    the 1-D yield surface; 24 of 24 plug particles below 0.99 Y (the top layer's mean deviator
    0.45 Y); top 0.031 % H0/s, 6.4e-10 M g H0 over the last quarter (poly6 0.065, 7.3e-9), R
    1.19 R0. (The particle floor's pile, 1.75 s, as measured before: 0 against 8.9 yield
    strains, 24 of 24.) With the yield surface at 0.5 Y (``plasticity.yield_surface``, which
    the Tresca hold reads too: the mutation) the plug flows 3.9 yield strains and the pile
    still sinks 1.05 % H0/s at 2 s; with the stress read 10 x (``_deviatoric_norm``: the
    mutation) none of the plug reads below 0.99 Y. With the Tresca hold left out the pile is
    not at rest at 2 s (0.19 % H0/s, 8.4e-8 M g H0), the plug still whole."""
    r = slumped_stiff
    assert r["plug_particles"] >= 12, r["plug_particles"]
    assert r["flowed_plastic_strain"] > 2.0, r["flowed_plastic_strain"]  # the base did flow
    assert r["plug_plastic_strain"] < 1.0, r["plug_plastic_strain"]
    assert r["plug_unyielded_fraction"] > 0.9, r["plug_unyielded_fraction"]
    assert r["at_rest"], (r["top_rate_pct_H0_per_s"], r["kinetic_last_quarter_over_MgH0"])


def test_slumped_plug_keeps_a_flat_top(slumped_stiff):
    """A plug that does not flow descends whole: its top stays flat, the highest particle of
    the pile no more than a quarter spacing above the centre's (dx = H0 / 8). Measured on the
    Tresca ground: 0.905 against 0.897 H0 (0.06 dx; poly6 0.07 dx; the particle floor's 0.909
    against 0.900). A top that flowed sags into a bowl instead (docs/physics.md, the S = 0.2
    pile below the 1-D height): on the Tresca ground at 8 across the S = 0.2 pile's rim stands
    0.88 dx above its centre, the S = 0.3 pile's 0.31 dx (its validation row, 8 s), so the
    bound is a quarter spacing, not the spacing the particle floor's S = 0.2 bowl (1.1 dx)
    allowed. With the yield surface at 0.5 Y (the mutation) the S = 0.5 top is a bowl of
    0.50 dx."""
    r = slumped_stiff
    assert r["top_max_over_H0"] - r["h_over_H0"] < 0.25 / 8.0, (r["top_max_over_H0"], r["h_over_H0"])


def test_slump_thickness_reads_the_top_of_a_flat_plug(slumped_stiff):
    """Where the top is a whole layer of particles (the intact S = 0.5 plug, flat) the
    material's thickness on the axis and the top particle read the same height, within a
    quarter spacing. Measured on the Tresca ground: 0.885 against 0.897 H0 (0.10 dx; the
    particle floor's 0.892 against 0.900). On the rough top of the S = 0.1 pile they do not
    (next test). With the top particle read at its centre (``slump``'s height without its
    dx / 2, each particle standing for a cell: the mutation) they are 0.40 dx apart."""
    r = slumped_stiff
    assert abs(r["thickness_over_H0"] - r["h_over_H0"]) < 0.25 / 8, (r["thickness_over_H0"], r["h_over_H0"])


@pytest.mark.slow
def test_s01_pile_centre_thickness_within_3_percent_of_the_1d_height_at_12_across():
    """S = 0.1, 12 across, defaults, 8 s (at rest: 0.003 % H0/s): the top particle near the
    axis reads h/H0 0.381, +15.4 % of the 1-D height 0.330 (+19.0 % at 16 across, 6 s), but
    the top is rough at the particle scale (its particles within R0/2 spread by 0.06 H0, the
    four lattice columns nearest the axis stand about a spacing above their neighbours) and
    the material's thickness there is 0.3335 (+1.0 %; 16 across 0.330, -0.1 %; 8 across,
    where the pile is three whole layers, 0.378): docs/physics.md, why the S = 0.1 pile
    stands above the 1-D height. At 4 s, the suite's reading: h 0.3817 (+15.6 %), thickness
    0.3349 (+1.4 %, still sinking 0.27 % H0/s). 314 s on the shared, loaded cores."""
    r = validation.slump(0.1, resolution=12, duration=8.0)
    assert r["finite"] and abs(r["thickness_rate_pct_H0_per_s"]) < 0.1, r["thickness_rate_pct_H0_per_s"]
    assert r["thickness_over_H0"] == pytest.approx(validation.slump_theory(0.1), rel=0.03), r["thickness_over_H0"]
    assert r["h_over_H0"] - r["thickness_over_H0"] > 0.5 / 12, (r["h_over_H0"], r["thickness_over_H0"])


def test_slump_height_within_10_percent_of_the_1d_theory(slumped, slumped_stiff):
    """Issue 12's height target on the suite's floor at 8 across, both as the report reads it
    (the centre thickness) and as the top particle near the axis. Measured on the Tresca
    ground: S = 0.2 thickness 0.484 H0 against the 1-D 0.522 (-7.2 %; poly6 +2.3 %, from its
    8 s run's history), top 0.524 (+0.4 %; poly6 +4.1 %); S = 0.5 thickness 0.885 against
    0.847 (+4.5 %; poly6 +5.1 %), top 0.897 (+6.0 %). (The particle floor's S = 0.2 pile, this
    tree, 6.5 s: thickness 0.506, -3.0 %, top 0.513, -1.7 %.) With the Tresca hold left out
    (the mutation) the S = 0.2 pile's thickness reads 0.346 H0 (-33.7 %); with the yield
    surface at 0.5 Y 0.394 (-24.5 %)."""
    for r in (slumped, slumped_stiff):
        assert r["thickness_over_H0"] == pytest.approx(r["theory_h_over_H0"], rel=0.10), (r["S"], r["thickness_over_H0"])
        assert r["h_over_H0"] == pytest.approx(r["theory_h_over_H0"], rel=0.10), (r["S"], r["h_over_H0"])


def test_slump_on_an_elastic_particle_floor_rests_higher_than_on_the_plastic_one():
    """The floor's plasticity (docs/physics.md, "The floor's plasticity"): on a floor the
    material sticks to (``floor="elastic_particles"``) the S = 0.2 pile at 8 across comes to
    rest higher than on the suite's plastic particle floor. Both run 3 s: the elastic floor's
    pile is at rest, the plastic floor's still sinks (the biweight's top 2.1 % H0/s) and only
    sinks further, so its 3 s thickness bounds the one it rests at from above (the biweight's
    0.5085 H0 at 3 s, 0.5063 at 6.5 s, at rest), and the plastic floor's run costs less than
    half of one to rest. Measured, the biweight: elastic floor 0.5571 H0 (+6.7 % of the 1-D
    0.5219; top 0.0068 % H0/s, KE over the last quarter 1.1e-9 M g H0), 0.049 H0 above the
    plastic floor's 0.5085; poly6 (earlier tree) 0.5438 (+4.2 %) against the plastic floor's
    0.4865 at 3 s (this tree), 0.057 H0 above. The biweight's elastic-floor pile is at rest
    from 2.75 s (5.7e-9 M g H0; 3.8e-8 at 2.5 s; read from the 3 s run's history). With the
    floor left plastic (``elastic=True`` not applied: the mutation) the pile still sinks
    2.1 % H0/s at 3 s, the two runs the same; with the yield surface at 0.5 Y (the mutation)
    the elastic floor's pile still sinks 0.51 % H0/s at 3 s (thickness 0.4787, -8.3 %). The
    1-D bound is the issue's 10 %: the biweight's +6.7 % stood 0.3 points inside the 7 % bound
    used before (+5.7 % at an earlier tree). At 12 / 16 across (earlier trees): -0.1 / -0.3 %
    (plastic floor -15.6 / -14.5 %); the thin S = 0.1 pile +28.8 % at 16."""
    held = validation.slump(0.2, resolution=8, elastic_force="variational", duration=3.0,
                            **{**PARTICLE_FLOOR, "floor": "elastic_particles"})
    plastic = validation.slump(0.2, resolution=8, elastic_force="variational", duration=3.0, **PARTICLE_FLOOR)
    assert held["finite"] and held["at_rest"], (held["top_rate_pct_H0_per_s"], held["kinetic_last_quarter_over_MgH0"])
    assert held["thickness_over_H0"] == pytest.approx(held["theory_h_over_H0"], rel=0.10), held["thickness_over_H0"]
    assert held["thickness_over_H0"] > plastic["thickness_over_H0"] + 0.04, (held["thickness_over_H0"], plastic["thickness_over_H0"])
    # Both piles within the disc less a support radius (0.5 R0), as the plastic floor's fixture asserted before the
    # Tresca ground: a rim beyond it would stand on no floor. Measured 1.605 / 1.612 R0 (the elastic floor's pile
    # with the yield surface at 0.5 Y: 1.763).
    for r in (held, plastic):
        assert r["radius_over_R0"] < PARTICLE_FLOOR["floor_radius"] - 0.5, (r["floor"], r["radius_over_R0"])


@pytest.mark.parametrize("resolution", [8, 12, 16])
def test_centre_thickness_reads_the_cylinder_height_on_its_lattice(resolution):
    """The slump's height as a volume (``centre_thickness`` over R0 / 2) of the cylinder
    before it slumps is H0 (measured 0.9997 / 0.9955 / 0.9990 at 8 / 12 / 16 across): its
    smooth weight keeps the lattice's count of columns inside a disc out of it (the particles
    whose centres lie within R0 / 2: 0.955 / 1.132 / 1.034 H0)."""
    model, free, _, _ = validation.slump_model(0.1, resolution)
    x = model.particle_x0.astype(np.float64)[free]
    volume = model.particle_volume.numpy().astype(np.float64)[free]
    assert validation.centre_thickness(x, volume, np.ones(len(x)), 0.025) == pytest.approx(0.1, rel=0.006)


def test_spread_theory_is_the_volume_of_its_profile():
    """R_RC = (225 rho g Omega^2 / (128 pi^2 tau_y))^(1/5) is the radius at which the shallow
    profile h(r) = sqrt(2 tau_y (R - r) / (rho g)) holds the volume Omega (midpoint rule)."""
    tau_y, volume = 30.0, 4.0e-4
    R = validation.spread_radius_theory(volume, tau_y)
    ell = tau_y / (validation.RHO * validation.G)
    n = 200000
    r = (0.5 + np.arange(n)) * R / n
    integral = float((2.0 * math.pi * r * (2.0 * ell * (R - r)) ** 0.5).sum() * R / n)
    assert integral == pytest.approx(volume, rel=1e-4)
    assert validation.spread_height_theory(R, tau_y) == pytest.approx((2.0 * ell * R) ** 0.5)


def test_slump_shallow_theory_holds_the_cylinder_volume_and_falls_with_its_aspect():
    """h_RC of the slump's cylinder: the shallow profile sqrt(2 l (R - r)) of that centre
    height holds pi R0^2 H0 (midpoint rule), and a taller, narrower cylinder of the same H0
    and S (less volume) gives a lower pile, where the 1-D height S (1 - ln S) stays put.
    At S = 0.1, aspect 1: 0.362 H0, above the 1-D 0.330; at aspect 1.5: 0.308, below it."""
    for aspect in (1.0, 1.5, 2.0):
        h = validation.slump_shallow_theory(0.1, aspect)
        ell = 0.1 / math.sqrt(3.0)
        R = h**2 / (2.0 * ell)
        n = 200000
        r = (0.5 + np.arange(n)) * R / n
        integral = float((2.0 * math.pi * r * (2.0 * ell * (R - r)) ** 0.5).sum() * R / n)
        assert integral == pytest.approx(math.pi * (0.5 / aspect) ** 2, rel=1e-4)
    assert validation.slump_shallow_theory(0.1, 1.0) > validation.slump_theory(0.1)
    assert validation.slump_shallow_theory(0.1, 1.5) < validation.slump_theory(0.1)


@pytest.fixture(scope="module")
def spread_pile(run_once):
    """The spread limit at its smallest size: a = h_RC / R_RC = 0.25, 3 particles through h_RC
    (720 particles), on the default particle floor under a disc of 1.0 R_RC (it rests at 0.85),
    read at 4 s. Whether it comes to rest takes 14 s to see (a rearrangement at its rim at
    about 7.5-10 s spreads it by 1 % of R_RC, then it rests: docs/physics.md, "The thin
    spread pile under energy_spiky: a late rearrangement, then rest"), over 3 minutes of
    this suite's CPU time, so the 14 s run is the validation benchmark's (the full plan's
    particle-floor pile, ``--only spread:floor=particles:resolution=3``: the quick plan's stands
    on the Tresca ground since 2026-12-07; docs/validation.md). It names
    poly6: the bounds below read its creep at 4 s, which the biweight's pile, creeping on
    longer, does not meet (docs/physics.md, "The switch list worked through"; its record at
    14 s is the benchmark's row, ``test_docs.py``'s
    ``test_the_biweight_spread_piles_record_is_the_benchmarks_row_at_rest_at_14_s``)."""
    return run_once("validation-spread_pile", lambda: validation.spread(resolution=3, shallowness=0.25, duration=4.0,
                                                                        floor="particles", floor_radius=1.0,
                                                                        fit_weight="poly6"))


def test_spread_pile_holds_the_theory_volume_and_slows_to_a_creep(spread_pile):
    """Measured with poly6 (energy_spiky, the fit guard cond(A) > 20) at 4 s: R 0.840 R_RC
    growing 0.214 % R_RC/s over 3-4 s, kinetic energy 7.3e-8 M g h_RC (falling an e-fold per
    0.8 s through 3-4 s; below 1e-7 from 3.7 s); the lattice holds the theory volume to 0.53 %
    and the material at the end (rest volumes times det F) that to 0.05 %; at 5 s 0.144 %
    R_RC/s and 3.7e-8; at 14 s (the benchmark) 0.021 % R_RC/s and 2.0e-11. A yield surface 10
    % low (0.9 Y) still spread 0.565 % R_RC/s at 4 s (measured when this pile read 0.199 %
    R_RC/s and 6.4e-8)."""
    r = spread_pile
    assert r["finite"]
    assert r["volume_over_theory"] == pytest.approx(1.0, abs=0.01), r["volume_over_theory"]
    assert r["end_volume_over_theory"] == pytest.approx(r["volume_over_theory"], rel=0.01), r["end_volume_over_theory"]
    assert 0.0 <= r["radius_rate_pct_per_s"] < 0.25, r["radius_rate_pct_per_s"]
    assert r["kinetic_over_Mgh"] < 1e-7, r["kinetic_over_Mgh"]


@pytest.mark.xfail(strict=True, reason="spread limit at the suite's size, a = 0.25, 3 through h_RC, particle floor: "
                   "measured R = 0.840 R_RC at 4 s (0.841 at 5 s), 0.854 at rest at 14 s (the validation suite's 4 / 5 through: "
                   "0.898 / 0.937, within 10 % at 5) (energy pressure force 0.857 at 8 s, spiky 0.869, ground collider 0.834); at 3 through the yield length l is 0.375 dx and the pile a "
                   "disc 3 particles thick with a rim 6 l tall (docs/physics.md, the spread regime)")
def test_spread_radius_within_10_percent_of_roussel_coussot(spread_pile):
    assert spread_pile["radius_over_theory"] == pytest.approx(1.0, abs=0.10), spread_pile["radius_over_theory"]


# A layer 3 particles thick on an incline, loaded to `load` x its continuum shear strength
# at the base (docs/physics.md, "The spread regime", thin layers): 240 / 144 particles, 0.6 s.
THIN_LAYER = {"layers": 3, "duration": 0.6, "length": 8.0}


@pytest.fixture(scope="module")
def held_strip(run_once):
    """The strip at 1.3 tau_y on the particle floor between walls through its outer rows'
    centres, 0.75 s: one run for the two tests that read it (it flows above yield; it keeps
    its width and is still sliding where the widened strip has stopped)."""
    return run_once("validation-held_strip", lambda: validation.incline(load=1.3, floor="particles", layers=3, length=8.0,
                                                                        duration=0.75, walls="centres"))


def _stops_below_and_flows_above(floor: str, above=None):
    """The strip on ``floor`` (walls through the outer rows' centres): at 0.6 tau_y its top
    stops (below 3 % of the Bingham surface speed at 1.3), at 1.3 tau_y it flows at more
    than half that speed (``above``: that run, if already made; else 0.6 s of it)."""
    below = validation.incline(load=0.6, floor=floor, walls="centres", **THIN_LAYER)
    if above is None:
        above = validation.incline(load=1.3, floor=floor, walls="centres", **THIN_LAYER)
    assert below["finite"] and above["finite"]
    scale = above["bingham_surface_speed"]
    assert abs(below["top_speed"]) < 0.03 * scale, (below["top_speed"], scale)
    assert above["top_speed"] > 0.5 * scale, (above["top_speed"], scale)


def test_thin_layer_on_a_floor_of_its_own_particles_stops_below_and_flows_above_the_shear_yield_stress(held_strip):
    """Floor: two pinned layers of the layer's own body, so every particle's fit is that of
    an interior one at the base. The walls normal to z go through the outer rows' centres,
    so the strip cannot widen, which stops it after about a spacing of slip (next test):
    what is left is the layer's shear strength. Measured with the default pressure force
    (energy_spiky): at 0.6 tau_y of basal shear the top stops (-0.013 mm/s at 0.6 s, after
    the plastic transient of the load ramp); at 1.3 tau_y it flows at 7.7 mm/s, 2.1 x the
    continuum Bingham surface speed (3.7 mm/s). With the walls at the faces it widens (1.11 x
    at 1.3 tau_y) and the top has slowed to 1.09 mm/s (0.30 x) by 0.6 s (0.06 mm/s at 0.6
    tau_y); the energy force, which this test ran with before, still flowed there at 7.45
    mm/s (widened 1.26 x). Earlier, with the energy force and the walls at the faces:
    longer runs stopped at 0.9 and flowed at 1.1 tau_y (0.34 against 0.48 mm/s). At 0.6 s
    the speed is not yet the steady one: energy_spiky, centres, 1.1 tau_y: 8.5 mm/s. The 1.3
    tau_y run read here is the next test's, 0.75 s (one run less): at 7cee5e65 its top slides
    at 2.57 / 4.81 mm/s (0.70 / 1.31 x Bingham, biweight / poly6), above the bound's half;
    on the elastic floor (the mutation: a floor that holds) -0.0006 x."""
    _stops_below_and_flows_above("particles", above=held_strip)


def test_the_particle_floor_holds_by_the_yield_stress_not_by_a_friction_coefficient():
    """The test above slides the strip at tan(theta) = 0.23 (1.3 tau_y at a critical angle of
    10 degrees); with tau_y set for 30 degrees the same floor holds it at tan(theta) = 0.44,
    0.8 tau_y. So the floor is no Coulomb wall: what lets the material slide over it is the
    base's shear stress against the yield stress, whatever the normal load (docs/physics.md,
    "The particle floor's friction"). Measured (0.6 s): -0.02 mm/s; the ground collider with
    Coulomb friction 0.3 in its place lets the strip run at 650 mm/s. Held too at 0.9 tau_y
    and tan(theta) 0.82 (45 degrees, 1.0 s); at 1.3 tau_y it slides at 9-15 mm/s at 30 and
    45 degrees (Bingham 3.7)."""
    r = validation.incline(load=0.8, floor="particles", walls="centres", critical_angle=30.0, **THIN_LAYER)
    assert r["finite"]
    assert math.tan(math.radians(r["theta_deg"])) > 0.4, r["theta_deg"]
    # The scale of the test above: the Bingham surface speed at 1.3 tau_y, 3.67 mm/s at any
    # critical angle (the plastic viscosity mu / flow_rate grows with tau_y as the slope does).
    scale = 3.67e-3
    assert abs(r["top_speed"]) < 0.03 * scale, (r["top_speed"], scale)


def test_thin_layer_on_an_elastic_particle_floor_is_held_where_the_plastic_floor_lets_it_flow():
    """``add_particle_floor(elastic=True)``: a floor that does not flow holds the material
    within a support radius of it (two of the strip's three layers at h = 2 dx), so the strip
    that flows on the plastic floor at 1.3 tau_y (test above: 7.7 mm/s, Bingham 3.7) does not
    slide on it. Measured: 0.000 mm/s at 1.3 tau_y (0.004 at 1.1)."""
    held = validation.incline(load=1.3, floor="elastic_particles", walls="centres", **THIN_LAYER)
    assert held["finite"]
    assert abs(held["top_speed"]) < 0.03 * held["bingham_surface_speed"], held["top_speed"]


def test_thin_layer_on_the_ghost_floor_stops_below_and_flows_above_the_shear_yield_stress():
    """``add_particle_floor(ghost=True)``: a no-slip wall that holds no layer, so the strip
    that the elastic floor holds at 1.3 tau_y (test above) flows on it, and at 0.6 tau_y it
    stops. Measured (0.6 s): -0.07 mm/s at 0.6 tau_y; 0.59 / 4.2 / 9.1 mm/s at 0.9 / 1.1 /
    1.3 tau_y (Bingham 0 / 0.48 / 3.67; at 0.9 the short strip's free ends still move it:
    the default 12 h long strip, 0.13 mm/s)."""
    _stops_below_and_flows_above("ghost_particles")


def test_thin_layer_on_a_particle_floor_stops_after_sliding_only_when_it_widens_between_its_walls(held_strip):
    """The layer's flow stops after about one spacing of slip (docs/physics.md, thin layers
    in shear) because the strip widens: its walls normal to z act on particle centres, half a
    spacing outside its outer rows, which move out to them, so the layers close up in y.
    With the walls at the faces the strip widens, its top sinks to 0.81 of its height (1.05
    of its plug thickness) and, after sliding at over 1.7 x the Bingham speed B to 0.5 s, it
    stops: from 9 / 7 mm/s at 0.52 / 0.57 s to under 1 by 0.6 s (poly6 / biweight); with the
    walls through the outer rows' centres it keeps its width and 0.88-0.89 of its height and
    is still sliding then. So the test reads both 0.15 s after that stop, at 0.75 s. Measured
    (Bingham 3.67 mm/s): faces 1.106 / 1.102 x wide, top 0.810 / 0.807, 0.17 / -0.06 mm/s
    (2.4 / 1.7 B at two thirds of the run); centres 0.994 / 0.996 x, 0.893 / 0.880, 4.81 /
    2.57 mm/s (1.31 / 0.70 B), poly6 / biweight. The held strip is not in steady flow: it
    slows from the load ramp's overshoot and its middle thins as its free ends slump: 0.08 /
    0.05 B by 2.0 s (docs/physics.md, "The three-layer strip read longer"; on a floor past
    its ends it comes to rest, the test below). Read at 1.0 s, as this test did, the held
    strip's reading is a point of that slowing down where the weights differ twofold (2.15 /
    0.97 mm/s, 0.58 / 0.26 B), 0.4 s after the widened strip's stop."""
    faces = validation.incline(load=1.3, floor="particles", layers=3, length=8.0, duration=0.75)
    centres = held_strip
    assert faces["finite"] and centres["finite"]
    scale = centres["bingham_surface_speed"]
    assert faces["width_ratio"] > 1.08 and faces["top_height_ratio"] < 0.82, faces
    # It stops after sliding: at two thirds of the run (0.5 s) it was still sliding.
    assert faces["top_speed_two_thirds"] > 0.5 * scale, (faces["top_speed_two_thirds"], scale)
    assert abs(faces["top_speed"]) < 0.1 * scale, (faces["top_speed"], scale)
    assert centres["width_ratio"] == pytest.approx(1.0, abs=0.02), centres["width_ratio"]
    assert centres["top_height_ratio"] > 0.85, centres["top_height_ratio"]
    assert centres["top_speed"] > 0.5 * scale, (centres["top_speed"], scale)


def test_thin_strip_on_a_floor_past_its_ends_comes_to_rest_just_above_its_plug_thickness():
    """The strip of the test above (3 layers, 8 h, 1.3 tau_y, walls through the outer rows'
    centres) on a particle floor that reaches 8 spacings past its ends (``floor_margin=8``: on
    the floor under the strip only, its ends slump off the floor's edges and the middle runs
    in bursts). Its free ends slump, its middle lengthens and thins, and near yield its
    Bingham speed goes as (h - h_p)^2, so the nominal B is no reference for it (docs/physics.md,
    "The three-layer strip read longer"). What a Bingham layer thinning on a slope does is come
    to rest where its basal shear has fallen to the yield stress: its thickness h_eff down to
    the plug thickness h_p = h / 1.3, its thinned Bingham speed B(h_eff) to 0. Measured
    (poly6): the middle runs at 8.7-15.5 x B(h_eff) to 2.35 s, then stops by 2.6 s; at 3.0 s
    0.04 mm/s (B 3.67) at h_eff = 1.057 h_p (B(h_eff) 0.036 B): 6 % of excess shear strength
    at the base, bounded here at 10 %. The biweight: stops at 1.2-1.6 s,
    0.005 mm/s at 3.0 s at 1.087 h_p (0.084 B). With the
    yield stress 10 % higher, at rest at 1.150 h_p (of the nominal h_p); with the viscosity
    doubled, 2.6 mm/s at 3.0 s, still flowing."""
    r = validation.incline(load=1.3, floor="particles", layers=3, length=8.0, duration=3.0, walls="centres",
                           floor_margin=8.0)
    assert r["finite"]
    scale = r["bingham_surface_speed"]
    assert abs(r["top_speed"]) < 0.03 * scale, (r["top_speed"], scale)
    # At rest within 10 % of the plug's basal shear: h_eff < 1.1 h_p, B(h_eff) < 0.11 B.
    assert r["plug_thickness"] < r["thickness"], (r["thickness"], r["plug_thickness"])
    assert r["thinned_bingham_surface_speed"] < 0.11 * scale, (r["thickness"] / r["plug_thickness"], r["thinned_bingham_surface_speed"], scale)


@pytest.mark.parametrize("kwargs, words", [
    ({"floor": "particles", "floor_margin": -1}, r"floor_margin = -1 is not allowed: must be >= 0"),
    ({"floor": "particles", "floor_margin": float("nan")}, r"floor_margin = nan is not allowed: must be a finite number"),
    ({"floor": "particles", "floor_margin": True}, r"floor_margin = True is not allowed: must be a number"),
    ({"floor": "particles", "floor_margin": 2.5}, r"floor_margin = 2.5 is not allowed: must be a whole number of spacings"),
    ({"floor": "particles", "floor_margin": 1e6}, r"floor_margin = 1000000.0 is not allowed: at spacing 0.005 "),
    ({"floor": "ground", "floor_margin": 8}, r"floor_margin = 8 is not allowed with floor = 'ground': "),
    ({"floor": "ground_images", "floor_margin": 8.0}, r"floor_margin = 8.0 is not allowed with floor = 'ground_images': "),
])
def test_incline_refuses_a_floor_margin_it_would_not_build_naming_it(kwargs, words):
    """incline's floor_margin (spacings) is refused by its own name and value: a negative or
    huge one was refused as the builder's margin in metres ('margin = -0.005'), 2.5 reached
    2 spacings (the floor is on the strip's lattice) and True one, and on a ground collider
    any margin was dropped while the result row recorded it."""
    with pytest.raises(ValueError, match="^" + words):
        validation.incline(duration=0.01, **kwargs)


def test_incline_refuses_unknown_walls_by_name():
    with pytest.raises(ValueError, match="walls = 'glass'"):
        validation.incline(walls="glass")


@pytest.mark.parametrize("case", ["incline", "slump", "spread"])
def test_an_unknown_floor_is_refused_by_name(case):
    kwargs = {"S": 0.1} if case == "slump" else {}
    with pytest.raises(ValueError, match="floor = 'sand'"):
        getattr(validation, case)(floor="sand", **kwargs)


@pytest.mark.parametrize("pressure_force", [
    pytest.param("energy", marks=pytest.mark.xfail(
        strict=True, reason="the energy pressure force follows the poly6 gradient, which vanishes as two particles "
        "meet: in the flowing S = 0.1 pile the particles pair up (mean nearest neighbour 0.523 / 0.519 / 0.498 dx at 0.7 / "
        "1.0 / 1.5 s at 6 across, 0.535 at 8, 0.54 dx at rest at 12 across), a packing of pairs that interlocks under "
        "pressure and holds the pile "
        "about 6 % taller than the spiky force or no pressure (docs/physics.md, the S = 0.1 slump under "
        "the energy pressure force)")),
    "spiky",
    "energy_spiky",
])
def test_slump_pressure_keeps_particles_apart(pressure_force):
    """An SPH pressure is a repulsion: the flowed, compressed pile keeps its particles farther
    apart than uncorrelated points of the same number density do (mean nearest neighbour
    0.554 dx). Read at 0.7 s, S = 0.1, 6 across (the suite's size: the pairing is a
    particle-scale effect, the same at 8 across at twice the cost): spiky 0.695 dx, energy
    0.523 dx, energy_spiky 0.814 dx, the pressure off (the mutation) 0.494 dx, failing it; at
    0.5 s spiky 0.678 dx, too near the bound (energy 0.464, energy_spiky 0.773). Measured at 1.0 s,
    the test's reading before (30 % more steps): spiky 0.737 dx, energy
    0.519 dx, energy_spiky (the same energy on a spiky density) 0.800 dx, the pressure off
    0.564 dx (h/H0 0.452, still sinking); at 1.5 s 0.707, 0.498, 0.781 and 0.534 dx; at 8
    across, 1.5 s, 0.717, 0.535 and 0.808 dx (start: the lattice, 1 dx). The particle floor
    under a disc of 2.6 R0, not the default 3.2 (576 particles instead of 760): at 1.0 s the
    piles reach 1.80-1.85 R0, a support radius (0.67 R0) short of it, and read as on the
    larger floor to 4 digits (0.7367, 0.5185, 0.7996, pressure off 0.5636 dx on both)."""
    r = validation.slump(0.1, resolution=6, duration=0.7, pressure_force=pressure_force, floor_radius=2.6)
    assert r["finite"]
    assert r["nearest_neighbor_mean"] > 0.65, r["nearest_neighbor_mean"]


def test_slump_refuses_a_negative_gravity_ramp_by_name():
    with pytest.raises(ValueError, match="gravity_ramp = -1.0"):
        validation.slump(0.1, gravity_ramp=-1.0)


def test_mirror_slump_gives_its_gravity_once_a_step():
    """``slump(floor="mirror")`` gives gravity towards the plane as a velocity kick before each
    step (``validation._Mirror``), so after the first step from rest the upper half's kinetic
    energy is ``M (g dt)^2 / 2`` as on a floor (measured: the particle floor to 2e-7 of it, the
    mirror 1.2 % under it: the SPH viscosity sees the two halves' kicks, ``2 g dt`` apart across
    the plane, one step early). Read after the next step's kick it was 4 times that."""
    model, *_ = validation.slump_model(0.2, 4, floor=validation.MIRROR)
    dt = 0.9 * model.stable_dt()
    r = validation.slump(0.2, resolution=4, floor=validation.MIRROR, duration=3 * dt, samples=3)
    assert r["dt"] == dt
    closed = validation.G * dt**2 / (2.0 * 0.1)  # M (g dt)^2 / 2 over M g H0
    assert 0.98 < r["ke_history"][0] / closed <= 1.0, r["ke_history"][0] / closed


def test_mirror_plane_is_a_frictionless_wall_that_pushes_only_where_the_images_reach():
    """``slump(floor="mirror")``'s plane (``validation._Mirror``) is an exact frictionless wall:
    the upper half of the 4-across S = 0.2 cylinder, lifted a spacing off the plane (its
    images out of reach, 3 dx > h), sheared (F with xy, xz and zy terms) and sliding, falls
    freely, its y-momentum ``p0 - M g t`` to round-off (gravity once a step, nothing from the
    images' mass), then lands, flows (plastic strain past 10 yield strains) and is pushed back
    by its images; through all of it its tangential momentum is kept to round-off (the images'
    pair forces cancel sideways only where their v and F are the mirror's: with F mirrored as
    ``R F`` rather than ``R F R`` it moved by 3e-4 of M u at landing, with F copied 7e-7,
    measured), and no particle crosses the plane."""
    import warp as wp
    import warp_esph as we

    model, upper, mu, Y = validation.slump_model(0.2, 4, floor=validation.MIRROR, dtype=wp.float64)
    n, dx, g = int(upper.sum()), model.spacing, validation.G
    x0 = model.particle_x0.copy()
    x0[:n, 1] += dx
    x0[n:, 1] -= dx
    model.particle_x0 = x0
    rng = np.random.default_rng(7)
    u = np.array([0.05, 0.0, -0.03])
    v = rng.normal(scale=0.02, size=(n, 3)) + u
    v[:, 1] = 0.0
    model.particle_v0 = np.concatenate([v, v * np.array([1.0, -1.0, 1.0])])
    solver, mirror = we.Solver(model), validation._Mirror(model, n)
    a, b = model.state(), model.state()
    F = a.F.numpy()
    F[:n] = np.eye(3) + np.array([[0.0, 0.02, 0.01], [0.0, 0.0, 0.0], [0.01, 0.015, 0.0]])
    a.F.assign(F)
    dt = 0.9 * model.stable_dt()
    m = model.particle_mass.numpy()[:n]
    M = m.sum()

    def momentum(state):
        return (m[:, None] * state.v.numpy()[:n]).sum(axis=0)

    p0 = momentum(a)
    mirror(a, g, dt)
    free_steps = 0
    for k in range(1, 81):
        reached = 2.0 * a.x.numpy()[:n, 1].min() < model.support_radius  # an image within h
        solver.step(a, b, dt)
        a, b = b, a
        p = momentum(a)
        assert np.abs(p - p0)[[0, 2]].max() < 1e-12 * M * np.abs(u).max(), (k, p - p0)
        pushed = (p[1] - p0[1] + M * g * k * dt) / (M * g * dt)  # the images' impulse over M g dt
        if not reached:
            assert abs(pushed) < 1e-10, (k, pushed)
            free_steps += 1
        mirror(a, g, dt)
    assert 30 < free_steps < 60, free_steps
    assert pushed > 10.0, pushed
    assert a.x.numpy()[:n, 1].min() > 0.0
    assert a.alpha.numpy()[:n].max() > 10.0 * Y / (2.0 * mu)  # it flowed: 40 yield strains


@pytest.mark.parametrize("aspect", [0.0, -2.0, float("nan")])
def test_slump_refuses_an_aspect_that_is_not_positive_by_name(aspect):
    with pytest.raises(ValueError, match=f"aspect = {aspect!r}"):
        validation.slump(0.1, aspect=aspect)


@pytest.mark.xfail(strict=True, reason="a layer 3 particles thick on the rough ground collider stops at 1.3 tau_y of "
                   "basal shear (walls through the outer rows' centres, as the other floors' tests: measured 0.007 mm/s "
                   "at 0.6 s, Bingham 3.67; it flows only "
                   "from about 2.5 tau_y, 2.2 at 6 thick): the ground's bottom layer is held and its one-sided fit "
                   "doubles its share (docs/physics.md, \"The ground collider's thin-layer strength\"; "
                   "add_ground(images=True), opt-in so far, flows here at 6.4 mm/s, the test below)")
def test_thin_layer_on_the_rough_ground_flows_above_the_shear_yield_stress():
    r = validation.incline(load=1.3, floor="ground", walls="centres", **THIN_LAYER)
    assert r["finite"]
    assert r["top_speed"] > 0.5 * r["bingham_surface_speed"], (r["top_speed"], r["bingham_surface_speed"])


def test_thin_layer_on_the_ground_with_floor_images_stops_below_and_flows_above_the_shear_yield_stress():
    """``add_ground(images=True)``: the plane's mirror images of the particles near it enter
    their fits, energy and density, so the bottom layer is not held on the plane and its fit
    is an interior one (docs/physics.md, "The ground collider's thin-layer strength").
    Walls through the outer rows' centres (the strip cannot widen, which with the walls at
    the faces stops a layer on either floor after about a spacing of slip). Measured, 3
    through, 8 h long, 0.6 s: at 0.6 tau_y the top stops (0.004 mm/s; particle floor
    -0.013); at 1.3 tau_y it flows at 12.3 mm/s (particle floor 7.74; Bingham 3.67). Before
    the images had their own F (``State.F_image``): -0.081 and 6.39 mm/s. The plain ground
    collider stops at 1.3 and at 2.0 tau_y and creeps at 2.5 (1.6 mm/s against 47.7; 12 h
    long, 1.5 s)."""
    _stops_below_and_flows_above("ground_images")


@pytest.mark.parametrize("fit_weight", ["poly6", "biweight"])
def test_thin_layer_on_the_imaged_ground_rests_below_yield_without_viscosity(fit_weight):
    """The same strip at 0.6 tau_y with no viscosity: the images' energy works on their own
    F (``State.F_image``), so nothing feeds the layer and its top rests: mean speed over the
    last third of 0.6 s 0.004 / -0.004 mm/s (poly6 / biweight), against 3 % of the Bingham
    surface speed at 1.3 tau_y (3.67 mm/s). Before, with each image carrying its particle's F,
    the undamped strip slid at about 5 mm/s (docs/physics.md, "The floor images' energy is not
    stored")."""
    r = validation.incline(load=0.6, floor="ground_images", walls="centres", viscosity=0.0, samples=200,
                           fit_weight=fit_weight, **THIN_LAYER)
    v = np.array(r["speed_history"])
    assert r["finite"]
    assert abs(v[2 * len(v) // 3:].mean()) < 0.03 * 3.67e-3, v[2 * len(v) // 3:].mean()


@pytest.mark.parametrize("label", [label for label, _ in validation._stability_materials()])
def test_no_preset_or_default_material_blows_up_at_half_the_stable_dt(label):
    """Each preset and ``Material(mu=1e5, lam=1e5)`` (paper force, pressure on), with and
    without viscosity, a 6^3 box at rest on the ground for 0.3 s at 0.5 stable_dt: not blown
    up (no particle ever faster than 5 m/s) and no particle faster than 2 m/s (measured: all
    below 1 m/s, the default material too,
    also over 1.5 s; the explosion issue 12 reports for it was not reproduced in this scene)."""
    material = dict(validation._stability_materials())[label]
    r = validation.stability(material, duration=0.3)
    assert not r["blew_up"], r
    assert r["max_speed"] < 2.0, r  # a start of a blow-up shows well before the 5 m/s limit
    # The row says how its run's neighbour rows were chosen: a box at rest keeps its lattice
    # rows (26 within h), far from full.
    assert r["particle_steps"] > 0 and r["full_row_particle_steps"] == 0 and r["neighbors_cut"] == 0, r


def test_a_cases_solver_counts_every_particle_step_whose_neighbour_row_was_full():
    """A result of the suite records its full rows, whose members the search chose: rows 12
    wide in a lattice box, where an interior particle has 26 neighbours within h and a corner
    fewer than 12, are full inside and not at the corners, every step, and the full interior
    rows dropped neighbours of non-zero weight (``neighbors_cut``). The box is elastic, so every
    step ran the rest-configuration model (``rest_model_steps``)."""
    import warnings

    import warp_esph as we

    b = we.SceneBuilder(spacing=0.02, max_neighbors=12)
    b.add_box((0.0, 0.0, 0.0), (0.1, 0.1, 0.1), we.Material(mu=1e5, lam=1e5))
    model = b.finalize()
    solver = validation._solver(model)
    a, c = model.state(), model.state()
    full = 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # the cut rows' warning: counted below
        for _ in range(3):
            solver.step(a, c, 1e-4)
            a, c = c, a
            full += int((a.neighbor_count.numpy() == 12).sum())
    fields = validation._row_fields(solver)
    assert fields == {"neighbors_cut": solver.guard_counts()["neighbors_cut"], "full_row_particle_steps": full,
                      "particle_steps": 3 * model.particle_count, "rest_model_steps": 3}, fields
    assert 0 < full < 3 * model.particle_count and fields["neighbors_cut"] > 0, fields


@pytest.fixture(scope="module")
def near_yield4(run_once):
    # The yield-off reference over 4 of its axial periods, not the default 8: it is relaxed by
    # then (its shortening the same to 2e-6 of itself at 3, 4, 6 and 8 periods).
    return run_once("validation-near_yield4", lambda: validation.near_yield_column(resolution=4, periods=20.0,
                                                                                    elastic_periods=4.0))


def test_near_yield_column_holds_with_only_its_bottom_yielding(near_yield4):
    """The near-yield column (uniaxial yield stress the weight above 0.8 L), 4 across, 5 x
    as tall, the default SPH pressure, gravity ramped, 20 axial periods. Measured: at rest
    (kinetic energy 1.6e-9 M g x the theory's shortening, top 0.41 % of it per s; at 24
    periods 2.5e-10 and 0.10 %; with the yield surface at 0.9 Y still 2.9e-6 at 20); the
    yield front 0.775 L deep (6 / 8 across: 0.717 / 0.69 L; the 1-D analysis: 0.8 L; bound:
    one width above it, where the base's spreading, which drags the layers above outward,
    may reach by Saint-Venant); the unyielded part 0.1-0.5 L deep peaked at 0.999 x the
    uniaxial stress of its weight over sigma_y (6 across: 1.009); nearest neighbours 0.97
    dx apart (without the pressure, at 6 / 8 across, they pair in the yielded base and the
    core collapses: docs/physics.md, "The near-yield column"). Its plastic shortening (total
    less the same column's with the yield off) is 0.064 x the 1-D analysis's (0.066 at 20 and
    24 periods at 5465965; 6 across:
    0.29), whose layers spread freely: the bottom layer on the ground collider, fitted
    one-sided, keeps about half the weight's stress in its F, never yields and holds the
    base in, less so as the spacing falls; so only the bracket is asserted: more than the
    elastic column, no more than free 1-D spreading."""
    r = near_yield4
    assert r["kinetic_over_weight"] < 1e-8, r
    assert abs(r["residual_rate_pct_per_s"]) < 1.0, r
    assert r["highest_yielded_depth"] >= r["yield_depth"] - 1.0 / 5.0, r
    assert r["upper_peak_over_weight"] == pytest.approx(1.0, abs=0.05), r
    assert r["nearest_neighbour_min"] > 0.5, r
    assert 0.0 < r["plastic_over_theory"] <= 1.0, r


@pytest.mark.xfail(strict=True, reason="near-yield column, 4 across: plastic shortening 0.064 x the 1-D analysis's "
                   "free spreading (6 / 8 across: 0.29 / 0.55; the continuum MPM's: 1.03 / 0.96 / 0.99 / 0.94 at 4 / 6 / "
                   "9 / 12 cells across); the ground collider's bottom layer, fitted one-sided, ties the base in "
                   "(on the slip ghost floor, fitted two-sided, before its rim fix: 0.44 / 0.61 / 0.82 / 0.90 / 1.01 at 4 / 6 / 8 / "
                   "10 / 12 across, columns that grow with n and buckle from 8 across; one 4 cm column after it, 4 / 6 / 8 "
                   "across: 0.42 / 0.49 / 0.54, still creeping; docs/physics.md, 'The near-yield column', 'The near-yield column at a fixed width')")
def test_near_yield_column_base_spreads_as_the_1d_analysis(near_yield4):
    assert near_yield4["plastic_over_theory"] == pytest.approx(1.0, abs=0.2), near_yield4


def test_near_yield_column_at_a_fixed_width_keeps_its_size_and_holds_its_top():
    """``width`` fixes the column and sets the spacing: at dx = 0.01 m the column grew with the
    resolution (n cm across, 5n cm tall) and was past Greenhill's self-weight buckling length
    from 8 across. A column 6 cm wide at 4 across has dx = 1.5 cm and is 30 cm tall, 0.91 of
    that length (E 1.5e5, rho 1000: 33.0 cm, closed form); a short run (gravity ramped over
    one axial period, three more) holds its top (shortens by less than twice the 1-D
    analysis's elastic and plastic shortening: no core collapse) and yields only near its base."""
    r = validation.near_yield_column(resolution=4, width=0.06, ramp=1.0, periods=4.0, elastic_periods=1.0)
    assert r["width"] == 0.06 and r["particles"] == 4 * 4 * 20, r
    assert r["dx"] == pytest.approx(0.015) and r["height"] == pytest.approx(0.30), r
    assert r["length_over_buckling"] == pytest.approx(0.30 / 0.3301, rel=2e-3), r
    assert r["highest_yielded_depth"] >= r["yield_depth"] - 1.0 / 5.0, r
    assert 0.0 < r["plastic_over_theory"] <= 1.0, r
    assert abs(r["shortening"]) < r["theory"] * 2.0, r


def test_near_yield_column_passes_its_fit_weight_to_the_column_and_its_elastic_reference(monkeypatch):
    """``fit_weight`` reaches the model of the plastic run and of the yield-off reference whose
    shortening it subtracts (a reference with the other weight would leave its elastic
    difference in the plastic part), and the row records the model's. The weight given is not
    the default's: given the default (the biweight, since 2026-12-06), a call that dropped it
    would build the same models."""
    built = []
    free_column = validation._free_column

    def recording(*args, **kwargs):
        out = free_column(*args, **kwargs)
        built.append(out[0].fit_weight)
        return out

    monkeypatch.setattr(validation, "_free_column", recording)
    r = validation.near_yield_column(resolution=4, width=0.06, ramp=0.5, periods=1.0, elastic_periods=0.5,
                                     floor="slip_ghost_particles", fit_weight=OTHER_WEIGHT)
    assert built == [OTHER_WEIGHT, OTHER_WEIGHT] and r["fit_weight"] == OTHER_WEIGHT, (built, r.get("fit_weight"))


def test_near_yield_column_on_the_tresca_ground_holds_its_elastic_reference_to_the_same_stress(monkeypatch):
    """On the Tresca ground (``floor=TRESCA``) the plastic column's base is held up to its shear
    yield stress, ``Y / sqrt(2)``; its elastic reference, whose material never yields, is held up
    to the same stress in Pa (the continuum's elastic twin keeps its cap in Pa), not refused for
    having no yield stress and not held by a yield stress of its own. Both columns stand on the
    ground at the box's face (the bottom layer's centres half a spacing over it, their images
    half a spacing under it: the lattice continued)."""
    built = []
    free_column = validation._free_column

    def recording(*args, **kwargs):
        out = free_column(*args, **kwargs)
        built.append(out)
        return out

    monkeypatch.setattr(validation, "_free_column", recording)
    r = validation.near_yield_column(resolution=4, width=0.04, ramp=0.5, periods=1.0, elastic_periods=0.5,
                                     floor=validation.TRESCA)
    assert r["floor"] == validation.TRESCA and len(built) == 2, r
    plastic, elastic = (out[0] for out in built)
    Y = plastic.materials[0].yield_stress
    assert Y == pytest.approx(math.sqrt(2.0 / 3.0) * validation.RHO * validation.G * 0.8 * 0.2, rel=1e-12)
    assert plastic.shear_cap == 1.0
    hold = elastic.shear_cap * elastic.materials[0].shear_yield_stress
    assert hold == pytest.approx(Y / math.sqrt(2.0), rel=1e-9), hold
    # The reference's yield stress is far above the weight's stress at its base: it never flows.
    assert elastic.materials[0].yield_stress > 1e5 * validation.RHO * validation.G * 0.2
    for model, *_ in built:
        (plane,) = [p for p in model.planes if p.images]
        assert plane.offset == 0.0 and model.particle_x0[:, 1].min() == pytest.approx(0.005, rel=1e-6)


def test_column_settlement_on_the_tresca_ground_shortens_as_the_closed_form():
    """The elastic column (4 across, pressure off) on the Tresca ground, held up to a stress of
    the near-yield column's order (900 Pa) by its never-reached yield stress: at rest and
    shortened as ``rho g L (L - dx) / (2 E)`` within 5 %, as on the frictionless ground; its
    base, fitted two-sided against the images, neither sinks nor is pulled in."""
    r = validation.column_settlement(resolution=4, floor=validation.TRESCA, shear_cap_pa=900.0)
    assert abs(r["residual_rate_pct_per_s"]) < 0.2, r
    assert r["ratio"] == pytest.approx(1.0, abs=0.05), r


@pytest.mark.parametrize("floor, cap, said", [
    ("tresca_images", None, r"^shear_cap_pa = None is not allowed with floor = 'tresca_images': the elastic column"),
    ("tresca_images", -1.0, r"^shear_cap_pa = -1\.0 is not allowed: must be > 0"),
    ("tresca_images", float("nan"), r"^shear_cap_pa = nan is not allowed"),
    ("ground", 900.0, r"^shear_cap_pa = 900\.0 is not allowed with floor = 'ground': it is the Tresca ground's hold"),
    # Above the column's Young's modulus: before, 1e300 was taken and its twin's yield stress
    # left float32's range, refused only at the build under another name.
    ("tresca_images", 1e300, r"^shear_cap_pa = 1e\+300 is not allowed: must be in \(0, E\] = \(0, [0-9.e+]+\] Pa"),
])
def test_column_settlement_refuses_a_tresca_hold_that_is_missing_or_misplaced(floor, cap, said, monkeypatch):
    """The Tresca ground's hold in Pa is required there (an elastic material has no shear yield
    stress to scale it) and refused on another floor, by name, before a column is built."""
    monkeypatch.setattr(validation, "_free_column", lambda *a, **k: pytest.fail("the column was built"))
    with pytest.raises(ValueError, match=said):
        validation.column_settlement(resolution=4, floor=floor, shear_cap_pa=cap)


@pytest.mark.parametrize("fit_weight", ["gauss", "Biweight", None])
def test_near_yield_column_refuses_an_unknown_fit_weight_by_name(fit_weight):
    """A weight that is not one of the fit's is refused by name, with the allowed ones, before
    the column runs (a misspelt one must not fall back to a default and record its row)."""
    with pytest.raises(ValueError, match=rf"^fit_weight = {fit_weight!r} is not allowed: must be one of 'poly6', 'biweight'"):
        validation.near_yield_column(resolution=4, width=0.04, floor="slip_ghost_particles", ramp=0.5, periods=0.5,
                                     elastic_periods=0.05, fit_weight=fit_weight)


def test_the_fixed_width_near_yield_study_stays_short_of_buckling_at_every_resolution():
    """The plan's fixed-width near-yield runs: one column (``NEAR_YIELD_WIDTH`` wide, 5 x as
    tall) at 4, 6 and 8 across on both floors, its height 0.79 of the buckling length (closed
    form: 0.2 m against 0.2519 m), so its resolutions resolve one column that stands."""
    runs = validation.select(validation.plan(False), f"near_yield_column:width={validation.NEAR_YIELD_WIDTH}")
    assert sorted((k["floor"], k["resolution"], (validation.PLAN_DEFAULTS | k)["fit_weight"]) for _, k in runs) == sorted(
        (f, n, w) for f in ("ground", "slip_ghost_particles") for n in (4, 6, 8) for w in ("biweight", "poly6"))
    for _, k in runs:
        dx = validation.column_spacing(k["resolution"], k["width"])
        assert dx * k["resolution"] == pytest.approx(0.04)
        assert 5 * k["resolution"] * dx / validation.column_buckling_length(1.5e5, k["resolution"] * dx) == \
            pytest.approx(0.2 / 0.2519, rel=2e-3)
    # Without a width the spacing stays 1 cm: the rows measured so stay as they were.
    assert validation.column_spacing(8, None) == 0.01


def _near_yield_row(n, plastic, floor="slip_ghost_particles", lean=1e-6, rate=0.05, front=0.775):
    return {"case": "near_yield_column", "resolution": n, "width": 0.04, "height": 0.2, "floor": floor,
            "elastic_force": "variational", "dtype": "float32", "tilt": 0.0, "length_over_buckling": 0.794,
            "yield_depth": 0.8, "plastic_over_theory": plastic, "highest_yielded_depth": front,
            "upper_peak_over_weight": 1.0, "residual_rate_pct_per_s": rate, "kinetic_over_weight": 1e-10,
            "lean": lean, "shortening": 0.005, "theory": 0.0054, "theory_plastic": 0.0041, "duration": 2.35, "run": 0}


def test_the_near_yield_target_judges_the_fixed_width_study_per_floor():
    """The report's near-yield row reads the fixed-width rows (with a ``width``): the finest
    resolution's plastic shortening against the 1-D analysis (10 %), its convergence over the
    last three, a lean past a spacing or a yield front more than a width above the 1-D depth as
    not holding, and a top whose creep would move the plastic shortening by 1 % of the
    analysis's over another run as not at rest; the dx = 0.01 m columns, which grow with the
    resolution, are said apart (in the row of the weight they ran, ``NEAR_YIELD_GROWING_WEIGHT``;
    a row without a ``fit_weight`` ran poly6)."""
    from benchmarks.validation_report import NEAR_YIELD_GROWING_WEIGHT, NEAR_YIELD_TARGET, _near_yield_target

    rows = [_near_yield_row(4, 0.44), _near_yield_row(6, 0.80), _near_yield_row(8, 0.95),
            _near_yield_row(4, 0.06, "ground", front=0.5), _near_yield_row(6, 0.30, "ground", lean=2.0, rate=1.0)]
    (target, measured, met, runs), = _near_yield_target(rows, NEAR_YIELD_GROWING_WEIGHT)
    assert target.startswith(NEAR_YIELD_TARGET) and runs == "R1"
    slip, ground, growing = met.split("; on ")[0], met.split("; on ")[1], met.split("; at dx")[1]
    assert slip.startswith("on the slip ghost floor (fixed width): holds, base only yielding (within a width): yes"), met
    assert "within 10 % at 8 across: yes (0.95 x); converging: yes" in slip and "at rest" not in slip, met
    assert ground.startswith("the ground collider (fixed width): holds, base only yielding (within a width): no"), met
    assert "within 10 % at 6 across: no (0.30 x)" in ground and "converging: not shown (only 4 / 6 across" in ground, met
    assert "at rest: not at 6 across" in ground and "not a resolution study" in measured, (ground, measured)
    assert growing.startswith(" = 0.01 m"), met
    assert "at 4 / 6 / 8 across: plastic shortening 0.44 / 0.80 / 0.95 x" in measured, measured
    # The growing columns on the slip ghost floor predate its rim fix: said so, and the floor's
    # rows after it are the fixed-width ones, read from the rows (they quoted the old columns alone).
    assert "on the slip ghost floor, which fits the bottom layer two-sided, before its rim fix" in measured, measured
    assert measured.endswith("; after it measured at a fixed width of 4 cm alone (R1): 0.44 / 0.80 / 0.95 x at 4 / 6 / 8 "
                             "across)"), measured
    assert met.endswith("on the slip ghost floor before its rim fix: within 10 % at 10 and 12 across, columns at and "
                        "past their buckling length; at rest: not at 12 across; after it measured at a fixed width of 4 "
                        "cm alone: 0.95 x at 8 across)"), met
    # Without fixed-width rows only the growing columns' verdict stands, with nothing after the fix.
    (_, measured, met, _), = _near_yield_target([], NEAR_YIELD_GROWING_WEIGHT)
    assert met.startswith("at dx = 0.01 m: holds") and "after it" not in measured + met, (measured, met)


def test_the_near_yield_target_reads_each_fit_weight_on_its_own():
    """A column of the other fit weight at a resolution the default's also has (the 8-across
    row of each) is a target row of its own, after the default's and named for its weight; the
    dx = 0.01 m part stays with poly6's row, which ran it; the default's verdict reads its own
    rows alone (the two 8-across rows together were refused as resolutions not increasing)."""
    from benchmarks.validation_report import NEAR_YIELD_GROWING_WEIGHT, NEAR_YIELD_TARGET, WEIGHT_NAMES, _targets

    rows = [dict(_near_yield_row(n, q), fit_weight=DEFAULT_WEIGHT) for n, q in ((4, 0.44), (6, 0.53), (8, 0.62))]
    rows.append(dict(_near_yield_row(8, 0.56), fit_weight=OTHER_WEIGHT, run=1))
    other = NEAR_YIELD_TARGET + f", with {WEIGHT_NAMES[OTHER_WEIGHT]} fit weight"
    near = [t for t in _targets(rows) if t[0].startswith(NEAR_YIELD_TARGET)]
    assert [t[0] for t in near] == [NEAR_YIELD_TARGET, other], near
    assert "within 10 % at 8 across: no (0.62 x)" in near[0][2] and "within 10 % at 8 across: no (0.56 x)" in near[1][2]
    for t, weight in zip(near, (DEFAULT_WEIGHT, OTHER_WEIGHT)):
        assert ("at dx = 0.01 m" in t[2]) == (weight == NEAR_YIELD_GROWING_WEIGHT), t
    assert "only 8 across measured" in near[1][2] and near[1][3] == "R2", near[1]
    # No row of the other weight: no target of it, unless it holds the dx = 0.01 m part.
    assert [t[0] for t in _targets(rows[:3]) if t[0].startswith(NEAR_YIELD_TARGET)] == [NEAR_YIELD_TARGET] + (
        [other] if OTHER_WEIGHT == NEAR_YIELD_GROWING_WEIGHT else [])


def _continuum_column(res, plastic, width=0.04, floor="Tresca 1 tau_y", duration=2.3517):
    return {"case": "near_yield_column", "res_cells_across": res, "width": width, "floor": floor, "duration": duration,
            "plastic_over_theory": plastic}


def test_the_near_yield_target_reads_the_tresca_ground_as_its_own_part():
    """The fixed-width columns on the Tresca ground (``floor=TRESCA``) are a part of the
    near-yield row of their own, after the slip ghost floor's, judged as every floor's against
    the 1-D free spreading; the continuum's column on a Tresca base (``docs/mpm_slump.json``'s
    checks, floor "Tresca 1 tau_y") is named beside it at the rows' width and duration alone (not
    the 6 cm column, not one run on to rest, not the slip floor's), and nothing is named where the
    continuum was not run."""
    from benchmarks.validation_report import NEAR_YIELD_TARGET, _targets

    slip = [dict(_near_yield_row(n, q), fit_weight=DEFAULT_WEIGHT) for n, q in ((4, 0.42), (6, 0.49), (8, 0.54))]
    tresca = [dict(_near_yield_row(n, q, validation.TRESCA, front=0.725), fit_weight=DEFAULT_WEIGHT, run=1)
              for n, q in ((4, 0.22), (6, 0.31), (8, 0.93))]
    mpm = {"checks": [_continuum_column(6, 0.61), _continuum_column(4, 0.66), _continuum_column(4, 0.653, width=0.06),
                      _continuum_column(4, 0.70, duration=7.05), _continuum_column(4, 0.96, floor="slip")]}
    (target, measured, met, runs), = [t for t in _targets(slip + tresca, mpm) if t[0] == NEAR_YIELD_TARGET]
    assert runs == "R1, R2", runs
    parts = measured.split("; fixed width ")
    assert "on the slip ghost floor" in parts[0] and "Tresca" not in parts[0], measured
    on_tresca = [p for p in parts if "on the Tresca ground" in p]
    assert len(on_tresca) == 1 and "at 4 / 6 / 8 across: plastic shortening 0.22 / 0.31 / 0.93 x the 1-D analysis's free " \
        "spreading, yield front 0.725 / 0.725 / 0.725 L deep" in on_tresca[0], measured
    assert on_tresca[0].endswith(" (the Tresca continuum's column, MPM on a base gripping up to the shear yield stress, "
                                 "as wide and as long: 0.66 / 0.61 x at 4 / 6 cells across)"), on_tresca[0]
    verdict = met.split("; on the Tresca ground (fixed width): ")
    assert len(verdict) == 2 and "0.54 x" in verdict[0], met
    assert verdict[1].startswith("holds, base only yielding (within a width): yes; the 1-D spreading within 10 % at 8 "
                                 "across: yes (0.93 x); converging:"), met
    # Without the continuum's Tresca column at this width, nothing is named beside it.
    (_, measured, met2, _), = [t for t in _targets(slip + tresca, {"checks": mpm["checks"][2:]}) if t[0] == NEAR_YIELD_TARGET]
    assert "Tresca continuum" not in measured and met2 == met, measured
    assert "Tresca continuum" not in [t for t in _targets(slip + tresca) if t[0] == NEAR_YIELD_TARGET][0][1]


def test_the_near_yield_target_does_not_judge_convergence_on_columns_still_creeping():
    """R100's three Tresca readings (0.223 / 0.343 / 0.405 x after 36 periods, the top still
    moving 1.0 / 2.4 / 3.7 % of the theory's shortening per s) fit a law of order 0.9 with a
    limit 0.62 x, but each is a lower bound of where its column rests (the 4- and 6-across ones
    rest at 0.227 / 0.358 x): the verdict names the resolutions not at rest in place of a
    convergence, and counts as not met; the same readings at rest are judged converging."""
    from benchmarks.validation_report import NEAR_YIELD_TARGET, _targets, _unmet

    def rows(rates):
        return [dict(_near_yield_row(n, q, validation.TRESCA, rate=rate, front=0.72), fit_weight=DEFAULT_WEIGHT)
                for n, q, rate in zip((4, 6, 8), (0.2229, 0.3431, 0.4053), rates)]

    def verdict(rates):
        (_, _, met, _), = [t for t in _targets(rows(rates)) if t[0] == NEAR_YIELD_TARGET]
        return met.split("on the Tresca ground (fixed width): ")[1]

    creeping = verdict((1.03, 2.37, 3.67))
    assert "; converging: not judged (not at rest at 4 / 6 / 8 across: lower bounds); at rest: not at 4 / 6 / 8 " \
        "across" in creeping and "order" not in creeping, creeping
    assert _unmet("holds: yes; converging: not judged (not at rest at 8 across: lower bounds)")
    # The finest alone still moving is enough: the fit's last point is a lower bound.
    assert "converging: not judged (not at rest at 8 across" in verdict((0.05, 0.05, 3.67))
    at_rest = verdict((0.05, 0.05, 0.05))
    assert "; converging: yes (order 0.9, limit 0.62 x)" in at_rest and "at rest" not in at_rest, at_rest


def test_the_near_yield_target_reads_one_study_per_floor_leaving_a_column_run_on_or_of_another_width_apart():
    """A floor's rows of one resolution study alone are judged: as wide and run as long as its
    finest resolution's (the plan's 36 periods). A 4-across column run on to 108 periods (it
    reads more: R100's rests at 0.227 x against 0.223) or 6 cm wide is named apart, with its
    run, and neither enters the shortening list, the convergence nor the continuum's match."""
    from benchmarks.validation_report import NEAR_YIELD_TARGET, _targets

    study = [dict(_near_yield_row(n, q, validation.TRESCA, front=0.72), fit_weight=DEFAULT_WEIGHT)
             for n, q in ((4, 0.22), (6, 0.34), (8, 0.41))]
    run_on = dict(_near_yield_row(4, 0.23, validation.TRESCA, front=0.72), fit_weight=DEFAULT_WEIGHT, duration=7.05,
                  run=4)
    wide = dict(_near_yield_row(8, 0.95, validation.TRESCA, front=0.72), fit_weight=DEFAULT_WEIGHT, width=0.06, run=5)
    mpm = {"checks": [_continuum_column(4, 0.58, duration=2.35), _continuum_column(4, 0.70, duration=7.05)]}

    def target(rows):
        (t,) = [t for t in _targets(rows, mpm) if t[0] == NEAR_YIELD_TARGET]
        return t

    _, alone, met, runs = target(study)
    _, measured, met_with, runs_with = target(study[:1] + [run_on] + study[1:] + [wide])
    assert met_with == met and runs == "R1" and runs_with == "R1, R5, R6", (met, met_with, runs_with)
    assert measured == alone.removesuffix(")") + ") (apart, not read with these: 4 across, 4 cm wide, 7.05 s: 0.23 x, " \
        "R5, 8 across, 6 cm wide, 2.35 s: 0.95 x, R6)", measured
    assert "at 4 / 6 / 8 across: plastic shortening 0.22 / 0.34 / 0.41 x" in measured and "0.58 x at 4 cells" in alone


@pytest.mark.parametrize("width", [0.0, -0.04, float("nan"), "4 cm"])
def test_near_yield_column_refuses_a_width_that_is_not_a_positive_length(width):
    with pytest.raises(ValueError, match=r"^width = .* is not allowed: must be"):
        validation.near_yield_column(resolution=4, width=width)


# ------------------------------------------------------------- lab tests with tools
def test_plate_compression_force_and_lateral_strain_within_10_percent_at_8_across():
    """Frictionless plane tools, 1 % strain: measured force 1.089 x E A eps and lateral
    strain 0.955 x nu eps at 8 across (4 across: 1.227 and 0.917), docs/validation.md, R62, on
    the rest model the default runs with tools, the block's elastic material taking the
    corotated stress (with eq. 9's stress: 1.078, 0.955 and 1.214, 0.917, R61; on the
    incremental composition, which it ran with tools before: 1.080, 0.956 and 1.218, 0.920,
    R56). R77, kinetic damping stopping the particles at ``v = -dt a / 2`` where R62 zeroed the
    velocities: the same to three digits but the 4-across lateral 0.916."""
    r = validation.plate_compression(resolution=8)
    assert r["force_ratio"] == pytest.approx(1.0, abs=0.10), r["force_ratio"]
    assert r["lateral_ratio"] == pytest.approx(1.0, abs=0.10), r["lateral_ratio"]


def test_uniaxial_flow_between_frictionless_plates_yields_at_the_uniaxial_yield_stress():
    """The slump material's S = sigma_y / (rho g H0) rests on sigma_y = sqrt(3/2) Y being the
    uniaxial yield stress of the |s| <= Y criterion. Squeezed 2 % (about 2.6 yield strains)
    between frictionless plates, pressure off, 6 across: the interior's elastic deviator
    along the uniaxial pattern measured 0.987 sigma_y (|s|/Y per particle 0.975), the plates'
    stress 1.111 sigma_y (their contact excess, 1.08-1.22 in the elastic plate test above).
    A criterion on another norm would put it at 0.82 or 1.22."""
    r = validation.plastic_compression(resolution=6, squeeze=0.02, pressure_stiffness=0.0)
    assert r["kinetic_energy"] < 1e-9, r
    assert r["interior_axial_over_sigma_y"] == pytest.approx(1.0, abs=0.03), r
    assert 1.0 <= r["stress_over_sigma_y"] <= 1.15, r


@pytest.fixture(scope="module")
def squeezed(run_once):
    """The cube 8 across squeezed at a constant plate speed to 0.6 of the plates' span in 2.0 s
    (log strain 0.92), the default fit weight: the moderate-strain test reads its rows to log
    strain 0.5 and, where the default is the biweight, the biweight's test those from 0.65 on.
    One run where each ran its own: the moderate test's stopped at 0.45 of the span in 1.5 s,
    the same plate speed, so its rows are this run's first ones (averaged over steps // 40 of
    this run's steps, not of that one's)."""
    return run_once("validation-squeezed", lambda: validation.uniaxial_flow(resolution=8, strain=0.6, duration=2.0))


def test_sustained_uniaxial_flow_carries_the_bingham_stress_to_moderate_strain(squeezed):
    """The flow rule's rate term in extension: a cube squeezed at a constant plate speed to
    0.6 of the plates' span in 2 s (log strain 0.92) carries, by the mean stress theorem,
    sigma_y + 3 (mu / flow_rate) strain rate. Measured 6 across with poly6: 0.96-1.15 of it
    for log strains 0.05-0.5, the interior particles' coherent elastic stress 1.23-1.27
    sigma_y against a Bingham 1.24-1.37. Beyond that, at 8 and 12 across, the body carries only 0.64-0.74 of
    it (docs/physics.md, "The flow stress in sustained uniaxial flow"); this test holds the
    moderate range, so it reads the squeeze at that plate speed only to log strain 0.5 (the
    ``squeezed`` run's rows; 0.45 of the span in 1.5 s, log strain 0.60, when it ran on its
    own, which the numbers below were measured on). It runs 8 across: in the band the squeezed, not yet rearranged lattice
    carries more than Bingham (the pressure resists the flattened packing), and at 6 across,
    2-3 layers from the plates, that excess is the coarse lattice's and the weight's: at 6 /
    8 / 10 across poly6 0.973-1.149 / 0.977-1.183 / 0.981-1.187, the biweight 0.972-1.367 /
    0.976-1.230 / 0.980-1.210 (the excess near 1.2 from 8 across with either weight). With
    the plastic viscosity halved (flow rate 400 /s, the mutation) at 8 across 0.883-1.043
    (poly6) and 0.883-1.087 (biweight), failing it. Read from the ``squeezed`` run (biweight):
    23 rows, 0.977-1.229; the mutation 0.884-1.086, failing it."""
    r = squeezed
    rows = [h for h in r["history"] if 0.05 <= h["log_strain"] <= 0.5]
    assert len(rows) >= 15, r["history"]
    ratios = [h["stress_over_sigma_y"] / h["bingham_over_sigma_y"] for h in rows]
    assert 0.9 < min(ratios) and max(ratios) < 1.25, ratios
    # The rate term is there: the Bingham stress grows with the strain rate (1/gap) and so must
    # the body's, by more than a rate-independent material's would (flat at sigma_y).
    assert rows[-1]["bingham_over_sigma_y"] > 1.3 and rows[-1]["stress_over_sigma_y"] > 1.3, rows[-1]


def test_biweight_fit_keeps_the_flow_stress_through_the_particles_rearrangement(squeezed):
    """With the paper's poly6 fit weight the cube 8 across carries 0.66-0.71 of the Bingham
    stress from log strain 0.65 on (R18 in docs/validation.md); with the biweight
    (``SceneBuilder(fit_weight="biweight")``) 0.83-0.93 to log strain 1.0 (R26; 16 across
    0.87-0.94, the MPM 0.91-0.96). The same cube squeezed to log strain 0.92 in 2.0 s, the
    moderate-strain test's plate speed (the plan's takes 3.2 s): measured 0.842-0.906 from
    0.65 on (0.835-0.930 in 3.2 s); with poly6 in the biweight's place (the mutation)
    0.711-0.745, failing it. The run is ``squeezed`` where the biweight is the default."""
    r = squeezed if squeezed["fit_weight"] == "biweight" else validation.uniaxial_flow(
        resolution=8, strain=0.6, duration=2.0, fit_weight="biweight")
    assert r["fit_weight"] == "biweight"
    ratios = [h["stress_over_sigma_y"] / h["bingham_over_sigma_y"] for h in r["history"] if 0.65 <= h["log_strain"]]
    assert len(ratios) >= 8, r["history"]
    assert 0.78 < min(ratios) and max(ratios) < 1.0, ratios


def test_the_validation_plan_names_the_solvers_fit_weights_and_runs_its_default():
    """The suite reads the solver's weights and default without importing Warp (a fresh
    interpreter that imports it has no ``warp`` module): the very objects the kernels' module
    ``smoothing`` reads; a case run without a ``fit_weight``, and a plan entry without one, run
    ``DEFAULT_FIT_WEIGHT``."""
    import inspect
    import subprocess

    from warp_esph.sim.smoothing import DEFAULT_FIT_WEIGHT, FIT_WEIGHTS

    loaded = subprocess.run([sys.executable, "-c", "import sys, benchmarks.validation; print('warp' in sys.modules)"],
                            cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert loaded.stdout.strip() == "False", (loaded.stdout, loaded.stderr[-2000:])
    assert validation.FIT_WEIGHTS is FIT_WEIGHTS and validation.DEFAULT_FIT_WEIGHT is DEFAULT_FIT_WEIGHT
    assert validation.PLAN_DEFAULTS == {"fit_weight": DEFAULT_FIT_WEIGHT}
    for name in validation.RESULT_CASES:
        default = inspect.signature(getattr(validation, name)).parameters["fit_weight"].default
        assert default == DEFAULT_FIT_WEIGHT, (name, default)


@pytest.fixture(scope="module")
def bent(run_once):
    """Held 0.2 s (the benchmark's 0.5 s reads the same stiffness to 1e-5: measured 0.7371 at
    0.2, 0.25 and 0.5 s), averaged over the last 0.1 s."""
    return run_once("validation-bent", lambda: validation.three_point_bending(resolution=4, hold=0.2))


def test_three_point_bending_is_soft_at_4_across(bent):
    """Held 0.2 s with mass-proportional damping and ``Solver(hourglass=0.1)``, measured: mid-span
    stiffness 0.737 x Timoshenko (0.640 x 48 E I / L^3) at 4 across (0.737 held 0.5 s) (0.724 while the contact
    bounced through its margin on the tools, docs/tools.md; 0.726 where docs/physics.md
    measured it, float64 then 0.725; 0.699 before F's round-off was
    carried, docs/physics.md, "Three-point bending in float32"),
    0.921 x at 8 across (docs/validation.md, R43; 0.848 x while the contact bounced): soft, as
    the linear fit's beams are at these thicknesses, approaching the theory with resolution."""
    r = bent
    assert 0.6 < r["ratio"] < 0.8, r["ratio"]
    assert r["ratio_euler_bernoulli"] < r["ratio"]  # the shear term makes the beam softer in theory
    assert r["deflection"] == pytest.approx(r["pin_travel"], rel=0.1)  # little local indentation


def test_three_point_bending_supports_carry_the_pin_load_in_a_static_state(bent):
    """Static equilibrium: over the last 0.1 s of the 0.2 s hold the supports carry the pin's
    load to 1e-3 (measured: 1.00010 x; held 0.25 / 0.5 s to 1e-5; held 0.15 s 1.0014 x, not yet
    static; 1.000 x at 8 across, docs/validation.md, R43) and the deflection changes by less
    than 1e-3 of itself per s (measured: 3.2e-5 held 0.2 s, 0.9e-6 held 0.25 s). With the
    hold's mass-proportional damping halved (the mutation) the supports carry 1.0016 x held
    0.2 s and fail it (1.00024 x held 0.25 s, which passed). While a particle the tools put the
    contact's margin outside was not touching them the next step, the contact bounced through
    the margin: the supports carried 0.988 x (0.986 x before the inside test had the margin)
    and the deflection crept 6.5 % of itself per s (1.2 %), which docs/validation.md read as
    the incremental deformation model's creep (docs/tools.md). Kinetic damping instead of the
    mass-proportional one let a motion at the free ends grow until contact was lost."""
    assert bent["support_force"] == pytest.approx(bent["force"], rel=1e-3), (bent["support_force"], bent["force"])
    assert abs(bent["creep"]) < 1e-3, bent["creep"]


@pytest.fixture(scope="module")
def indented(run_once):
    """8 across, the default solver: for this elastic block the curvature-corrected fit with
    the hourglass control at 0.05 (docs/physics.md, "The default: the fit by material"), on
    the rest model, the tools notwithstanding. Held 0.02 s at the deepest (``late``; 0.05 s
    and the benchmark's 0.1 s read the same: next tests)."""
    return run_once("validation-indented", lambda: validation.sphere_indentation(resolution=8, late=0.02))


def test_sphere_indentation_at_2_mm_within_10_percent_of_the_bonded_layer(indented):
    """The 4 cm block on its held base is a layer bonded to a rigid base, not a half-space:
    at 2 mm (contact radius 1.8 dx, chi = a / h = 0.26) the layer correction of Dimitriadis et
    al. (2002) makes it 28 % stiffer than Hertz. Measured with the default solver (the rest
    model): 1.071 x the bonded layer (1.370 x Hertz) at 2 mm, 0.949 x at 1 mm (contact radius
    1.3 dx: under-resolved), exponent 1.78 for the layer's 1.61 (docs/validation.md, R62; R77
    the same with kinetic damping's stop at ``v = -dt a / 2``); at
    12 across 1.047 at 2 mm, 1.068 at 1 mm, exponent 1.57. The bound is 10 %: the contact is
    past small strain (a / R = 0.22 at 2 mm), where the stress model moves the force by 5 %.
    The block's elastic ``linear`` material takes the corotated stress (``forces.corotated_stress``), linear in the
    stretch, where eq. 9's first Piola stress, which it took before, is the stretch times that,
    softer in compression by about the contact's strain: with it 1.020 / 0.928 x at 8 across,
    exponent 1.75 (docs/validation.md, R61), 0.993 / 1.037 at 12 across. Under either stress the
    force comes towards the layer theory with resolution (1.071 -> 1.047; 1.020 -> 0.993), the
    discretisation error of a contact 1.8 spacings wide (the paper's linear fit with the
    control at 0.1, on the incremental composition with eq. 9: 0.991 at 2 mm; 0.984 and 0.969
    at 12 and 16 across; with the corotated stress 1.043 at 8 across, R62)."""
    r = indented
    assert r["ratios"][1] == pytest.approx(1.0, abs=0.10), r["ratios"]
    assert r["ratios_hertz"][1] > 1.15, r["ratios_hertz"]  # the half-space misses the layer's stiffening
    assert 0.8 < r["ratios"][0] < 1.05, r["ratios"]
    assert r["exponent"] == pytest.approx(r["theory_exponent"], abs=0.25), (r["exponent"], r["theory_exponent"])


def test_sphere_indentation_base_is_bonded_and_carries_the_load(indented):
    """The bonded-layer theory holds the base: the plane tool's friction (mu = 2) keeps the
    base layer in place (measured: largest sideways motion 0.8 % of the depth, rise 0.08 %;
    0.9 % and 0.08 % on the incremental composition), and the base carries the sphere's load
    (static: measured 1.0006 x; 1.001 x on the incremental composition)."""
    r = indented
    assert r["base_slip"] < 0.02, r["base_slip"]
    assert r["base_lift"] < 0.01, r["base_lift"]
    assert r["base_forces"][1] == pytest.approx(r["forces"][1], rel=0.01), (r["base_forces"], r["forces"])


def test_sphere_indentation_force_holds_while_the_sphere_is_held(indented):
    """Held 0.02 s longer at 2 mm: measured 1.0683 x the bonded layer against 1.0712 x at the
    first reading, 0.9973 of it (0.05 s longer 1.0708; 0.1 s longer, the benchmark's: 1.068
    against 1.071, R62 and R77; zeroing the velocities in the holds, before kinetic damping's
    stop at ``v = -dt a / 2``, 1.0680 against 1.0707; with eq. 9's stress,
    before the block's elastic material took the corotated one: 1.015 against 1.020, R61; on
    the incremental composition 1.039 against 1.043, R56). What holds it is the rest model
    that the default runs for this elastic block, not the control alone: held 0.05 s, without
    the control (``model.AUTO_HOURGLASS = 0``) it read 0.9993 x its first reading, within the
    1 % bound; without both (``fit="curvature_corrected", hourglass=0``, the incremental fit)
    0.577 x (0.932 x held 0.02 s: the mutation, failing it), and with the paper's linear fit
    and no control (the next test's set-up) 0.648 x, far outside it."""
    assert indented["late_ratio"] == pytest.approx(indented["ratios"][-1], rel=0.01)


def test_without_the_hourglass_control_the_lattice_under_a_held_sphere_gives_way():
    """The cause of the decay, kept visible: the same indentation straight to 2 mm with the
    paper's linear fit and no control (``fit="linear", hourglass=0``; the default adds the
    control to this elastic block), the force 0.075 s later is well below its first reading:
    the layers under the apex take up the fit's zero-energy pattern. Run 6 across (the
    decay is the lattice's, at any resolution): measured 0.666 x the bonded layer from
    1.021 x, 0.652 of it (0.664 from 1.020 when the holds' kinetic damping zeroed the
    velocities); with the control (``hourglass=0.05``, the mutation) it holds 0.9993
    of it. At 8 across, the fixture's resolution: 0.833 x Hertz from 1.319 x, 0.631 of it
    (0.05 / 0.06 / 0.1 s later 0.82 / 0.66 / 0.53 of it: the lattice gives way between 0.05
    and 0.06 s; held 0.1 s with eq. 9's stress, which the block's elastic linear material
    took before the corotated one, 0.685 from 1.254), 0.9965 of it with the control."""
    r = validation.sphere_indentation(resolution=6, depths=(0.002,), fit="linear", hourglass=0.0, late=0.075)
    print(f"without the control: {r['ratios'][-1]:.3f} then {r['late_ratio']:.3f} x the bonded layer")
    assert r["late_ratio"] < 0.8 * r["ratios"][-1], (r["ratios"], r["late_ratio"])


@pytest.mark.parametrize("case, kwargs, message", [
    ("plate_compression", {"resolution": 0}, r"resolution = 0 is not allowed: must be an integer in \[2, "),
    ("plate_compression", {"resolution": 1}, r"resolution = 1 is not allowed: must be an integer in \[2, "),
    ("plate_compression", {"strain": 0.0}, r"strain = 0.0 is not allowed: must be in \(0, 1\)"),
    ("plate_compression", {"strain": -0.01}, r"strain = -0.01 is not allowed: must be in \(0, 1\)"),
    ("plate_compression", {"strain": 1.5}, r"strain = 1.5 is not allowed: must be in \(0, 1\)"),
    ("three_point_bending", {"resolution": 0}, r"resolution = 0 is not allowed: must be an integer in \[4, "),
    ("three_point_bending", {"resolution": 6}, r"resolution = 6 is not allowed: must be a multiple of 4 "),
    ("three_point_bending", {"deflection": -5e-4}, r"deflection = -0.0005 is not allowed: must be in \(0, 0.04\)"),
    ("three_point_bending", {"hold": 0.0}, r"hold = 0.0 is not allowed: must be > 0"),
    ("three_point_bending", {"hold": 0.1, "average": 0.2}, r"average = 0.2 is not allowed: must be <= hold = 0.1"),
    ("sphere_indentation", {"resolution": 1}, r"resolution = 1 is not allowed: must be an integer in \[2, "),
    ("sphere_indentation", {"depths": ()}, r"depths = \(\) is not allowed: must hold one depth or more"),
    ("sphere_indentation", {"depths": 0.001}, r"depths = 0.001 is not allowed: must be a sequence of depths"),
    ("sphere_indentation", {"depths": (-0.001,)}, r"depths\[0\] = -0.001 is not allowed: must be in \(0, 0.035\)"),
    ("sphere_indentation", {"depths": (0.001, 0.05)}, r"depths\[1\] = 0.05 is not allowed: must be in \(0, 0.035\)"),
    ("sphere_indentation", {"hold": 0.0}, r"hold = 0.0 is not allowed: must be > 0"),
    ("sphere_indentation", {"late": 0.0}, r"late = 0.0 is not allowed: must be > 0"),
    ("sphere_indentation", {"R": -0.04}, r"R = -0.04 is not allowed: must be > 0"),
])
def test_lab_tests_refuse_inputs_they_cannot_measure_by_name(case, kwargs, message):
    """Measured before these were refused: a resolution of 0 was a ZeroDivisionError; plates
    at strain 0 read inf x the theory, at -0.01 (the plate lifted off) a force of 0, at 1.5
    (the top plate through the bottom one) 1.33 x; the beam at 6 across, its supports between
    two particle columns 0.57 mm under its bottom layer, a force and stiffness of 0; a hold of
    0 read the loading (creep 17.9 per s) or was blamed on the keyframe times; no depths an
    AttributeError, a negative one a math domain error, one of 5 cm pushed the sphere through
    the 4 cm block and read 0.30 x the layer theory."""
    with pytest.raises(ValueError, match="^" + message):
        getattr(validation, case)(**kwargs)


def test_plate_compression_at_nu_0_reads_its_lateral_ratio_as_nan_not_minus_inf():
    """nu = 0 is legal (the lateral strain is then measured against 0): its ratio to the theory is
    undefined, and was -inf with a RuntimeWarning."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        r = validation.plate_compression(resolution=2, nu=0.0)
    assert math.isnan(r["lateral_ratio"]) and r["lateral_theory"] == 0.0
    assert r["force_ratio"] > 0.5, r  # the plates still press the cube


def test_plate_compression_at_a_tiny_strain_reads_the_linear_response_in_float64():
    """Linear elasticity: the ratios to E A eps and nu eps do not depend on the strain. At a strain
    of 1e-6 the plate's travel is below float32's resolution of the sample's place; measured at 4
    across the lateral ratio read 0.62 (then 1.41) in float32 for 0.917 at 1 %. The lab tests take
    ``dtype="float64"`` (they ran float32 only): there it reads 0.9171 at 1e-6 and 0.9170 at 1 %."""
    tiny = validation.plate_compression(resolution=4, strain=1e-6, dtype="float64")
    usual = validation.plate_compression(resolution=4, dtype="float64")
    assert tiny["dtype"] == "float64"
    assert tiny["lateral_ratio"] == pytest.approx(usual["lateral_ratio"], rel=2e-3), (tiny, usual)
    assert tiny["force_ratio"] == pytest.approx(usual["force_ratio"], rel=2e-3), (tiny, usual)
    with pytest.raises(ValueError, match=r"^dtype = 'float16' is not allowed: must be one of 'float32', 'float64'"):
        validation.three_point_bending(dtype="float16")


@pytest.mark.parametrize("run", [validation.beam_deflection, validation.near_yield_column, validation.three_point_bending])
@pytest.mark.parametrize("dtype", ["float16", "double", "vec3"])
def test_validation_runs_refuse_an_unknown_dtype_by_name(run, dtype):
    """Every validation run that takes ``dtype`` refuses one that is not float32 or float64 by
    name, before it builds anything (the beam and the near-yield column looked the name up
    in Warp: ``"double"`` raised AttributeError, ``"float16"`` and ``"vec3"`` reached
    ``finalize``)."""
    with pytest.raises(ValueError, match=rf"^dtype = '{dtype}' is not allowed: must be one of 'float32', 'float64'"):
        run(dtype=dtype)


# ------------------------------------------------------- partial runs merged into a report
def test_only_selects_plan_entries_by_case_and_keyword_values():
    runs = validation.plan(False)
    picked = validation.select(runs, "slump:resolution=12:elastic_force=variational,bar_frequency")
    slumps = [k for n, k in picked if n == "slump"]
    assert {k["S"] for k in slumps} == set(validation.SLUMP_S)
    assert all(k["resolution"] == 12 and k["elastic_force"] == "variational" for k in slumps)
    assert len([n for n, _ in picked if n == "bar_frequency"]) == len([n for n, _ in runs if n == "bar_frequency"])
    assert validation.select(runs, None) == runs
    # A run that names no fit weight runs the default's, and is selected by it.
    bars = validation.select(runs, "bar_frequency:resolution=4:elastic_force=variational")
    assert [k.get("fit_weight") for _, k in bars] == [None, OTHER_WEIGHT]
    at = "bar_frequency:resolution=4:elastic_force=variational:fit_weight="
    assert validation.select(runs, at + DEFAULT_WEIGHT) == bars[:1]
    assert validation.select(runs, at + OTHER_WEIGHT) == bars[1:]
    with pytest.raises(ValueError, match="key=value"):
        validation.select(runs, "slump:resolution")


def test_merge_replaces_the_rows_measured_again_and_tags_every_row_with_its_run():
    old_rows = [{"case": "slump", "S": 0.2, "resolution": 8, "elastic_force": "variational", "h_over_H0": 0.40},
                {"case": "slump", "S": 0.2, "resolution": 12, "elastic_force": "variational", "h_over_H0": 0.41},
                # written before the field "dtype" existed: matches a float32 row on the other fields
                {"case": "beam", "resolution": 6, "elastic_force": "paper", "ratio": 1.9}]
    earlier = {"command": "an older run", "machine": "x86_64", "python": "3.11", "wall_s": 10.0, "results": old_rows}
    new_rows = [{"case": "slump", "S": 0.2, "resolution": 8, "elastic_force": "variational", "h_over_H0": 0.50},
                {"case": "beam", "resolution": 6, "elastic_force": "paper", "dtype": "float32", "ratio": 1.1}]
    meta = {"command": "python -m benchmarks.validation --only slump", "machine": "x86_64", "python": "3.11",
            "wall_s": 5.0}
    doc = validation.merge(earlier, new_rows, meta)
    assert [r["command"] for r in doc["runs"]] == ["an older run", meta["command"]]
    by = {(r["case"], r["resolution"]): r for r in doc["results"]}
    assert len(doc["results"]) == 3
    assert by["slump", 8]["h_over_H0"] == 0.50 and by["slump", 8]["run"] == 1
    assert by["slump", 12]["h_over_H0"] == 0.41 and by["slump", 12]["run"] == 0
    assert by["beam", 6]["ratio"] == 1.1 and by["beam", 6]["run"] == 1
    # Merging again keeps the first run's surviving rows under their own run.
    again = validation.merge(doc, [new_rows[0] | {"h_over_H0": 0.51}], meta | {"command": "third"})
    assert [r["command"] for r in again["runs"]] == ["an older run", meta["command"], "third"]
    by = {(r["case"], r["resolution"]): r for r in again["results"]}
    assert by["slump", 12]["run"] == 0 and by["beam", 6]["run"] == 1 and by["slump", 8]["run"] == 2
    assert validation.merge(None, new_rows, meta)["runs"] == [meta]
    # Rows of a dropped case go; a run left without rows stays listed, marked, so that the
    # numbers of the runs after it (which the report's notes cite) do not move.
    dropped = validation.merge(earlier, new_rows[1:], meta, drop=("slump",))
    assert [r["case"] for r in dropped["results"]] == ["beam"]
    assert [r["command"] for r in dropped["runs"]] == ["an older run", meta["command"]]
    assert dropped["runs"][0]["superseded"] and "superseded" not in dropped["runs"][1]
    assert dropped["results"][0]["run"] == 1
    assert "superseded" not in again["runs"][0]
    # Marking a run leaves the merged document it came from as it was.
    validation.merge(doc, [], meta, drop=("slump", "beam"))
    assert not any("superseded" in r for r in doc["runs"])


@pytest.mark.parametrize("radii,verdict,law", [
    # The particle floor's piles (R27, R60, R65, 3 digits): each nearer, and their changes
    # shrink as a law of order 0.56 toward 1.19 R_RC allows; the limit is reported though it
    # is past 10 %, as the slump's.
    ((0.816, 0.871, 0.908), "within 10 %: yes; converging: yes", "a = 0.25 order 0.56, limit 1.19 R_RC"),
    # poly6's (R3, R21, R60): each nearer, but the last change (0.039) too large against the one
    # before (0.044) for any law of positive order: the old rule (each no further) read "yes".
    ((0.854, 0.898, 0.937), "within 10 %: yes; converging: not shown for a = 0.25 (0.854/0.898/0.937 R_RC at 3/4/5)",
     None),
    ((0.854, 0.950, 0.930), "within 10 %: yes; converging: not shown for a = 0.25 (0.854/0.950/0.930 R_RC at 3/4/5)",
     None),
    ((0.750, 0.800, 0.830), "within 10 %: no; converging: yes", "a = 0.25 order 1, limit 0.95 R_RC"),
    # The last change within what a law of order 6 leaves, either sign: settled.
    ((0.900, 0.950, 0.949), "within 10 %: yes; converging: yes", "a = 0.25 settled, limit 0.95 R_RC")])
def test_report_reads_the_spread_target_at_the_finest_resolution_and_its_convergence(tmp_path, radii, verdict, law):
    """As the slump's target, by the slump's rule (``validation_report.convergence``): the radius
    within 10 % of Roussel & Coussot at the finest resolution of each shallowness, and the last
    three resolutions fit R_inf + C n^-p with p > 0 (or settle), whose order and limit the row
    reports whether or not the limit is the theory's."""
    from benchmarks import validation_report

    rows = [_spread_row(n, r) for n, r in zip((3, 4, 5), radii)]
    doc = {"runs": [{"command": "rows", "machine": "x86_64", "python": "3.11", "wall_s": 1.0}], "results": rows}
    md, _ = validation_report.write(rows, tmp_path, doc)
    target = next(line for line in md.read_text().splitlines() if line.startswith("| spread limit"))
    got = target.split(" | ")[1]
    assert f"| {verdict} |" in target, target
    assert (f"; changes over the last three resolutions fit R_inf + C n^-p: {law}" in got if law
            else "R_inf" not in got), got


def _spread_row(n, radius, floor="particles"):
    """A made spread row (a = 0.25, 14 s, at rest) ``n`` through, resting at ``radius`` R_RC."""
    return {"case": "spread", "shallowness": 0.25, "resolution": n, "elastic_force": "variational", "floor": floor,
            "fit_weight": DEFAULT_WEIGHT, "particles": 100 * n, "duration": 14.0, "radius_over_theory": radius,
            "height_over_theory": 1.1, "height_over_radius": 0.3, "profile_over_theory": [1.0] * 8,
            "radius_rate_pct_per_s": 0.01, "kinetic_over_Mgh": 1e-11, "time_history": [0.0, 14.0],
            "radius_history": [0.5, radius], "height_history": [2.0, 1.1], "run": 0}


def test_the_tresca_grounds_spread_piles_get_the_suites_row_and_the_particle_floors_are_counted_apart():
    """The spread piles on the Tresca ground (floor "tresca_images", the suite's floor) are
    judged in the suite's row, against Roussel & Coussot's radius (its base carries the shear
    yield stress, the ground's wall law); the particle floor's, against the same radius, in a
    row named for that floor that the opening counts apart; each row reads its own piles
    alone, and the rough imaged ground's (no target of its own) are in neither."""
    from benchmarks.validation_report import _summary, _targets

    particles = [_spread_row(n, r) for n, r in ((3, 0.82), (4, 0.87), (5, 0.91))]
    ground = [_spread_row(n, r, "tresca_images") for n, r in ((3, 0.95), (4, 1.02))]
    imaged = [_spread_row(n, r, "ground_images") for n, r in ((3, 0.70), (4, 0.75))]
    targets = _targets(particles + ground + imaged)
    spread = {t[0]: t for t in targets if t[0].startswith("spread limit")}
    name = ("spread limit: radius within 10 % of Roussel & Coussot at the finest resolution, converging "
            "(the suite's own target)")
    theirs = name.replace("converging", "converging on the particle floor")
    assert set(spread) == {name, theirs}, list(spread)
    _, got, verdict, _ = spread[name]
    assert got == ("a = 0.25, 3 through: 0.950 R_RC (0.01 % R_RC/s at 14 s); a = 0.25, 4 through: 1.020 R_RC "
                   "(0.01 % R_RC/s at 14 s)"), got
    # Two resolutions show which is nearer, not a convergence (the slump's "three needed").
    assert verdict == "within 10 %: yes; converging: not shown for a = 0.25 (resolutions 3/4: three needed)", verdict
    assert {t[0]: t for t in _targets(particles + ground + [_spread_row(5, 1.01, "tresca_images")])}[name][2] == \
        "within 10 %: yes; converging: yes"
    apart = spread[theirs]
    assert "0.820 R_RC" in apart[1] and "0.950" not in apart[1] and "0.700" not in apart[1], apart
    # One resolution shows no convergence.
    alone_3 = {t[0]: t for t in _targets(particles + ground[:1])}[name]
    assert alone_3[2] == "within 10 %: yes; converging: not shown for a = 0.25 (resolutions 3: three needed)", alone_3
    # The headline counts the suite's floor's rows; the particle floor's row is counted apart.
    alone = _summary(_targets(ground))
    text = _summary(targets)
    assert re.search(r"\*\*In short\*\*: \d+ of the \d+ rows", text).group() == \
        re.search(r"\*\*In short\*\*: \d+ of the \d+ rows", alone).group(), (alone, text)
    assert "(the 1 on the particle floor apart, below)" in text and "0 of its 1 rows are met in full" in text, text


def test_report_lists_its_runs_and_names_the_run_of_every_row(tmp_path):
    from benchmarks import validation_report

    bar = {"case": "bar", "elastic_force": "variational", "particles": 640, "frequency": 12.5, "theory": 12.5}
    old = [bar | {"resolution": 4, "ratio": 0.9992}, bar | {"resolution": 6, "ratio": 1.0003}]
    stab = {"case": "stability", "label": "preset clay", "elastic_force": "variational", "preset_force": "variational",
            "dt": 3e-4, "duration": 0.3, "max_speed": 0.5, "blew_up": False, "blew_up_at": None}
    earlier = {"command": "the earlier run", "machine": "x86_64", "python": "3.11", "wall_s": 9.0, "results": old}
    meta = {"command": "python -m benchmarks.validation --only bar_frequency:resolution=4", "commit": "abc1234",
            "date": "2026-11-30", "machine": "x86_64", "python": "3.11", "wall_s": 3.0}
    doc = validation.merge(earlier, [bar | {"resolution": 4, "ratio": 0.9975}, stab], meta)
    md, _ = validation_report.write(doc["results"], tmp_path, doc)
    text = md.read_text()
    assert "| R1 | `the earlier run` |" in text and f"| R2 | `{meta['command']}` | abc1234 |" in text
    rows = [line for line in text.splitlines() if line.startswith("| 4 | variational") or line.startswith("| 6 | variational")]
    assert len(rows) == 2 and rows[0].endswith("| 0.998 | R2 |") and rows[1].endswith("| 1 | R1 |")
    target = next(line for line in text.splitlines() if line.startswith("| bar frequency within 2 %"))
    assert "0.9975 x c/(2L)" in target and target.endswith("| yes | R2 |")
    assert next(line for line in text.splitlines() if line.startswith("| preset clay")).endswith("| R2 |")


def test_report_judges_the_elastic_references_and_the_step_bound_per_fit_weight(tmp_path):
    """Bar and stability rows of the other fit weight are listed with their weight and judged
    in target rows named for it; the default's targets read only the default's rows, whatever
    the order of the rows."""
    from benchmarks import validation_report

    named = f"with {validation_report.WEIGHT_NAMES[OTHER_WEIGHT]} fit weight"

    bar = {"case": "bar", "elastic_force": "variational", "particles": 640, "frequency": 12.5, "theory": 12.5,
           "resolution": 4}
    stab = {"case": "stability", "label": "preset clay", "elastic_force": "variational", "preset_force": "variational",
            "dt": 3e-4, "duration": 1.0, "max_speed": 0.5, "blew_up": False, "blew_up_at": None}
    rows = [bar | {"ratio": 0.9975, "fit_weight": DEFAULT_WEIGHT}, bar | {"ratio": 0.95, "fit_weight": OTHER_WEIGHT},
            stab | {"fit_weight": DEFAULT_WEIGHT},
            stab | {"fit_weight": OTHER_WEIGHT, "max_speed": 7.0, "blew_up": True, "blew_up_at": 0.4}]
    meta = {"command": "python -m benchmarks.validation", "machine": "x86_64", "python": "3.11", "wall_s": 1.0}
    doc = validation.merge(None, rows[::-1], meta)
    md, _ = validation_report.write(doc["results"], tmp_path, doc)
    lines = md.read_text().splitlines()
    bars = [line for line in lines if line.startswith("| bar frequency within 2 %")]
    assert len(bars) == 2 and "0.9975 x c/(2L)" in bars[0] and bars[0].endswith("| yes | R1 |"), bars
    assert named in bars[1] and "0.9500 x c/(2L)" in bars[1] and "| no |" in bars[1], bars
    steps = [line for line in lines if line.startswith("| no preset or default material blows up")]
    assert len(steps) == 2 and "none of 1 runs" in steps[0] and steps[0].endswith("| yes | R1 |"), steps
    assert named in steps[1] and "blew up: preset clay (variational)" in steps[1], steps
    assert [line for line in lines if line.startswith("| 4 | variational |")] == [
        line for line in lines if line.startswith("| 4 | variational | poly6 |")
        or line.startswith("| 4 | variational | biweight |")]
    assert len([line for line in lines
                if line.startswith(f"| preset clay | variational | variational | {OTHER_WEIGHT} |")]) == 1


def test_report_lists_the_lab_tests_and_the_energy_rows_with_their_fit_weight(tmp_path):
    """The plates, indentation, bending and energy tables name each row's fit weight (a
    biweight twin read without it would stand as a second poly6 measurement of the same row),
    the default's first; rows written before the option read as poly6."""
    import json

    from benchmarks import validation_report

    old = json.loads((ROOT / "docs" / "validation.json").read_text())["results"]
    rows = []
    for case in ("plates", "indentation", "bending", "energy"):
        first = next(r for r in old if r["case"] == case and r.get("fit_weight", "poly6") == "poly6")
        first = {k: v for k, v in first.items() if k not in ("run", "fit_weight")}
        rows += [first | {"fit_weight": "biweight"}, first]
    meta = {"command": "python -m benchmarks.validation", "machine": "x86_64", "python": "3.11", "wall_s": 1.0}
    doc = validation.merge(None, rows, meta)
    md, _ = validation_report.write(doc["results"], tmp_path, doc)
    text = md.read_text()
    for title in ("### Compression between frictionless plates", "### Sphere indentation", "### Three-point bending",
                  "## Undamped elastic energy"):
        table = [line for line in text.split(title, 1)[1].split("\n#", 1)[0].splitlines() if line.startswith("|")]
        header = [c.strip() for c in table[0].strip("|").split("|")]
        col = header.index("fit weight")
        weights = [[c.strip() for c in line.strip("|").split("|")][col] for line in table[2:]]
        assert weights and weights == sorted(weights, key=(DEFAULT_WEIGHT, OTHER_WEIGHT).index), (title, weights)
        assert weights.count("poly6") == weights.count("biweight"), (title, weights)

def test_the_energy_plot_draws_the_default_weights_rows_only(tmp_path, monkeypatch):
    """The energy figure draws the default fit weight's rows (the table lists the other's beside
    them): with both weights' twins its legend of 24 lines covered the curves."""
    import json

    from benchmarks import validation_report

    drawn = {}

    def save(fig, img, name, made):
        drawn[name] = [line.get_label() for ax in fig.axes for line in ax.get_lines()]
        made.append(name)

    monkeypatch.setattr(validation_report, "_save", save)
    old = json.loads((ROOT / "docs" / "validation.json").read_text())["results"]
    energy = [r for r in old if r["case"] == "energy" and r.get("fit_weight", "poly6") == "poly6"][:2]
    rows = [r | {"fit_weight": DEFAULT_WEIGHT} for r in energy] + [r | {"fit_weight": OTHER_WEIGHT, "dt_factor": 7.0}
                                                                  for r in energy]
    validation_report._plots(rows, tmp_path)
    assert len(drawn["energy.png"]) == 2 and not any("dt x 7.0" in label for label in drawn["energy.png"]), drawn

def test_report_says_which_deformation_model_the_default_ran_for_the_variational_rows(tmp_path):
    """The default solver runs the rest model for a purely elastic scene without floor images or
    a ghost floor and the incremental composition elsewhere (``rest_model_steps`` counts the
    former's steps; a row without the field predates that default): the force column cannot
    tell them apart, so the energy table names the default's rest rows and each section says
    which rows ran which."""
    from benchmarks import validation_report

    energy = {"case": "energy", "amplitude": 0.002, "elastic_force": "variational", "deformation": "incremental",
              "fit": "curvature_corrected", "hourglass": 0.05, "resolution": 6, "dt_factor": 1.0, "periods": 50.0,
              "peak_strain": 0.005, "drift": -0.001, "max_deviation": 0.02, "blew_up": False, "t": [0.0, 1.0],
              "relative_energy": [0.0, -0.001]}
    bar = {"case": "bar", "elastic_force": "variational", "particles": 640, "frequency": 12.5, "theory": 12.5,
           "ratio": 0.9975}
    stab = {"case": "stability", "elastic_force": "variational", "preset_force": "variational", "dt": 3e-4,
            "duration": 1.0, "max_speed": 0.5, "blew_up": False, "blew_up_at": None}
    meta = {"command": "python -m benchmarks.validation", "machine": "x86_64", "python": "3.11", "wall_s": 1.0}
    earlier = validation.merge(None, [energy | {"dt_factor": 0.5, "drift": 0.034}, bar | {"resolution": 6}], meta)
    doc = validation.merge(earlier, [energy | {"rest_model_steps": 2001}, bar | {"resolution": 4, "rest_model_steps": 990},
                                     stab | {"label": "preset rubber", "rest_model_steps": 3000},
                                     stab | {"label": "preset clay", "rest_model_steps": 0}], meta)
    md, _ = validation_report.write(doc["results"], tmp_path, doc)
    text = md.read_text()
    lines = text.splitlines()
    assert [line.split(" | ")[0] for line in lines if line.startswith("| variational")] == [
        "| variational", "| variational (default: rest, curvature_corrected fit, control 0.05)"]
    elastic = text[text.index("## Elastic references"):text.index("### Free-free bar")]
    assert "1 of the 2 variational rows ran the rest model (`rest_model_steps`" in elastic, elastic
    assert "; 1 ran the incremental composition (measured by R1, before that default)." in elastic, elastic
    stability = text[text.index("## Stability at half"):]
    assert '1 of the 2 variational rows ran the rest model ("preset rubber"; `rest_model_steps`' in stability, stability
    assert "; 1 ran the incremental composition." in stability, stability


# ------------------------------------------------------- the rest verdict of the slumps
def test_the_full_plan_reads_every_slump_at_its_rest_duration_and_the_quick_plan_stays_short():
    """Every slump of the full plan runs ``SLUMP_DURATION`` (8 s: at 4 s the S = 0.3 and 0.05
    piles at 8 across still sank 0.56 / 0.67 % H0/s), the 16-across ones
    ``SLUMP_DURATION_FINE`` (12 s: the 16-across S = 0.1 pile still rang at 8 s), as do the
    24-across ones of the particle floor (the convergence verdict's third resolution); the CI-sized
    plan keeps its short runs. The ghost floor's piles rest by about 4 s at every resolution
    (8 s each), the Tresca ground's (the suite's floor) by 8 s up to 16 across (R98, R99), its
    24-across ones run 12 s as the particle floor's."""
    full = [k for n, k in validation.plan(False) if n == "slump"]
    assert {k["resolution"] for k in full} == {8, 12, 16, 24}
    ghost = [k for k in full if k.get("floor") == "ghost_particles"]
    assert ghost and all(k["duration"] == validation.SLUMP_DURATION for k in ghost)
    suite = [k for k in full if k.get("floor") == validation.SUITE_FLOOR == validation.TRESCA]
    assert {k["resolution"] for k in suite} == {8, 12, 16, 24}, suite
    assert all(k["duration"] == (validation.SLUMP_DURATION_FINE if k["resolution"] == 24 else validation.SLUMP_DURATION)
               for k in suite)
    full = [k for k in full if k.get("floor", "particles") == "particles"]
    assert all(k["duration"] == validation.SLUMP_DURATION == 8.0 for k in full if k["resolution"] < 16)
    assert all(k["duration"] == validation.SLUMP_DURATION_FINE == 12.0 for k in full if k["resolution"] >= 16)
    assert {k["S"] for k in full if k["resolution"] == 24} == {0.1, 0.2, 0.3, 0.5}
    quick = [k for n, k in validation.plan(True) if n == "slump"]
    assert quick and all(k["duration"] <= 5.0 for k in quick)


def test_the_full_plan_has_a_twin_of_every_target_row_below_24_across():
    """A default switch must re-measure every row the targets of issue 12 read (docs/physics.md,
    "The fit weight's default: the evidence"): each slump of the full plan of the default fit
    weight with the default elastic force below 24 across (the particle floor's, S = 0.05 with
    them, and the no-slip ghost floor's) and each spread pile at a = 0.25 has the same entry
    with the other weight, so ``--only ...:fit_weight=<it>`` can run it."""
    runs = validation.plan(False)

    def wanted(name, k):
        if name == "slump":
            return k.get("elastic_force", "variational") == "variational" and k["resolution"] < 24
        return name == "spread" and k["shallowness"] == 0.25

    base = [(n, k) for n, k in runs if wanted(n, k) and "fit_weight" not in k]
    other = [(n, k) for n, k in runs if wanted(n, k) and k.get("fit_weight") == OTHER_WEIGHT]
    assert not [k for n, k in runs if k.get("fit_weight") == DEFAULT_WEIGHT], "the default's entries name no weight"
    assert {(n, k["resolution"], k.get("S"), k.get("floor")) for n, k in base} == {
        (n, k["resolution"], k.get("S"), k.get("floor")) for n, k in other}
    twins = {(n, tuple(sorted((k | {"fit_weight": DEFAULT_WEIGHT}).items()))) for n, k in other}
    assert {(n, tuple(sorted((k | {"fit_weight": DEFAULT_WEIGHT}).items()))) for n, k in base} == twins
    # Every slump and spread entry names its floor: the suite's, the particle floor's counted
    # apart, the ghost floor's.
    assert {k.get("floor") for n, k in other} == {"ghost_particles", "particles", validation.SUITE_FLOOR}
    for weight in validation.FIT_WEIGHTS:
        picked = validation.select(runs, f"slump:S=0.05:elastic_force=variational:fit_weight={weight}")
        assert sorted(picked, key=str) == sorted((
            ("slump", {"S": 0.05, "resolution": res, "elastic_force": "variational", "duration": 8.0, "floor": floor}
             | ({"fit_weight": weight} if weight != DEFAULT_WEIGHT else {}))
            for floor in (validation.SUITE_FLOOR, "particles") for res in (8, 12)), key=str), picked


def _planned(runs, default):
    """Each entry of ``runs`` as (case, its keyword arguments with the fit weight it runs)."""
    return [(n, tuple(sorted(({"fit_weight": default} | k).items()))) for n, k in runs]


def test_the_full_plan_runs_each_entry_once_with_each_fit_weight(monkeypatch):
    """Before and after the default weight became the biweight (docs/physics.md's
    Recommendation), every row of docs/validation.md has its measurement with each weight,
    not only the targets' (the paper's force, the energy, the lab tests, the near-yield column,
    the 24-across piles): each entry of the full plan runs once with each weight, whichever
    weight is the default (the entries that named the biweight while poly6 was the default ran
    twice after a switch), and the plan is the same set of runs under either default."""
    plans = {}
    for default in validation.FIT_WEIGHTS:
        monkeypatch.setattr(validation, "DEFAULT_FIT_WEIGHT", default)
        plans[default] = _planned(validation.plan(False), default)
    for default, key in plans.items():
        assert len(set(key)) == len(key), (default, sorted(k for k in key if key.count(k) > 1)[:3])
        by_weight = [{(n, tuple((f, v) for f, v in k if f != "fit_weight")) for n, k in key if dict(k)["fit_weight"] == w}
                     for w in validation.FIT_WEIGHTS]
        assert by_weight[0] == by_weight[1], (default, sorted(by_weight[0] ^ by_weight[1])[:3])
        assert {n for n, _ in by_weight[0]} >= {"plate_compression", "sphere_indentation", "three_point_bending",
                                                 "energy_drift"}
    assert set(plans["poly6"]) == set(plans["biweight"])


class _Built(Exception):
    pass


@pytest.mark.parametrize("case, kwargs", [("plate_compression", {"resolution": 2}),
                                          ("sphere_indentation", {"resolution": 2, "depths": (0.001,)}),
                                          ("three_point_bending", {"resolution": 4}),
                                          ("plastic_compression", {"resolution": 2})])
def test_each_lab_function_builds_its_model_with_the_fit_weight_it_is_given(monkeypatch, case, kwargs):
    seen = []

    def solver(model, **kw):
        seen.append(model.fit_weight)
        raise _Built

    monkeypatch.setattr(validation, "_solver", solver)
    for weight in ("biweight", "poly6"):
        with pytest.raises(_Built):
            getattr(validation, case)(fit_weight=weight, **kwargs)
    assert seen == ["biweight", "poly6"], seen


def test_slump_at_rest_needs_both_a_still_top_and_a_still_pile():
    rate, ke = validation.REST_RATE, validation.REST_KINETIC
    assert validation.slump_at_rest(0.5 * rate, 0.5 * ke)
    assert validation.slump_at_rest(-0.5 * rate, 0.5 * ke)  # a top rising as slowly is as still
    assert not validation.slump_at_rest(1.5 * rate, 0.5 * ke)
    assert not validation.slump_at_rest(-1.5 * rate, 0.5 * ke)
    assert not validation.slump_at_rest(0.5 * rate, 1.5 * ke)  # a still top on a ringing pile
    assert not validation.slump_at_rest(float("nan"), 0.5 * ke)


def _slump_row(S, resolution, rate, ke=1e-10, force="variational", **extra):
    """A slump's row as the case function writes it, of the default fit weight unless ``extra`` names one."""
    h = validation.slump_theory(S)
    row = {"case": "slump", "S": S, "resolution": resolution, "aspect": 1.0, "elastic_force": force,
           "floor": "particles", "fit_weight": DEFAULT_WEIGHT, "particles": 100, "duration": 8.0, "h_over_H0": h, "theory_h_over_H0": h,
           "ratio_to_theory": 1.0, "top_rate_pct_H0_per_s": rate, "kinetic_over_MgH0": ke,
           "kinetic_last_quarter_over_MgH0": ke, "at_rest": validation.slump_at_rest(rate, ke),
           "fraction_at_yield": 0.9, "plug_particles": 0, "plug_unyielded_fraction": float("nan"),
           "plug_plastic_strain": float("nan"), "flowed_plastic_strain": 10.0, "radius_over_R0": 1.5,
           "radius_over_spread_theory": 0.8, "spread_theory_h_over_H0": 0.5,
           "time_history": [0.0, 8.0], "h_history": [1.0, h]}
    return row | extra


def _rest_target(text):
    return next(line for line in text.splitlines() if line.startswith("| every slumped top at rest"))


def test_report_gives_the_uniaxial_flow_against_bingham_by_band_of_log_strain(tmp_path):
    from benchmarks import validation_report

    hist = [{"log_strain": e, "stress_over_sigma_y": s, "bingham_over_sigma_y": 1.2}
            for e, s in ((0.02, 0.6), (0.1, 1.2), (0.4, 1.32), (0.6, 0.9), (0.8, 0.84), (1.2, 0.78))]
    rows = [{"case": "uniaxial_flow", "resolution": 8, "strain": 0.75, "duration": 4.0, "history": hist, "run": 0}]
    rows.append(rows[0] | {"fit_weight": "biweight", "history": [h | {"stress_over_sigma_y": 1.1} for h in hist]})
    doc = {"runs": [{"command": "python -m benchmarks.validation --only uniaxial_flow"}], "results": rows}
    md, made = validation_report.write(rows, tmp_path, doc)
    text = md.read_text()
    # A row written before the fit weight was recorded is the paper's poly6; the default's first.
    assert "| 8 | poly6 | 0.75 | 4 | 1.00-1.10 | 0.75-0.75 | 0.70-0.70 | 0.65-0.65 | R1 |" in text, text
    assert "| 8 | biweight | 0.75 | 4 | 0.92-0.92 | 0.92-0.92 | 0.92-0.92 | 0.92-0.92 | R1 |" in text, text
    assert text.index(f"| 8 | {DEFAULT_WEIGHT} |") < text.index(f"| 8 | {OTHER_WEIGHT} |")
    assert "uniaxial_flow.png" in made
    # Flows at another strain or with another fit weight are other rows, not the same one measured again.
    assert not validation.same_run(rows[0], rows[0] | {"strain": 0.6})
    assert not validation.same_run(rows[0] | {"fit_weight": "poly6"}, rows[1])
    # A row written before the field existed ran poly6: the biweight row does not replace it.
    assert not validation.same_run(rows[0], rows[1]) and validation.same_run(rows[0], rows[0] | {"fit_weight": "poly6"})
    merged = validation.merge(doc, rows[1:], {"command": "again", "machine": "x86_64", "python": "3.11"})
    assert sorted(r.get("fit_weight", "-") for r in merged["results"]) == ["-", "biweight"]


def test_report_judges_rest_at_the_finer_resolution_and_takes_gpu_rows_at_any_resolution(tmp_path):
    """The rest target is met only if every slump at the finest resolution that has every S is
    at rest, and names those that are not; a coarser row still moving is named but not judged.
    Rows measured elsewhere (``--add``: a GPU's, at 24 and 32 across, with a ``device``) join
    the table, the plot against resolution and the targets, under a run of their own."""
    import json

    from benchmarks import validation_report

    S = (0.1, 0.2, 0.3, 0.5)
    moving = 3.0 * validation.REST_RATE
    cpu = [_slump_row(s, 8, moving if s == 0.3 else 0.0) for s in S]
    cpu += [_slump_row(s, 12, moving if s == 0.2 else 0.0) for s in S]
    meta = {"command": "python -m benchmarks.validation --only slump", "machine": "x86_64", "python": "3.11", "wall_s": 1.0}
    doc = validation.merge(None, cpu, meta)
    md, made = validation_report.write(doc["results"], tmp_path, doc)
    target = _rest_target(md.read_text())
    assert "12 across" in target and "S = 0.3 at 8" in target and target.endswith("| no (S = 0.2: top 0.3 % H0/s) | R1 |"), target
    assert "slump_resolution.png" in made

    gpu = [_slump_row(s, res, 0.0, device="NVIDIA H200") for res in (24, 32) for s in S]
    (tmp_path / "gpu.json").write_text(json.dumps(gpu))
    doc = validation.added_rows(doc, tmp_path / "gpu.json")
    assert [r["machine"] for r in doc["runs"]] == ["x86_64", "? (NVIDIA H200)"]
    md, made = validation_report.write(doc["results"], tmp_path, doc)
    text = md.read_text()
    assert "32 across" in _rest_target(text) and _rest_target(text).endswith("| yes | R2 |"), _rest_target(text)
    gpu_rows = [line for line in text.splitlines() if line.startswith("| 0.2 | 32 | variational")]
    assert len(gpu_rows) == 1 and gpu_rows[0].endswith("| NVIDIA H200 | R2 |"), gpu_rows
    assert (tmp_path / "images" / "validation" / "slump_resolution.png").stat().st_size > 0


def test_the_command_line_merges_rows_measured_elsewhere_without_running_the_plan(tmp_path):
    """``python -m benchmarks.validation --merge A --add B``: B's rows (a GPU's) replace the rows
    of A they measure again, under a run of their own, and no case of the plan is run."""
    import json

    meta = {"command": "an earlier run", "machine": "x86_64", "python": "3.11", "wall_s": 1.0}
    earlier = validation.merge(None, [_slump_row(0.2, 12, 0.5), _slump_row(0.3, 12, 0.0)], meta)
    (tmp_path / "earlier.json").write_text(json.dumps(earlier))
    (tmp_path / "gpu.json").write_text(json.dumps([_slump_row(0.2, 12, 0.01, device="gpu", wall_s=3.0)]))
    out = tmp_path / "out"
    assert validation.main(["--merge", str(tmp_path / "earlier.json"), "--add", str(tmp_path / "gpu.json"),
                            "--out", str(out), "--no-report"]) == 0
    doc = json.loads((out / "validation.json").read_text())
    by = {r["S"]: r for r in doc["results"]}
    assert len(doc["results"]) == 2 and by[0.2]["device"] == "gpu" and by[0.2]["run"] == 1 and by[0.3]["run"] == 0
    assert by[0.2]["at_rest"] and not earlier["results"][0]["at_rest"]
    assert doc["runs"][1]["wall_s"] == 3.0 and "gpu" in doc["runs"][1]["machine"]
    assert not (out / "validation.md").exists()


def test_the_command_line_refuses_an_unknown_device_by_name_before_any_run(tmp_path):
    with pytest.raises(ValueError, match="--device = 'gpu9'"):
        validation.main(["--device", "gpu9", "--only", "bar_frequency", "--no-report", "--out", str(tmp_path)])
    assert not (tmp_path / "validation.json").exists()


def test_the_command_line_records_the_device_of_each_row(tmp_path):
    import json

    validation.main(["--device", "cpu", "--only", "poisson_compression:resolution=4:elastic_force=variational:fit_weight=poly6",
                     "--no-report", "--out", str(tmp_path)])
    rows = json.loads((tmp_path / "validation.json").read_text())["results"]
    assert [r["device"] for r in rows] == ["cpu"]


def test_report_judges_the_default_fit_weight_and_gives_the_biweight_targets_of_their_own(tmp_path):
    """Rows measured with the other fit weight than the default are listed with their weight
    and judged in target rows named for it; the default's target rows read only the rows of
    ``DEFAULT_FIT_WEIGHT``."""
    from benchmarks import validation_report

    S = (0.1, 0.2, 0.3, 0.5)
    rows = [_slump_row(s, 16, 0.0) for s in S]
    rows += [_slump_row(s, 16, 0.0, fit_weight=OTHER_WEIGHT, thickness_over_H0=0.8 * validation.slump_theory(s))
             for s in S]
    named = f"with {validation_report.WEIGHT_NAMES[OTHER_WEIGHT]} fit weight"
    meta = {"command": "python -m benchmarks.validation --only slump", "machine": "x86_64", "python": "3.11", "wall_s": 1.0}
    doc = validation.merge(None, rows, meta)
    assert len(doc["results"]) == 8
    md, _ = validation_report.write(doc["results"], tmp_path, doc)
    text = md.read_text()
    height = [line for line in text.splitlines() if line.startswith("| slump height within 10 %")]
    assert len(height) == 2, height
    assert " fit weight" not in height[0] and "| within 10 %: yes;" in height[0], height[0]
    assert named in height[1] and "S = 0.1 -20.0 %" in height[1], height[1]
    assert "| within 10 %: no (S = 0.1, S = 0.2, S = 0.3, S = 0.5);" in height[1], height[1]
    assert len([line for line in text.splitlines()
                if line.startswith(f"| 0.2 | 16 | variational | particles | {OTHER_WEIGHT} |")]) == 1


def test_the_validation_page_names_a_shared_miss_only_on_a_floor_whose_continuum_runs_its_wall_law():
    """docs/validation.md said of the particle floor's plug "the continuum on a slip base misses
    it too", in its table and its opening, though that floor grips and the slip continuum does
    not: a loss of the plug by a continuum on another wall law is shown beside the piles', not
    named as the same miss (as the height's). Every verdict on the page that names one is a
    row on a floor of ``SAME_WALL``, naming that floor's own continuum."""
    from benchmarks.validation_report import CONTINUUM_BASE, FLOOR_NAMES, SAME_WALL, SUITE_FLOOR, _base_name

    page = (pathlib.Path(__file__).resolve().parent.parent / "docs" / "validation.md").read_text()
    lines = [line for line in page.splitlines() if "misses it too" in line]
    assert lines, "the page names no shared miss (the ghost floor's and the Tresca ground's rows do)"
    for line in lines:
        # A row named for no floor is the suite's floor's.
        floors = [f for f in FLOOR_NAMES if f" on {FLOOR_NAMES[f]}" in line.split(": ")[0].split(" | ")[0]] or [SUITE_FLOOR]
        assert len(floors) == 1 and floors[0] in SAME_WALL, line
        assert f"the continuum on a {_base_name(CONTINUUM_BASE[floors[0]])} base misses it too" in line, line


def test_the_validation_page_opens_with_every_target_it_does_not_meet():
    """docs/validation.md opened on 62 runs' table, and the targets table came after it with no
    word on top of what is met: a reader had to find that the slump's height at S = 0.2 and 0.3
    is outside the 1-D theory's 10 %. The report now opens with each row of the targets table
    that is not met in full, as the table says it, and the page holds that opening."""
    import json as _json

    from benchmarks.validation_report import _apart, _summary, _targets

    docs = pathlib.Path(__file__).resolve().parent.parent / "docs"
    rows = _json.loads((docs / "validation.json").read_text())["results"]
    targets = _targets(rows, _json.loads((docs / "mpm_slump.json").read_text()))
    opening = _summary(targets)
    page = (docs / "validation.md").read_text()
    assert opening and opening in page and page.index(opening) < page.index("| run | command |")
    listed = [t for t, _, met, _ in targets if f"- {t}: {met}\n" in opening]
    # A verdict opens the entry or follows a colon: "yes", "no (S = 0.2)", "converging: not shown".
    verdicts = {t: re.findall(r"(?:^|: )(yes|no|not shown)\b", met) for t, _, met, _ in targets}
    assert all(verdicts.values())
    assert listed == [t for t, v in verdicts.items() if set(v) != {"yes"}]
    assert any(t.startswith("slump height within 10 %") and "S = 0.2" in met and "S = 0.3" in met
               for t, _, met, _ in targets if t in listed)
    # A row met in full is not listed, and the count says how many are: the suite's floor's
    # (the Tresca ground) and the ghost floor's in the headline, the particle floor's apart.
    assert not any(met == "yes" for t, _, met, _ in targets if t in listed)
    suite = [t for t, _, _, _ in targets if not _apart(t)]
    apart = [t for t, _, _, _ in targets if _apart(t)]
    assert apart, "docs/validation.json holds no particle-floor rows"
    unmet = [t for t in suite if t in listed]
    assert f"**In short**: {len(suite) - len(unmet)} of the {len(suite)} rows" in opening
    unmet = [t for t in apart if t in listed]
    assert f"{len(apart) - len(unmet)} of its {len(apart)} rows are met in full" in opening
