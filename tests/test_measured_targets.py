"""Measured position data as fit targets: gaps (NaN, an occluded marker) in position
targets, point-cloud files as a lab writes them, and what the readers make of lab data.

Gradients are judged in float64 against central finite differences.
"""

import warnings

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from warp_esph.fit import _warn_target_scale, load_target
from warp_esph.losses import PositionLoss
from warp_esph.rollout import Rollout

DT = 1.0e-3
STEPS = 4
FRAMES = [2, 4]


def _block():
    """A 3x3x3 block thrown sideways, float64: a loss on its positions reaches mu and v0."""
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, -9.81, 0.0))
    b.add_box((0.0, 0.0, 0.0), (0.06, 0.06, 0.06),
              we.Material(density=1000.0, mu=1.0e3, lam=1.5e3, yield_stress=10.0, flow_rate=50.0))
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    model.particle_x0 += np.random.default_rng(5).normal(scale=2e-5, size=model.particle_x0.shape)
    model.particle_v0 = 20.0 * model.particle_x0 * np.array([1.0, -0.5, 0.3])
    return model


def _gappy(x, rng):
    """``x`` (frames, n, 3) moved a little, with a few particles missing (NaN) per frame."""
    t = x + rng.normal(scale=1e-3, size=x.shape)
    for k in range(len(t)):
        t[k, rng.choice(t.shape[1], 3 + k, replace=False)] = np.nan
    return t


def _numpy_loss(x, t):
    seen = np.isfinite(t).all(axis=2)
    d = np.where(seen[..., None], x - np.nan_to_num(t), 0.0)
    return float(np.sum(d * d) / seen.sum()), int(seen.sum())


def test_missing_target_points_drop_out_of_value_residuals_and_counts():
    """A NaN row is a missing observation: the loss is the mean over the observed
    (frame, particle) pairs, the residual vector holds only theirs, and the count that the
    diagnostics' degrees of freedom come from is 3 per observed pair. (Such a target was
    refused whole as 'non-finite values'.)"""
    rng = np.random.default_rng(0)
    x = rng.uniform(0.0, 0.1, (2, 10, 3))
    t = _gappy(x, rng)
    loss = PositionLoss(t, frames=[3, 7])
    positions = {3: x[0], 7: x[1]}
    expect, pairs = _numpy_loss(x, t)
    assert loss(positions) == pytest.approx(expect, rel=1e-12, abs=0.0)
    r = loss.residuals(positions)
    assert len(r) == 3 * pairs == loss.observation_count()
    assert np.isfinite(r).all()
    assert loss.residual_scale() * loss(positions) == pytest.approx(float(np.sum(r * r)), rel=1e-12, abs=0.0)
    # A particle missing everywhere is the same as leaving it out by ``particles``.
    t2 = x + 1e-3
    t2[:, 4] = np.nan
    keep = [i for i in range(10) if i != 4]
    gone = PositionLoss(t2, frames=[3, 7])
    subset = PositionLoss(t2[:, keep], frames=[3, 7], particles=keep)
    assert gone(positions) == pytest.approx(subset(positions), rel=1e-12, abs=0.0)
    # The position gradient of a missing particle is 0 at that frame only.
    _, g = loss.value_and_grad({f: wp.array(p, dtype=wp.vec3d) for f, p in positions.items()})
    for k, f in enumerate([3, 7]):
        gf = g[f].numpy()
        missing = ~np.isfinite(t[k]).all(axis=1)
        assert np.all(gf[missing] == 0.0) and np.all(np.abs(gf[~missing]).sum(axis=1) > 0.0)


def test_gradients_with_missing_targets_match_central_differences():
    """d loss / d mu and d loss / d v0 through a rollout, with markers missing at each
    frame, vs central differences (float64)."""
    model = _block()
    r = Rollout(model, STEPS, DT, frames=FRAMES)
    x = np.stack(r.forward())
    loss = PositionLoss(_gappy(x, np.random.default_rng(1)), frames=FRAMES)
    _, grads = r.value_and_grad(loss)
    base = r.get_parameters()

    def value(params=None, v0=None):
        r.set_parameters(params or base)
        r.forward(v0=v0)
        return loss.value(dict(zip(r.frames, r.frame_positions)))

    h = 1e-5 * base["mu"][0]
    plus, minus = ({k: v.copy() for k, v in base.items()} for _ in range(2))
    plus["mu"] += h
    minus["mu"] -= h
    fd = (value(plus) - value(minus)) / (2 * h)
    assert abs(fd) > 1e-14
    assert grads["mu"][0] == pytest.approx(fd, rel=1e-4, abs=0.0)
    for i, c in ((0, 0), (5, 1), (13, 2)):
        vals = []
        for d in (1e-6, -1e-6):
            v = model.particle_v0.copy()
            v[i, c] += d
            vals.append(value(v0=v))
        assert grads["v0"][i, c] == pytest.approx((vals[0] - vals[1]) / 2e-6, rel=1e-4, abs=0.0)


def test_positions_missing_everywhere_or_in_a_whole_frame_are_refused_by_name():
    t = np.zeros((2, 4, 3))
    t[1] = np.nan
    with pytest.raises(ValueError, match=r"^targets at step 9 are not allowed: every point there is NaN \(missing\)"):
        PositionLoss(t, frames=[5, 9])
    t[:] = np.nan
    with pytest.raises(ValueError, match=r"^targets at every step are not allowed: every point there is NaN"):
        PositionLoss(t, frames=[5, 9])
    t = np.zeros((4, 3))
    t[2, 1] = np.inf  # an overflow is no gap
    with pytest.raises(ValueError, match=r"^targets at step 5 is not allowed: it has non-finite values \(first at point 2"):
        PositionLoss({5: t})


def test_a_positions_file_holding_arrays_the_reader_does_not_read_is_refused_naming_them(tmp_path):
    """A lab's .npz of markers with a 'times' array (seconds from a clock not at 0, or in ms)
    in place of 'frames' and 'fps' was read as frames 0..K-1 at the scene's rate, the times
    dropped without a word: a run 100 s long was fitted as if it took K frames. Every array
    other than positions, frames and fps is refused by name; the same positions with frames
    and fps read."""
    x0 = _block().particle_x0
    x = np.stack([x0 + 0.001 * k for k in range(3)])
    np.savez(tmp_path / "timed.npz", positions=x, times=np.array([12.0, 12.5, 13.0]))
    with pytest.raises(ValueError, match=r"target .*timed\.npz is not allowed: it holds the array 'times', which a positions "
                                         r"target does not read \(allowed: positions, frames, fps\); 'times' is not read: "
                                         r"store the frame of each entry as 'frames'"):
        load_target(tmp_path / "timed.npz")
    np.savez(tmp_path / "labelled.npz", positions=x, frames=[0, 1, 2], fps=2.0, labels=np.array(["a", "b"]),
             units=np.array("mm"))
    with pytest.raises(ValueError, match=r"labelled\.npz is not allowed: it holds the arrays 'labels', 'units', which"):
        load_target(tmp_path / "labelled.npz")
    np.savez(tmp_path / "framed.npz", positions=x, frames=[0, 1, 2], fps=2.0)
    t = load_target(tmp_path / "framed.npz")
    assert (t.frames, t.fps) == ([0, 1, 2], 2.0)


def test_a_positions_file_with_gaps_is_read_and_fitted_by_its_observed_markers(tmp_path):
    """An .npz of a motion-capture export with occluded markers (NaN) is read; its frames
    keep their gaps, a frame with no marker seen is left out with a warning, a file of
    nothing but NaN or with an inf is refused by its name."""
    model = _block()
    n = model.particle_count
    x = np.stack([model.particle_x0 + 0.001 * k for k in range(4)])
    x[1, 3] = np.nan
    x[2] = np.nan
    x[3, :5] = np.nan
    np.savez(tmp_path / "mocap.npz", positions=x, frames=[0, 1, 2, 3])
    t = load_target(tmp_path / "mocap.npz")
    with pytest.warns(UserWarning, match=r"mocap\.npz: frame 2 observes no particle \(every position NaN, missing\) and is left out"):
        loss = t.loss(model, {0: 0, 1: 10, 2: 20, 3: 30})
    assert loss.frames == (10, 30)
    assert [int(loss.observed[f].sum()) for f in loss.frames] == [n - 1, n - 5]
    np.savez(tmp_path / "blank.npz", positions=np.full((2, n, 3), np.nan))
    with pytest.raises(ValueError, match=r"target .*blank\.npz is not allowed: every position in it is NaN \(missing\)"):
        load_target(tmp_path / "blank.npz")
    x[3, 7, 1] = -np.inf
    np.save(tmp_path / "inf.npy", x)
    with pytest.raises(ValueError, match=r"target .*inf\.npy is not allowed: it has an infinite position \(frame entry 3, "
                                         r"particle 7\); a missing one \(an occluded marker\) is NaN"):
        load_target(tmp_path / "inf.npy")


def test_a_millimetre_target_with_gaps_is_still_warned_of():
    """The units check (positions 20 times the scene's spread) read a frame with a missing
    marker as a spread of NaN, and said nothing of a target in millimetres."""
    model = _block()
    t = np.stack([model.particle_x0 * 1000.0] * 2)
    t[:, 0] = np.nan
    with pytest.warns(UserWarning, match=r"targets in other units than metres"):
        _warn_target_scale(PositionLoss(t, frames=[2, 4]), model, "target")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _warn_target_scale(PositionLoss(t / 1000.0, frames=[2, 4]), model, "target")


def test_the_plan_line_measures_entry_zero_over_its_observed_markers(tmp_path):
    """The plan's line on an unnumbered file says how far its entry 0 lies from the scene's
    start; with a marker missing there it said 'nan spacings'."""
    from warp_esph.calibrate import _frame_reading  # noqa: PLC0415

    model = _block()
    x = np.stack([model.particle_x0 + 0.5 * model.spacing, model.particle_x0])
    x[0, 2] = np.nan
    np.save(tmp_path / "gaps.npy", x)
    line = _frame_reading(tmp_path / "gaps.npy", load_target(tmp_path / "gaps.npy"), False, model)
    assert f"lies {0.5 * np.sqrt(3.0):.3g} spacings RMS from the scene's initial positions" in line  # (h/2)(1, 1, 1)


@pytest.mark.parametrize("name, text", [
    ("header.csv", "x,y,z\n0.1,0.2,0.3\n0.2,0.25,0.3\n"),
    ("bom.csv", "\ufeff0.1,0.2,0.3\n0.2,0.25,0.3\n"),
    ("bom_header.csv", "\ufeffX,Y,Z\r\n0.1,0.2,0.3\r\n0.2,0.25,0.3\r\n"),
    ("ids_first.csv", "marker,z,x,y (m)\n7,0.3,0.1,0.2\n8,0.3,0.2,0.25\n"),
    ("header.xyz", "# scanner export\nx y z\n0.1 0.2 0.3\n0.2 0.25 0.3\n"),
    # 'quantity / unit', as ISO 80000 writes a column head: refused as naming no x, y, z.
    ("slash.csv", "x / m,y / m,z / m\n0.1,0.2,0.3\n0.2,0.25,0.3\n"),
])
def test_a_cloud_text_file_with_a_header_row_or_a_byte_order_mark_is_read(tmp_path, name, text):
    """A spreadsheet's CSV starts with a byte-order mark, a scanner's with a header row
    naming its columns; both were refused with numpy's "could not convert string". The
    columns named x, y, z are read, whatever else the file holds and in whatever order."""
    (tmp_path / name).write_bytes(text.encode("utf-8"))
    t = load_target(tmp_path / name)
    assert t.kind == "points"
    np.testing.assert_array_equal(t.data, [[0.1, 0.2, 0.3], [0.2, 0.25, 0.3]])


@pytest.mark.parametrize("name, text, message", [
    ("mm.csv", "x (mm),y (mm),z (mm)\n100,200,300\n", r"its header gives the coordinates in mm; positions are metres"),
    ("slash_mm.csv", "x / mm,y / mm,z / mm\n100,200,300\n", r"its header gives the coordinates in mm; positions are metres"),
    ("names.csv", "u,v,w\n1,2,3\n", r"its first row 'u,v,w' is a header that names no columns x, y and z"),
    ("semicolons.csv", "x;y;z\n0,1;0,2;0,3\n", r"its fields are separated by semicolons"),
    ("ragged.csv", "0.1,0.2,0.3\n0.4,0.5\n", r"line 2 has 2 columns, line 1 has 3; every line of a point cloud holds "
                                             r"the same number of columns$"),
    ("flat.xyz", "0.1 0.2\n0.3 0.4\n", r"is not allowed as a point cloud: it holds points of shape \(2, 2\)"),
    ("empty.xyz", "", r"is not allowed as a point cloud: it holds no points"),
    ("header_only.csv", "x,y,z\n", r"is not allowed as a point cloud: it holds no points"),
    # A force log cut after its preamble: told of points alone, as if it were taken for a cloud.
    ("preamble_only.csv", "# Instron 5965\n# 23 C\n", r"it holds no points; it needs one or more points of three "
                                                       r"coordinates \(x y z\); nor is it a force log, which needs a "
                                                       r"header naming frame, time, tool, fx, fy, fz$"),
    # A column named twice: the first was read and the other left without a word (two markers a
    # row fitted the first marker's points alone; 'X [mm]' beside 'x' was not even unit-checked).
    ("two_markers.csv", "x,y,z,x,y,z\n0.1,0.2,0.3,0.5,0.6,0.7\n",
     r"its header names the column x twice \('x' in column 1, 'x' in column 4\); which one to read is not ours to "
     r"choose: give one point a row, its columns x, y, z named once$"),
    ("mm_beside.csv", "x,y,z,Z [mm]\n0.1,0.2,0.3,300\n", r"its header names the column z twice \('z' in column 3, "
                                                           r"'Z \[mm\]' in column 4\)"),
])
def test_a_cloud_text_file_that_is_no_cloud_in_metres_is_refused_by_name(tmp_path, name, text, message):
    (tmp_path / name).write_text(text)
    with pytest.raises(ValueError, match=rf"^target .*{name.replace('.', r'[.]')} .*{message}"):
        load_target(tmp_path / name)


@pytest.mark.parametrize("shape", [(6,), (5, 2), (7, 4), (0, 3)])
def test_an_npy_of_no_positions_or_cloud_shape_says_both_are_allowed(tmp_path, shape):
    np.save(tmp_path / "a.npy", np.zeros(shape))
    with pytest.raises(ValueError, match=r"positions must be \(K, n, 3\) or \(n, 3\) with K, n >= 1 \(an \(M, 3\) \.npy of "
                                         r"another count than the scene's particles is a point cloud\)$"):
        load_target(tmp_path / "a.npy")


def test_markers_numbered_otherwise_than_the_particles_are_refused_by_frame_zero(tmp_path):
    """A lab's positions compare marker i with particle i. Markers in another order passed,
    and the fit pulled each particle toward another's path; where the file's frame 0 holds
    the scene's start point for point in another order, it is refused naming a marker."""
    model = _block()
    n = model.particle_count
    x0 = model.particle_x0 + np.random.default_rng(2).normal(scale=1e-4, size=(n, 3))
    x = np.stack([x0, x0 + 0.001])
    order = np.arange(n)
    order[[3, 8]] = order[[8, 3]]  # two markers' labels swapped
    np.savez(tmp_path / "swapped.npz", positions=x[:, order], frames=[0, 1])
    with pytest.raises(ValueError, match=r"swapped\.npz is not allowed: its frame 0 holds the scene's initial positions in "
                                         rf"another order \(2 of {n} observed markers on another particle's start; marker 3 "
                                         r"on particle 8's\); particles are compared by index"):
        load_target(tmp_path / "swapped.npz").loss(model, {0: 0, 1: 10})
    # In order (with a marker missing at frame 0), or a frame 0 that is no start at all: read.
    x[0, 5] = np.nan
    np.savez(tmp_path / "ordered.npz", positions=x, frames=[0, 1])
    assert load_target(tmp_path / "ordered.npz").loss(model, {0: 0, 1: 10}).frames == (10,)
    np.savez(tmp_path / "moved.npz", positions=x[:, order] + 0.3, frames=[0, 1])
    assert load_target(tmp_path / "moved.npz").loss(model, {0: 0, 1: 10}).frames == (10,)


def test_a_fit_to_gappy_positions_counts_only_the_observed_residuals():
    """The diagnostics' residual count (their degrees of freedom) is 3 per observed
    (frame, particle) pair, and the residual RMS stays finite."""
    from warp_esph.fit import fit  # noqa: PLC0415

    r = Rollout(_block(), STEPS, DT, frames=FRAMES)
    t = _gappy(np.stack(r.forward()), np.random.default_rng(3))
    res = fit(_block(), PositionLoss(t, frames=FRAMES), ["mu"], steps=STEPS, dt=DT, iterations=2, noise=1e-3,
              progress=False)
    assert res.diagnostics.observations == 3 * int(np.isfinite(t).all(axis=2).sum()) < t.size
    assert np.isfinite(res.diagnostics.residual_rms).all()


CLOUD = [[0.1, 0.2, 0.3], [0.2, 0.25, 0.3], [0.15, 0.22, 0.31]]


def _cloud_lines(sep=",", first=None):
    rows = CLOUD if first is None else [[f, *p] for f, p in zip(first, CLOUD)]
    return "".join(sep.join(repr(v) for v in row) + "\n" for row in rows)


@pytest.mark.parametrize("name, first", [("ids0.csv", [0, 1, 2]), ("ids1.csv", [1, 2, 3]), ("ids1.xyz", [1, 2, 3]),
                                         ("ids7.txt", [7, 8, 9]), ("gap.csv", [1, 2, 4])])
def test_a_headerless_cloud_whose_first_column_counts_its_rows_is_refused(tmp_path, name, first):
    """A lab's marker export without a header, 'id, x, y, z', was read as x, y, z: the ids
    taken for x (metres), the z column dropped, and the fit ran against a cloud that never
    was. A first column of consecutive whole numbers beside three more is refused, saying
    how a header row tells which columns are x, y, z; with that header it is read."""
    sep = "," if name.endswith(".csv") else " "
    (tmp_path / name).write_text(_cloud_lines(sep, first))
    with pytest.raises(ValueError, match=rf"^target .*{name.replace('.', '[.]')} cannot be read as a point cloud: its first "
                                         rf"column numbers its rows in order \({first[0]}, {first[1]}, \.\.\., {first[-1]}: "
                                         r"a marker or point id\?\) beside 3 more columns, and a cloud without a header row "
                                         r"is read as x, y, z from its first three columns: add a header row naming them"):
        load_target(tmp_path / name)
    (tmp_path / name).write_text(sep.join(["id", "x", "y", "z"]) + "\n" + _cloud_lines(sep, first))
    np.testing.assert_array_equal(load_target(tmp_path / name).data, CLOUD)


def test_a_headerless_table_of_markers_per_frame_is_refused_as_no_cloud(tmp_path):
    """A lab's long table 'frame, marker, x, y, z' without a header was read as a cloud of
    (frame, marker, x) points."""
    rows = "".join(f"{f},{m},{0.1 * m + 0.01 * f!r},0.2,0.3\n" for f in (0, 1) for m in (0, 1, 2))
    (tmp_path / "long.csv").write_text(rows)
    with pytest.raises(ValueError, match=r"long\.csv cannot be read as a point cloud: its first column holds whole numbers in "
                                         r"order, some repeated \(0 to 1: a frame number of a table of frames\?\) beside 4 "
                                         r"more columns, .*: a table of markers per frame is no point cloud: give positions "
                                         r"per frame as an \.npz"):
        load_target(tmp_path / "long.csv")


def test_a_headerless_cloud_of_three_columns_or_of_no_counted_column_is_read_as_before(tmp_path):
    """Only four columns or more with a counting first column are refused: three columns are
    x, y, z whatever they hold, and a fourth column after them (an intensity) is read past."""
    (tmp_path / "three.csv").write_text("0,0.2,0.3\n1,0.25,0.3\n2,0.22,0.31\n")
    np.testing.assert_array_equal(load_target(tmp_path / "three.csv").data, [[0, 0.2, 0.3], [1, 0.25, 0.3], [2, 0.22, 0.31]])
    (tmp_path / "intensity.csv").write_text("".join(f"{x!r},{y!r},{z!r},{k}\n" for k, (x, y, z) in enumerate(CLOUD)))
    np.testing.assert_array_equal(load_target(tmp_path / "intensity.csv").data, CLOUD)
    # A flat scan at x = 0 (one whole number throughout) is a cloud.
    (tmp_path / "flat.csv").write_text("".join(f"0,{y!r},{z!r},7\n" for _, y, z in CLOUD))
    np.testing.assert_array_equal(load_target(tmp_path / "flat.csv").data, [[0.0, y, z] for _, y, z in CLOUD])


@pytest.mark.parametrize("name, xs", [
    # A lattice centred on 0, sorted by x: no id or frame is negative.
    ("centred.xyz", [-2, -2, -1, -1, 0, 0, 1, 1, 2, 2]),
    ("negative_line.xyz", [-5, -4, -3, -2, -1]),
    # Sorted by x at a spacing of 2 or 5: rows are counted by 1, frames follow one another.
    ("spacing2.xyz", [0, 0, 0, 2, 2, 2, 4, 4, 4]),
    ("spacing5.xyz", [0, 5, 10, 15, 20]),
])
def test_a_headerless_scan_whose_x_holds_sorted_whole_numbers_is_read(tmp_path, name, xs):
    """'x y z intensity' of a scan on a lattice of whole coordinates, sorted by x, was
    refused as a marker id ('numbers its rows in order (-5, -4, ..., -1: a marker or point
    id?)', '(0, 5, ..., 20: ...)') or as the frame of a table of frames ('0, 0, 0, 2, 2,
    2'): it had been read, and is. An id or a frame is never negative, ids count rows by 1
    (a dropped marker leaves a gap, not a stride), and frames follow one another."""
    rows = [(x, 0.1 * k, 0.2 + 0.01 * (k % 3)) for k, x in enumerate(xs)]
    (tmp_path / name).write_text("".join(f"{x} {y!r} {z!r} {k % 7}\n" for k, (x, y, z) in enumerate(rows)))
    np.testing.assert_array_equal(load_target(tmp_path / name).data, rows)


def test_a_cloud_point_of_nan_is_a_missing_point_left_out_with_a_warning(tmp_path):
    """A NaN in a position target is a missing marker; a point cloud's was refused ('every
    point must be finite'), though a cloud is unordered and a NaN row can only be a point
    not seen. It is left out with a warning naming how many; a cloud of nothing but NaN, or
    an infinite coordinate, is refused by name."""
    (tmp_path / "gap.csv").write_text("x,y,z\n0.1,0.2,0.3\nnan,nan,nan\n0.2,nan,0.3\n0.2,0.25,0.3\n")
    with pytest.warns(UserWarning, match=r"gap\.csv: 2 of its 4 points have a NaN coordinate \(missing\) and are left out "
                                         r"\(2 points\)"):
        t = load_target(tmp_path / "gap.csv")
    np.testing.assert_array_equal(t.data, [[0.1, 0.2, 0.3], [0.2, 0.25, 0.3]])
    (tmp_path / "none.xyz").write_text("nan nan nan\nnan 0.1 0.2\n")
    with pytest.raises(ValueError, match=r"none\.xyz is not allowed as a point cloud: every point has a NaN coordinate "
                                         r"\(missing\); it observes nothing"):
        load_target(tmp_path / "none.xyz")
    (tmp_path / "inf.xyz").write_text("0.1 0.2 0.3\n0.1 inf 0.2\n")
    with pytest.raises(ValueError, match=r"inf\.xyz is not allowed as a point cloud: point 1 is \[0\.1, inf, 0\.2\]; a "
                                         r"coordinate must be finite, or NaN for a missing point"):
        load_target(tmp_path / "inf.xyz")


@pytest.mark.parametrize("name, text", [
    ("tabs.csv", _cloud_lines("\t")),
    ("commas.txt", _cloud_lines(",")),
    ("commas.xyz", _cloud_lines(", ")),
    ("trailing_commas.csv", _cloud_lines(",").replace("\n", ",\n")),
    ("empty_rows.csv", "x,y,z\r\n" + _cloud_lines(",").replace("\n", "\r\n") + ",,\r\n,,\r\n\r\n"),
    ("comma_header.txt", "x,y,z\n" + _cloud_lines(" ")),
])
def test_a_cloud_as_lab_software_writes_it_is_read(tmp_path, name, text):
    """Tab-separated '.csv' files, comma-separated '.txt'/'.xyz', a comma after every line
    and a spreadsheet's empty rows at the end were refused, the first three as 'a header
    that names no columns x, y and z' though their first row is numbers, the last as
    "could not convert string ''" at a row number of numpy's counting."""
    (tmp_path / name).write_text(text)
    np.testing.assert_array_equal(load_target(tmp_path / name).data, CLOUD)


def test_a_cloud_line_that_cannot_be_read_is_named_by_its_line_in_the_file(tmp_path):
    """numpy numbered rows from 0 for a bad number and from 1 for a short row, counting
    neither the header nor comments: the line said was not the file's."""
    (tmp_path / "bad.csv").write_text("# scanner\nx,y,z\n0.1,0.2,0.3\n\n0.2,O.3,0.4\n")
    with pytest.raises(ValueError, match=r"bad\.csv cannot be read as a point cloud: line 5, column 2: 'O\.3' is not a "
                                         r"number$"):
        load_target(tmp_path / "bad.csv")
    (tmp_path / "na.csv").write_text("x,y,z\n0.1,0.2,0.3\n0.2,NA,0.4\n")
    with pytest.raises(ValueError, match=r"na\.csv cannot be read as a point cloud: line 3, column 2: 'NA' is not a number; "
                                         r"a point not seen is a row of nan \(or no row\)$"):
        load_target(tmp_path / "na.csv")
    (tmp_path / "short.csv").write_text("# scanner\nx,y,z\n0.1,0.2,0.3\n0.2,0.3\n")
    with pytest.raises(ValueError, match=r"short\.csv cannot be read as a point cloud: line 4 has 2 columns, line 3 has "
                                         r"3; every line of a point cloud holds the same number of columns$"):
        load_target(tmp_path / "short.csv")


def test_a_chamfer_loss_given_a_nan_point_says_to_leave_it_out():
    """The Python API's refusal of a NaN cloud point said only 'non-finite values', where a
    position target takes NaN as a missing marker: it now says how a cloud holds a point
    not seen (by leaving it out)."""
    from warp_esph.losses import ChamferLoss  # noqa: PLC0415

    with pytest.raises(ValueError, match=r"^targets at step 2 is not allowed: it has non-finite values \(first at point 1: "
                                         r"\[nan, 0\.2, 0\.3\]\); a cloud is unordered: leave a point not seen out of it"):
        ChamferLoss(np.array([[0.1, 0.2, 0.3], [np.nan, 0.2, 0.3]]), radius=0.05, frames=[2])


def test_a_pts_file_that_starts_with_its_point_count_is_read(tmp_path):
    """A Leica .pts (as CloudCompare writes it) starts with a line holding its point count,
    then 'x y z intensity r g b': refused as 'line 2 has 7 columns, line 1 has 1'. The count
    line is read past where it is the number of points that follow; another count (a file
    cut short) is refused saying both."""
    rows = "".join(f"{x!r} {y!r} {z!r} -1200 90 80 70\n" for x, y, z in CLOUD)
    (tmp_path / "scan.pts").write_text(f"{len(CLOUD)}\n" + rows)
    np.testing.assert_array_equal(load_target(tmp_path / "scan.pts").data, CLOUD)
    (tmp_path / "cut.pts").write_text(f"{len(CLOUD) + 5}\n" + rows)
    with pytest.raises(ValueError, match=r"cut\.pts cannot be read as a point cloud: its first line says it holds 8 points, "
                                         r"and 3 follow \(a file cut short\?\)"):
        load_target(tmp_path / "cut.pts")


def test_a_cloud_of_decimal_commas_is_refused_as_such(tmp_path):
    """'0,1 0,2 0,3' (a locale of decimal commas) was refused as a header naming no columns
    x, y and z."""
    (tmp_path / "comma.txt").write_text("0,1 0,2 0,3\n0,2 0,25 0,3\n")
    with pytest.raises(ValueError, match=r"comma\.txt cannot be read as a point cloud: its numbers have decimal commas "
                                         r"\('0,1'\); write them with a decimal point"):
        load_target(tmp_path / "comma.txt")


def test_a_cloud_with_a_time_or_frame_column_is_read_as_a_cloud_or_refused_as_a_table_of_frames(tmp_path):
    """A cloud whose header names x, y, z and a 'time' column (a scanner's time stamp per
    point) or a 'frame' column was refused as a force log lacking fx, fy, fz. It is a cloud
    where that column takes one value, or a time its own per point; where its values repeat
    (several points per frame) it is a table of positions over frames, which a cloud would
    merge into one: refused saying so."""
    (tmp_path / "stamped.csv").write_text("x,y,z,time\n" + "".join(f"{x!r},{y!r},{z!r},{0.1 * k!r}\n"
                                                                  for k, (x, y, z) in enumerate(CLOUD)))
    np.testing.assert_array_equal(load_target(tmp_path / "stamped.csv").data, CLOUD)
    (tmp_path / "one_frame.csv").write_text("frame,x,y,z\n" + _cloud_lines(",", [7, 7, 7]))
    np.testing.assert_array_equal(load_target(tmp_path / "one_frame.csv").data, CLOUD)
    (tmp_path / "frames.csv").write_text("frame,x,y,z\n" + _cloud_lines(",", [0, 0, 1]))
    with pytest.raises(ValueError, match=r"frames\.csv cannot be read as a point cloud: its column 'frame' holds 2 different "
                                         r"values over 3 rows: a table of positions over frames, which one cloud would "
                                         r"merge; give positions per frame as an \.npz \('positions' \(K, n, 3\), 'frames'\), "
                                         r"or one frame's points as a cloud"):
        load_target(tmp_path / "frames.csv")


@pytest.mark.parametrize("name, head", [("temperature.csv", "X,Y,Z,T (degC)"), ("kelvin.txt", "x y z t[K]"),
                                        ("slash.xyz", "x y z T/degC")])
def test_a_cloud_column_named_t_in_a_unit_of_no_time_is_no_time_stamp(tmp_path, name, head):
    """A thermal scan's 'T (degC)' beside x, y, z was taken for a time stamp ('t'), and a
    temperature shared by two points refused as 'its column 'T (degC)' holds 2 different
    values over 3 rows: a table of positions over frames'. A column in a unit that is no
    time's is no time stamp: read past, as any other column is."""
    sep = "," if name.endswith(".csv") else " "
    rows = [[*p, t] for p, t in zip(CLOUD, (21.5, 21.5, 21.7))]
    (tmp_path / name).write_text(head + "\n" + "".join(sep.join(repr(v) for v in r) + "\n" for r in rows))
    np.testing.assert_array_equal(load_target(tmp_path / name).data, CLOUD)


def test_a_cloud_time_column_in_seconds_still_tells_a_table_of_frames_and_says_how_a_scan_is_read(tmp_path):
    """'time (s)' is a time stamp, and a time shared by several points is still refused as a
    table over frames; as a scanner stamps every point of one pulse or one profile with one
    time, the refusal also says how such a scan is read (the column left out or renamed)."""
    rows = [[*p, t] for p, t in zip(CLOUD, (0.001, 0.001, 0.002))]
    (tmp_path / "scan.csv").write_text("x,y,z,time (s)\n" + "".join(",".join(repr(v) for v in r) + "\n" for r in rows))
    with pytest.raises(ValueError, match=r"scan\.csv cannot be read as a point cloud: its column 'time \(s\)' holds 2 "
                                         r"different values over 3 rows: a table of positions over frames, which one cloud "
                                         r"would merge; .*; a scan whose points share a time stamp \(one pulse's returns, "
                                         r"one profile's points\) is read as one cloud with the column 'time \(s\)' left out "
                                         r"of the file, or with its header cell renamed 'scan_time', which is read past as "
                                         r"any column other than x, y, z is$"):
        load_target(tmp_path / "scan.csv")


@pytest.mark.parametrize("name, head, extra", [
    ("colours.txt", "//X,Y,Z,R,G,B", [[255, 0, 0], [0, 255, 0], [0, 0, 255]]),
    ("spaces.xyz", "//X Y Z", None),
    ("fields.txt", "//X Y Z R G B Scalar_field Intensity", [[1, 2, 3, 0.5, 7], [4, 5, 6, 0.6, 8], [7, 8, 9, 0.7, 9]]),
    ("lower.asc.txt", "// x y z", None),
    # Its point count under the header row, as CloudCompare writes both.
    ("count.txt", "//X,Y,Z\n3", None),
    # A scalar field named Time, a stamp per point: a .csv had been refused as a force log.
    ("stamped.csv", "//X,Y,Z,Time", [[0.0], [0.001], [0.002]]),
    # Its semicolon separator: refused as a header naming no x, y, z (and with no header, as one).
    ("semicolons.txt", "//X;Y;Z;R;G;B", [[255, 0, 0], [0, 255, 0], [0, 0, 255]]),
    ("semicolons_count.pts", "//X;Y;Z\n3", None),
    ("no_header.txt", ";", None),
])
def test_a_cloudcompare_ascii_export_whose_header_row_starts_with_slashes_is_read(tmp_path, name, head, extra):
    """CloudCompare's ASCII export writes its header row as '//X,Y,Z,R,G,B' (spaces for its
    space separator, its scalar fields' names after them); it was refused as a header that
    names no columns x, y and z. The '//' is read past and the columns X, Y, Z read."""
    sep = "," if "," in head else ";" if ";" in head else " "
    head = "" if head == sep else head + "\n"
    rows = [[*p, *(extra[k] if extra else [])] for k, p in enumerate(CLOUD)]
    (tmp_path / name).write_text(head + "".join(sep.join(repr(v) for v in r) + "\n" for r in rows))
    np.testing.assert_array_equal(load_target(tmp_path / name).data, CLOUD)


@pytest.mark.parametrize("name, text, message", [
    ("names.txt", "//U V W\n0.1 0.2 0.3\n", r"its first row '//U V W' is a header that names no columns x, y and z"),
    ("mm.txt", "//X (mm),Y (mm),Z (mm)\n100,200,300\n", r"its header gives the coordinates in mm"),
    ("cut.txt", "//X,Y,Z\n5\n0.1,0.2,0.3\n0.2,0.3,0.4\n", r"its line 2, under the header row, says it holds 5 points, and 2 follow"),
    # Semicolons read, but not beside decimal commas (a spreadsheet's locale): said of both, as
    # under a header it had been refused as a cell that is no number.
    ("commas.txt", "//X;Y;Z\n0,1;0,2;0,3\n", r"its fields are separated by semicolons and its numbers have decimal commas "
                                          r"\('0,1'\); write them with a decimal point \(x y z in metres, separated by "
                                          r"spaces, tabs, commas or semicolons\)$"),
    ("bare_commas.txt", "0,1;0,2;0,3\n", r"its fields are separated by semicolons and its numbers have decimal commas "
                                         r"\('0,1'\)"),
])
def test_a_slashed_header_row_is_refused_as_any_header_row_is(tmp_path, name, text, message):
    """With the '//' read past, a header row naming no x, y, z or another unit than metres, and
    a count the rows do not hold, are refused as they are without it."""
    (tmp_path / name).write_text(text)
    with pytest.raises(ValueError, match=rf"{name.replace('.', '[.]')} cannot be read as a point cloud: {message}"):
        load_target(tmp_path / name)


@pytest.mark.parametrize("name, sep", [("shared.txt", " "), ("shared.xyz", " "), ("shared.csv", ",")])
def test_a_time_shared_by_points_is_refused_with_how_to_read_the_scan_and_that_reads_it(tmp_path, name, sep):
    """'x y z time' where points share a time is a table of markers over frames or a scan
    (one laser pulse's returns, a line scanner's profile): the stamps cannot tell which. A
    line scanner's profiles hold one count of points each, in one order, as frames of the same
    markers do (the rows below are both: 3 markers over 2 frames, moving 1 mm in z, or 2
    profiles of 3 points swept 1 mm in z), and a tracker's table that leaves out a marker not
    seen has unequal counts per time, as a pulse's returns do. So it stays refused, and the
    refusal says exactly how a scan is read: the column left out, or its header renamed
    'scan_time'; it said 'left out or renamed', naming neither the column nor a name that
    is read past. Both cures, done as it says, read the file as one cloud."""
    pts = [[0.1, 0.2, 0.3], [0.2, 0.25, 0.3], [0.15, 0.22, 0.31],
           [0.1, 0.2, 0.301], [0.2, 0.25, 0.301], [0.15, 0.22, 0.311]]
    times = [0.0, 0.0, 0.0, 0.01, 0.01, 0.01]

    def write(head, rows):
        (tmp_path / name).write_text(sep.join(head) + "\n" + "".join(sep.join(repr(v) for v in r) + "\n" for r in rows))

    cure = (rf"{name.replace('.', '[.]')} cannot be read as a point cloud: its column 'time' holds 2 different values "
            r"over \d rows: a table of positions over frames, .*; a scan whose points share a time stamp \(one pulse's "
            r"returns, one profile's points\) is read as one cloud with the column 'time' left out of the file, or with "
            r"its header cell renamed 'scan_time'")
    write(["x", "y", "z", "time"], [[*p, t] for p, t in zip(pts, times)])
    with pytest.raises(ValueError, match=cure):
        load_target(tmp_path / name)
    # A marker not seen in the second frame, its row left out: 3 points, then 2.
    write(["x", "y", "z", "time"], [[*p, t] for p, t in zip(pts[:5], times[:5])])
    with pytest.raises(ValueError, match=cure):
        load_target(tmp_path / name)
    write(["x", "y", "z", "scan_time"], [[*p, t] for p, t in zip(pts, times)])
    np.testing.assert_array_equal(load_target(tmp_path / name).data, pts)
    write(["x", "y", "z"], pts)
    np.testing.assert_array_equal(load_target(tmp_path / name).data, pts)


@pytest.mark.parametrize("name, sep", [("stamps.csv", ","), ("stamps.txt", " ")])
def test_a_nan_time_stamp_is_no_repeat_of_another(tmp_path, name, sep):
    """A time column of distinct stamps per point, one of them NaN (a time not recorded), was
    refused as a table over frames: the NaN row was counted as a repeat. It is read as the
    cloud it is; a stamp shared by two points beside a NaN is still refused."""
    head = sep.join(["x", "y", "z", "time"]) + "\n"
    rows = [[*p, t] for p, t in zip(CLOUD, (0.001, float("nan"), 0.003))]
    (tmp_path / name).write_text(head + "".join(sep.join(repr(v) for v in r) + "\n" for r in rows))
    np.testing.assert_array_equal(load_target(tmp_path / name).data, CLOUD)
    rows = [[*p, t] for p, t in zip([*CLOUD, [0.3, 0.1, 0.2]], (0.001, float("nan"), 0.003, 0.003))]
    (tmp_path / name).write_text(head + "".join(sep.join(repr(v) for v in r) + "\n" for r in rows))
    with pytest.raises(ValueError, match=r"its column 'time' holds 2 different values over 3 rows \(and 1 of no "
                                         r"value\): a table of positions over frames"):
        load_target(tmp_path / name)


@pytest.mark.parametrize("name, sep", [("track.csv", ","), ("track.txt", " ")])
def test_a_frame_column_of_one_point_per_frame_is_a_track_not_a_cloud(tmp_path, name, sep):
    """'frame, x, y, z' with a frame of its own on every row is one marker tracked over
    frames: a cloud is one frame's points, and this one was read as a cloud of the marker's
    whole path (a '.csv' had been refused, as a force log; a '.txt' read so before the frame
    column was looked at). Refused as a table over frames, as a frame shared by several
    points is; a time stamp of its own per point stays a scanner's, read as a cloud."""
    (tmp_path / name).write_text(sep.join(["frame", "x", "y", "z"]) + "\n" + _cloud_lines(sep, [0, 1, 2]))
    with pytest.raises(ValueError, match=rf"{name.replace('.', '[.]')} cannot be read as a point cloud: its column 'frame' "
                                         r"holds 3 different values over 3 rows: a table of positions over frames, which "
                                         r"one cloud would merge; give positions per frame as an \.npz"):
        load_target(tmp_path / name)
    (tmp_path / name).write_text(sep.join(["time", "x", "y", "z"]) + "\n" + _cloud_lines(sep, [0.0, 0.001, 0.002]))
    np.testing.assert_array_equal(load_target(tmp_path / name).data, CLOUD)


def test_a_pts_count_below_the_points_that_follow_is_not_said_to_be_a_file_cut_short(tmp_path):
    """A .pts whose count line says fewer points than follow was refused as '(a file cut
    short?)', a cause that cannot give more points than counted."""
    rows = "".join(f"{x!r} {y!r} {z!r} -1200 90 80 70\n" for x, y, z in CLOUD)
    (tmp_path / "more.pts").write_text(f"{len(CLOUD) - 1}\n" + rows)
    with pytest.raises(ValueError, match=r"more\.pts cannot be read as a point cloud: its first line says it holds 2 "
                                         r"points, and 3 follow \(points added after the count was written\?\)$"):
        load_target(tmp_path / "more.pts")
