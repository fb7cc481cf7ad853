"""Parameter sweeps (warp_esph.sweep, ``warp-esph sweep``): sampling, the table, workers, Ray
(the tests that need a running Ray instance are in ``test_sweep_ray.py``).

The scene (``sweep_cases.py``) is a 125-particle box of toothpaste (2 cm spacing) dropped 1 cm onto the
ground, run for 10 frames at 30 fps (a third of a second): enough for a low yield stress
to slump visibly and a high one to stay a box.
"""

import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import time
import warnings

import numpy as np
import pytest
from PIL import Image

from warp_esph import cli
from warp_esph.builder import SceneBuilder
from warp_esph.material import Material
from warp_esph.scenes import Scene
from warp_esph.sim.smoothing import DEFAULT_FIT_WEIGHT
from warp_esph.sweep import SweepTable, _plan, parse_param, sample_points, sweep
from run_files import run_script
from pool_items import _dies_first, _dies_second, _exits_at
from sweep_cases import (FRAMES, SAMPLE_EXTRAS, YIELD, _box, _extra_by_sample, _extra_of_a_function,
                         _extra_raising_what_pickle_cannot_rebuild, _extra_that_exits, _extra_that_fails, _rows)

SCENE_TOML = """
[scene]
name = "paste_box"
spacing = 0.02
frames = 10
fps = 30

[materials.paste]
preset = "toothpaste"

[[bodies]]
shape = "box"
name = "paste"
material = "paste"
center = [0.0, 0.06, 0.0]
size = [0.1, 0.1, 0.1]

[[colliders]]
type = "ground"
friction = 0.5
"""


@pytest.fixture(scope="module")
def serial():
    return sweep(_box(), [YIELD], frames=FRAMES, workers=1)


@pytest.fixture
def scene_file(tmp_path):
    path = tmp_path / "box.toml"
    path.write_text(SCENE_TOML)
    return str(path)


# ------------------------------------------------------------------ sampling
def test_grid_is_every_combination_last_parameter_fastest():
    pts = sample_points(["yield_stress=100:1000:log:3", "flow_rate=50:500:lin:4"])
    assert len(pts) == 12
    ys = np.geomspace(100.0, 1000.0, 3)
    fr = np.linspace(50.0, 500.0, 4)
    expected = [(y, f) for y in ys for f in fr]
    assert [(p["yield_stress"], p["flow_rate"]) for p in pts] == expected
    # Log levels are equally spaced in log: 100, 316.2..., 1000.
    assert pts[4]["yield_stress"] == pytest.approx(math.sqrt(1e5), rel=1e-12)
    # Explicit values and a fixed value.
    pts = sample_points(["mu=1e3,2e3", "paste.flow_rate=7"])
    assert pts == [{"mu": 1e3, "paste.flow_rate": 7.0}, {"mu": 2e3, "paste.flow_rate": 7.0}]
    # A grid draws nothing: a seed was taken and ignored (the same points whatever it was).
    with pytest.raises(ValueError, match=r"^seed = 3 is not allowed with sample = 'grid': it seeds the draws of sample = "
                                         r"'random' and 'lhs', and a grid draws nothing$"):
        sample_points(["mu=1e3,2e3"], "grid", seed=3)


@pytest.mark.parametrize("n", [1, 5, 17])
@pytest.mark.parametrize("seed", [0, 3])
def test_lhs_uses_each_stratum_once(n, seed):
    specs = ["yield_stress=10:1000:log", "flow_rate=5:50"]
    pts = sample_points(specs, "lhs", n, seed)
    assert len(pts) == n
    y = np.array([p["yield_stress"] for p in pts])
    f = np.array([p["flow_rate"] for p in pts])
    # Strata are equal in log for a log parameter, equal in value for a linear one.
    sy = np.floor((np.log(y) - np.log(10.0)) / (np.log(1000.0) - np.log(10.0)) * n).astype(int)
    sf = np.floor((f - 5.0) / 45.0 * n).astype(int)
    assert sorted(sy) == list(range(n)) and sorted(sf) == list(range(n))
    assert sample_points(specs, "lhs", n, seed) == pts
    if n > 1:
        assert sample_points(specs, "lhs", n, seed + 1) != pts


def test_random_samples_stay_in_range_and_follow_the_seed():
    pts = sample_points(["yield_stress=10:1000:log", "flow_rate=5:50:lin"], "random", 200, 7)
    y = np.array([p["yield_stress"] for p in pts])
    f = np.array([p["flow_rate"] for p in pts])
    assert (y >= 10).all() and (y <= 1000).all() and (f >= 5).all() and (f <= 50).all()
    # Log-uniform: about half the draws below the geometric midpoint 100, not ~9 %.
    assert 0.35 < (y < 100.0).mean() < 0.65
    assert pts == sample_points(["yield_stress=10:1000:log", "flow_rate=5:50:lin"], "random", 200, 7)


# ------------------------------------------------------------------ physics and workers
def test_yield_stress_changes_the_slump(serial):
    assert [r["status"] for r in serial.rows] == ["ok"] * 3
    assert list(serial.column("sample")) == [0, 1, 2]
    y = serial.column("yield_stress")
    assert y == pytest.approx([10.0, 316.22776601683796, 10000.0])
    top = serial.column("max_height")
    spread = serial.column("radial_spread")
    # The box's top starts at 0.11 m: a higher yield stress flows less, so it stays taller
    # and narrower.
    assert top[0] < top[1] < top[2] < 0.11
    assert spread[0] > spread[1] > spread[2]
    assert serial.column("centroid_height")[0] < serial.column("centroid_height")[2]


def test_a_row_is_the_run_of_that_material(serial):
    """Sample 0 equals a plain run of the model with that yield stress, to the last bit."""
    from warp_esph.simulate import resolve_timestep, simulate

    model = _box().builder.finalize()
    model.set_material(0, model.materials[0].replace(yield_stress=10.0))
    _, dt = resolve_timestep(model, 30.0)
    state = simulate(model, FRAMES, fps=30.0, dt=dt, progress=False)
    x = state.x.numpy()
    row = serial.rows[0]
    assert row["max_height"] == float(x[:, 1].max())
    assert row["steps"] == FRAMES * round(1 / 30.0 / dt) and row["dt"] == dt


def test_two_workers_give_the_same_table(serial, tmp_path):
    parallel = sweep(_box(), [YIELD], frames=FRAMES, workers=2)
    assert parallel.columns == serial.columns
    assert _rows(parallel) == _rows(serial)
    # And the CSV round-trips every value exactly.
    back = SweepTable.read_csv(parallel.to_csv(tmp_path / "t.csv"))
    assert _rows(back) == _rows(parallel) and back.params == ["yield_stress"]


def test_a_ray_address_where_nothing_answers_is_refused_at_once(capsys, tmp_path):
    """``ray.init`` retried such an address for minutes, printing as it went; the command
    line now refuses it in one line, before the plan's."""
    from warp_esph.cli import main

    for address, reason in (("127.0.0.1:1", "nothing answers at 127.0.0.1:1"), ("nonsense", "give 'auto', HOST:PORT")):
        status = main(["sweep", "dough_drop", "--param", "yield_stress=100:1000:log:2", "--ray", address, "--no-progress",
                       "-o", str(tmp_path / "sw")])
        err = capsys.readouterr().err
        assert status == 2 and err.count("\n") == 1 and reason in err, err
    assert not (tmp_path / "sw").exists()


def test_every_ray_refusal_names_the_option_as_the_others_do(capsys, tmp_path, monkeypatch):
    """'--ray = '127.0.0.1:1' is not allowed: ...' for an address nothing answers at, but
    '--ray auto is not allowed: ...' where Ray is missing or cannot connect: one option, two
    wordings. Each now says '--ray = <value> is not allowed'."""
    from warp_esph.cli import main

    monkeypatch.setitem(sys.modules, "ray", None)  # as where Ray is not installed
    status = main(["sweep", "dough_drop", "--param", "yield_stress=100,1000", "--scale", "0.3", "--frames", "1",
                   "--ray", "auto", "--no-progress", "-o", str(tmp_path / "sw")])
    assert status == 2
    assert capsys.readouterr().err == ("warp-esph: error: --ray = 'auto' is not allowed: Ray is not installed; "
                                       "pip install 'warp-esph[ray]'\n")


def test_a_python_caller_s_ray_refusals_name_the_parameter_not_the_option(monkeypatch):
    """``parallel_map(..., ray=...)`` and ``sweep(..., ray=...)`` were refused as '--ray = ...
    is not allowed', and told to 'give --ray HOST:PORT': an option of the command line, which a
    Python caller has not. They name the parameter, ``ray``; the command its option."""
    ray = pytest.importorskip("ray")
    from warp_esph.sweep import parallel_map

    for address, reason in (("127.0.0.1:1", "nothing answers at 127.0.0.1:1 "), ("nonsense", "give 'auto', HOST:PORT")):
        with pytest.raises(ValueError, match=f"^ray = {re.escape(repr(address))} is not allowed: {re.escape(reason)}"):
            parallel_map(abs, [(1,)], ray=address)

    def no_cluster(*args, **kwargs):
        raise ConnectionError("Could not find any running Ray instance. Please specify the one to connect to by setting "
                              "the `--address` flag or `RAY_ADDRESS` environment variable.")

    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", no_cluster)
    with pytest.raises(ValueError, match=r"^ray = 'auto' is not allowed: cannot connect to a Ray cluster there: Could not "
                                         r"find any running Ray instance; give ray = 'HOST:PORT' or 'ray://HOST:PORT' of a "
                                         r"running cluster, or with ray = 'auto' start one on this machine first \('ray "
                                         r"start --head'\) or name its address in the RAY_ADDRESS environment variable$"):
        sweep(_box(), ["mu=1e3,1e4"], frames=1, ray="auto")
    monkeypatch.setitem(sys.modules, "ray", None)  # as where Ray is not installed
    with pytest.raises(ValueError, match=r"^ray = 'auto' is not allowed: Ray is not installed; pip install 'warp-esph\[ray\]'$"):
        parallel_map(abs, [(1,)], ray="auto")


def test_a_worker_count_with_ray_and_ray_resources_without_it_are_refused(tmp_path, monkeypatch, capsys):
    """Each was taken and ignored: with a Ray address the cluster runs one task per item, so
    ``workers`` (``--workers``) counted nothing; without one, ``ray_resources`` asked nobody.
    Refused before any connection (the address here answers nothing)."""
    from warp_esph.sweep import parallel_map

    said = ("is not allowed with {r} = '127.0.0.1:1': the Ray cluster runs one task per item on its own cores, and {w} "
            "counts the processes on this machine; give one of them")
    with pytest.raises(ValueError, match="^workers = 2 " + re.escape(said.format(w="workers", r="ray")) + "$"):
        parallel_map(abs, [(1,)], workers=2, ray="127.0.0.1:1")
    with pytest.raises(ValueError, match="^workers = 2 " + re.escape(said.format(w="workers", r="ray")) + "$"):
        sweep(_box(), ["mu=1e3,1e4"], frames=1, workers=2, ray="127.0.0.1:1")
    with pytest.raises(ValueError, match=r"^ray_resources = \{'num_cpus': 2\} is not allowed without ray: it is what each "
                                         r"Ray task asks the cluster for, and without ray the items run in processes here$"):
        parallel_map(abs, [(1,)], workers=1, ray_resources={"num_cpus": 2})
    # Its own parameter, not the command's option '--workers'.
    with pytest.raises(ValueError, match=r"^workers = 0 is not allowed: must be an integer >= 1$"):
        parallel_map(abs, [(1,)], workers=0)
    monkeypatch.chdir(tmp_path)
    assert cli.main(["sweep", "dough_drop", "--param", "mu=1e3,2e3", "--workers", "2", "--ray", "127.0.0.1:1"]) == 2
    err = capsys.readouterr().err
    assert err == "warp-esph: error: --workers = 2 " + said.format(w="--workers", r="--ray") + "\n", err
    assert list(tmp_path.iterdir()) == []


def test_ray_auto_without_a_cluster_says_what_the_command_takes(capsys, tmp_path, monkeypatch):
    """Ray's refusal of 'auto' with no cluster running advises its own command line's
    '`--address` flag', which warp-esph has not; the line says what --ray takes instead.
    Ray's own error is raised without starting anything, and before the plan's line
    ('... on Ray at auto -> ...'), which printed first: the error is the one stderr line."""
    ray = pytest.importorskip("ray")
    from warp_esph.cli import main

    def no_cluster(*args, **kwargs):
        raise ConnectionError("Could not find any running Ray instance. Please specify the one to connect to by setting "
                              "the `--address` flag or `RAY_ADDRESS` environment variable.")

    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", no_cluster)
    status = main(["sweep", "dough_drop", "--param", "yield_stress=100,1000", "--scale", "0.3", "--frames", "1",
                   "--ray", "auto", "--no-progress", "-o", str(tmp_path / "sw")])
    err = capsys.readouterr().err.splitlines()
    assert status == 2 and len(err) == 1 and err[0].startswith("warp-esph: error: "), err
    assert "--address" not in err[0], err
    assert err[0].endswith("--ray = 'auto' is not allowed: cannot connect to a Ray cluster there: Could not find any running "
                           "Ray instance; give --ray HOST:PORT or ray://HOST:PORT of a running cluster, or with --ray auto "
                           "start one on this machine first ('ray start --head') or name its address in the RAY_ADDRESS "
                           "environment variable"), err
    assert not (tmp_path / "sw").exists()


# ------------------------------------------------------------------ the command
def test_energy_blow_up_check_is_ten_times_the_energy_scale():
    """``simulate.energy_growth`` on an end state: at rest and in place, the energy grew by
    0.5 M u^2 for a uniform speed u, a blow-up past 10 x (KE0 + M |g| L) + 0.5 M (0.1 c_P)^2, i.e.
    u^2 > 20 |g| L + (0.1 c_P)^2 here."""
    from warp_esph.simulate import BLOWUP_FACTOR, energy_growth

    def _blew_up(model, state):
        hit = energy_growth(model, model.particle_x0, model.particle_v0, state.x.numpy(), state.v.numpy())
        return None if hit is None else hit[0]

    b = SceneBuilder(spacing=0.1)
    b.add_box((0.0, 0.5, 0.0), (0.3, 0.3, 0.3), Material.preset("putty"))
    model = b.finalize(dtype="float64")
    x0 = model.particle_x0.astype(np.float64)
    L = float(np.linalg.norm(x0.max(axis=0) - x0.min(axis=0))) + model.spacing
    c = float(model.wave_speeds(model.parameter_values()).max())
    u_limit = math.sqrt(2.0 * BLOWUP_FACTOR * float(np.linalg.norm(model.gravity)) * L + (0.1 * c) ** 2)
    for factor, blown in ((0.99, False), (1.01, True)):
        state = model.state()
        state.v.assign(np.tile([factor * u_limit, 0.0, 0.0], (model.particle_count, 1)))
        why = _blew_up(model, state)
        assert (why is not None) == blown, (factor, why)
        if blown:
            assert "blew up" in why
    assert _blew_up(model, model.state()) is None


def test_cli_records_a_blown_up_sample_and_exits_3(scene_file, tmp_path, capsys):
    out = tmp_path / "out"
    # dt = 1/300 s is stable for mu = 1e3 Pa and 20x above the limit for mu = 1e6 Pa.
    rc = cli.main(["sweep", scene_file, "--param", "paste.mu=1000,1000000", "--frames", "5", "--dt", "0.0033333333333333335",
                   "--workers", "1", "-o", str(out), "--no-progress"])
    captured = capsys.readouterr()
    assert rc == 3
    table = SweepTable.read_csv(out / "sweep.csv")
    assert [r["status"] for r in table.rows] == ["ok", "failed"]
    # simulate's divergence monitor (a speed far beyond what the scene can produce) stops
    # the run before the sweep's own energy check sees its end state (that check:
    # test_energy_blow_up_check_is_ten_times_the_energy_scale); the reason is its message.
    assert "the simulation diverged after step" in table.rows[1]["reason"] and table.rows[0]["reason"] is None
    # The reason alone and the stable step, no caller's option (it said 'try a smaller dt= (stable
    # limit ...)', a Python caller's parameter, where a refused start's row gave its reason alone).
    assert re.fullmatch(r"the simulation diverged after step \d+ \(frame \d+, t = \S+ s, dt = 0\.003333 s\): .*, at "
                        r"particle \d+ of body 'paste'; the sample's stable step is [\d.e-]+ s", table.rows[1]["reason"]), \
        table.rows[1]["reason"]
    assert "1 ok, 1 failed" in captured.out
    assert "sample 1 failed" in captured.err and "Traceback" not in captured.err
    assert (out / "sweep.json").exists()
    try:
        import pyarrow.parquet as pq
    except ImportError:
        assert "pyarrow is not installed" in captured.out
    else:
        back = pq.read_table(out / "sweep.parquet").to_pydict()
        assert back["paste.mu"] == [1000.0, 1000000.0] and back["status"] == ["ok", "failed"]
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        assert "matplotlib is not installed" in captured.out
    else:
        assert (out / "sweep.png").stat().st_size > 0


def test_cli_solver_options_override_the_scene_files(scene_file, tmp_path, capsys):
    """``--hourglass``, ``--solver-fit`` and ``--contact`` reach every sample's solver as the
    scene file's ``[solver]`` table does: the same rows, bit for bit, and other rows than
    without them; ``sweep.json`` records the options run."""
    import json

    chosen = tmp_path / "chosen.toml"
    chosen.write_text('[solver]\nhourglass = 0.1\nfit = "curvature_corrected"\ncontact = "instant"\n' + SCENE_TOML)

    def rows(scene, name, *extra):
        out = tmp_path / name
        assert cli.main(["sweep", str(scene), "--param", "paste.yield_stress=10000", "--frames", "3", "--workers", "1",
                         "-o", str(out), "--no-progress", *extra]) == 0
        meta = json.loads((out / "sweep.json").read_text())
        return [{k: v for k, v in r.items() if k not in ("wall_s", "warnings")} for r in SweepTable.read_csv(out / "sweep.csv").rows], meta

    plain, meta_plain = rows(scene_file, "plain")
    by_file, meta_file = rows(chosen, "file")
    by_flags, meta_flags = rows(scene_file, "flags", "--hourglass", "0.1", "--solver-fit", "curvature_corrected",
                                "--contact", "instant")
    back, _ = rows(chosen, "back", "--hourglass", "0", "--solver-fit", "linear", "--contact", "continuous")
    assert by_flags == by_file and back == plain
    hourglass_only, _ = rows(scene_file, "hourglass", "--hourglass", "0.1")
    assert by_file[0]["max_height"] != plain[0]["max_height"]
    assert hourglass_only[0]["kinetic_energy"] != plain[0]["kinetic_energy"]  # the control alone reaches the samples
    # None: by the fit ("auto" runs no control for this paste, a material that can flow).
    assert (meta_plain["hourglass"], meta_plain["fit"], meta_plain["contact_ramp"]) == (None, None, 1.0)
    assert (meta_flags["hourglass"], meta_flags["fit"], meta_flags["contact_ramp"]) == (0.1, "curvature_corrected", 0.0)
    assert (meta_file["hourglass"], meta_file["fit"]) == (0.1, "curvature_corrected")
    capsys.readouterr()


@pytest.mark.parametrize("args, words", [
    (["--param", "yield_stress"], ["'yield_stress'", "NAME=LO:HI:SCALE:N"]),
    (["--param", "yield_stress=1:2:log:3:4"], ["yield_stress", "5 fields"]),
    (["--param", "yield_strss=100:1000:log:8"], ["'yield_strss'", "unknown parameter", "yield_stress"]),
    (["--param", "yield_stress=1000:100:log:8"], ["yield_stress", "1000", "LO < HI"]),
    (["--param", "yield_stress=0:100:log:8"], ["yield_stress", "LO = 0.0", "LO > 0"]),
    (["--param", "yield_stress=10:100:log:0"], ["yield_stress", "N = 0", ">= 1"]),
    (["--param", "yield_stress=10:100:log:x"], ["yield_stress", "'x'", "integer"]),
    (["--param", "mu=-5:10:lin:2"], ["mu", "-5.0", "> 0"]),
    (["--param", "yield_stress=10:100:log:200", "--param", "flow_rate=1:2:lin:100"],
     ["20000", "--max-samples = 10000"]),
    (["--param", "yield_stress=10:100:log:8", "--sample", "lhs", "--samples", "4"], ["N = 8", "--sample lhs"]),
    (["--param", "yield_stress=10:100:log", "--sample", "lhs"], ["--samples is required"]),
    (["--param", "yield_stress=10:100:log", "--sample", "lhs", "--samples", "0"], ["--samples = 0", ">= 1"]),
    # As fit refuses --seed where nothing is drawn: the grid ran as without it.
    (["--param", "yield_stress=10:100:log:2", "--seed", "3"],
     ["--seed = 3 is not allowed with --sample grid: it seeds the draws of --sample random and lhs, and a grid draws nothing"]),
    (["--param", "yield_stress=10:100:log:2", "--sample", "grid", "--seed", "0"], ["--seed = 0 is not allowed with --sample grid"]),
    # Every sample failed alone at a frame of millions of steps, exit 3.
    (["--param", "mu=1e3:1e5:log:3", "--fps", "1e-4", "--frames", "1"],
     ["--fps = 0.0001 is not allowed for this sweep: no sample can run at its own stable step (sample 0, mu = 1000: a frame "
      "(1/fps = 10000 s) would take 4.79e+06 steps of the stable step 0.00209 s, more than 1e+06"]),
    # Where the hourglass control's limit sets the step, its option is advised, not softer materials.
    (["--param", "mu=1e3:1e5:log:3", "--fps", "1e-4", "--frames", "1", "--hourglass", "1000"],
     ["--fps = 0.0001 is not allowed for this sweep", "; the hourglass control sets it (the hourglass control's limit at "
      "strength c = 1000, ", "; give a higher --fps, a smaller --scale (a larger spacing, whose stable step is longer), or a "
      "smaller --hourglass (or the scene's [solver] hourglass)"]),
    (["--param", "crust.yield_stress=10:100:log:2"], ["crust.yield_stress", "'crust'", "paste"]),
    (["--param", "yield_stress=10:100:log:2", "--param", "paste.yield_stress=1:2:lin:2"], ["paste.yield_stress", "already"]),
    (["--param", "yield_stress=10:100:log:2", "--workers", "0"], ["--workers", "0"]),
    # Named as the command's other options are (it said 'max_samples = 0').
    (["--param", "yield_stress=10:100:log:2", "--max-samples", "0"], ["--max-samples = 0 is not allowed: must be an integer >= 1"]),
    (["--param", "yield_stress=10:100:log:2", "--frames", "2", "--duration", "1"], ["--duration", "--frames"]),
    (["--param", "yield_stress=10:100:log:2", "--dt", "0.007"], ["--dt = 0.007", "whole number of steps", "leave --dt out"]),
    (["--param", "yield_stress=10:100:log:2", "--duration", "1e300"], ["--duration = 1e+300", "more than the 1e+10 steps"]),
    (["--param", "mu=1e-320:1:log:3"], ["mu", "LO = 1e-320", "log scale LO >= 2.23e-308"]),
    (["--param", "yield_stress=10:100:log:2", "--duration", "1", "--fps", "1e12"], ["--fps = 1000000000000.0", "at most 1e+06"]),
    (["--param", "yield_stress=10:100:log:2", "--hourglass", "-1"], ["--hourglass = -1 is not allowed", ">= 0"]),
    (["--param", "yield_stress=10:100:log:2", "--hourglass", "x"], ["--hourglass = 'x'", ">= 0"]),
    (["--param", "yield_stress=10:100:log:2", "--solver-fit", "quad"], ["--solver-fit = 'quad'", "'linear'"]),
    (["--param", "yield_stress=10:100:log:2", "--contact", "soft"], ["--contact = 'soft'", "'instant', 'continuous'"]),
])
def test_bad_input_exits_2_with_one_line(scene_file, capsys, args, words, tmp_path):
    rc = cli.main(["sweep", scene_file, *args, "-o", str(tmp_path / "never"), "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1 and err[0].startswith("warp-esph: error:"), err
    for w in words:
        assert w in err[0], (w, err[0])
    assert not os.path.exists(tmp_path / "never")


def test_a_sweep_no_sample_of_which_can_step_at_its_fps_is_refused_before_the_first_sample():
    """At fps 0.01 a frame of the stiff samples needs millions of stable steps: each sample
    failed alone with that refusal, one after the other, and the sweep ended with a table of
    failures (the CLI: exit 3). Now it is refused once, before any sample, by the option's
    name; a sweep one of whose samples can run still runs (the others are its rows). The advice
    is the sweep's own options: a run's 'give dt or substeps' and 'a larger dt' named a
    substeps it lacks and a dt that would blow its samples up. The --fps and --frames refusals
    give the sample's reason without its own 'the stable step ... is not allowed' or 'frames =
    ... is not allowed', which said the refusal twice."""
    from warp_esph.cli import option_flag

    fps = (r"^{} = 0\.01 is not allowed for this sweep: no sample can run at its own stable "
           r"step \(sample 0, mu = 1e\+09: a frame \(1/fps = 100 s\) would take 2\.2\d*e\+07 "
           r"steps of the stable step 4\.5e-06 s, more than 1e\+06; the stiffest "
           r"material \(p-wave speed \S+ m/s\) or the most viscous one needs it\); give a higher "
           r"{}, a smaller {} \(a larger spacing, whose stable step is longer\), or softer "
           r"or less viscous materials or swept values$")
    frames = (r"^{} = 1000000000 is not allowed for this sweep: no sample can run at its own "
              r"stable step \(sample 0, mu = 1000: at 16 steps "
              r"per frame the run would take 1\.6e\+10 steps, more than 1e\+10\); give fewer "
              r"{} or a shorter {}, or a smaller {} \(.*\)$")
    # A Python caller is told sweep()'s parameters; the command (which plans with option_flag) its options.
    with pytest.raises(ValueError, match=fps.format("fps", "fps", "scale")):
        sweep(_box(), ["mu=1e9,1e8"], fps=0.01, frames=1, workers=1)
    with pytest.raises(ValueError, match=frames.format("frames", "frames", "duration", "scale")):
        sweep(_box(), ["mu=1e3"], frames=10**9, workers=1)
    with pytest.raises(ValueError, match=fps.format("--fps", "--fps", "--scale")):
        _plan(_box(), ["mu=1e9,1e8"], "grid", None, 0, 1, None, 0.01, None, 1.0, "float32", "cpu", 1, 100, None, flag=option_flag)
    with pytest.raises(ValueError, match=frames.format("--frames", "--frames", "--duration", "--scale")):
        _plan(_box(), ["mu=1e3"], "grid", None, 0, 10**9, None, None, None, 1.0, "float32", "cpu", 1, 100, None, flag=option_flag)
    assert len(_plan(_box(), ["mu=1e9,1e3"], "grid", None, 0, 1, None, 0.01, None, 1.0, "float32", "cpu", 1, 100, None).tasks) == 2


def test_a_python_caller_is_told_the_parameters_and_the_command_its_options(scene_file, capsys, tmp_path):
    """``sweep()`` and ``sample_points()`` refused by the command's options (``--frames = 0``,
    ``--workers``, ``--samples``, ``--param mu: ... with --sample random``), options a Python
    caller has not; the ray and seed refusals named the parameters. Each caller is told its own
    words: the command plans with ``cli.option_flag``, as ``export_frames`` is given it."""
    cases = [
        (lambda: sweep(scene_file, ["mu=1e3,2e3"], frames=0), ["--frames", "0"], "frames = 0 is not allowed: must be an integer >= 1",
         "--frames = 0 is not allowed: must be an integer >= 1"),
        (lambda: sweep(scene_file, ["mu=1e3,2e3"], workers=0), ["--workers", "0"], "workers = 0 is not allowed: must be an integer >= 1",
         "--workers = 0 is not allowed: must be an integer >= 1"),
        (lambda: sample_points(["mu=1e3,2e3"], "lhs", 0), ["--sample", "lhs", "--samples", "0"],
         "samples = 0 is not allowed: must be an integer >= 1", "--samples = 0 is not allowed: must be an integer >= 1"),
        (lambda: sample_points(["mu=1:2:lin:3"], "random", 4), ["--sample", "random", "--samples", "4"],
         "params entry mu: N = 3 levels is not allowed with sample = 'random': the count is samples; write mu=1:2:lin",
         "--param mu: N = 3 levels is not allowed with --sample random: the count is --samples; write mu=1:2:lin"),
        (lambda: sample_points(["mu=1e3,2e3"], "random"), ["--sample", "random"],
         "samples is required with sample = 'random': the number of samples to draw",
         "--samples is required with --sample random: the number of samples to draw"),
        (lambda: sweep(scene_file, ["mu=1e3,2e3"], fps=30, dt=0.0007), ["--fps", "30", "--dt", "0.0007"],
         "dt = 0.0007 is not allowed: a frame (1/fps = 0.0333333 s) must be a whole number of steps, but 1/fps / dt = "
         "47.619; use e.g. dt = 0.000694444 or 0.00070922, or leave dt out (the stable step, rounded to fill a frame)",
         "--dt = 0.0007 is not allowed: a frame (1/fps = 0.0333333 s) must be a whole number of steps, but 1/fps / dt = "
         "47.619; use e.g. --dt 0.000694444 or 0.00070922, or leave --dt out (the stable step, rounded to fill a frame)"),
        (lambda: sweep(scene_file, ["mu=1e3,2e3"], scale=0.2), ["--scale", "0.2"],
         f"scale = 0.2 is not allowed for {scene_file}: body 'paste' is under-resolved at spacing 0.1: it is 1 particle "
         "layer thick, and 1 of its 1 particles have too few neighbours, or too flat a neighbourhood, for the deformation "
         "fit (paper §4), which would skip them silently; the smallest scale above 0.2 that resolves it is 0.4",
         f"--scale = 0.2 is not allowed for {scene_file}: body 'paste' is under-resolved at spacing 0.1: it is 1 particle "
         "layer thick, and 1 of its 1 particles have too few neighbours, or too flat a neighbourhood, for the deformation "
         "fit (paper §4), which would skip them silently; the smallest --scale above 0.2 that resolves it is 0.4"),
    ]
    for call, args, said, cli_said in cases:
        with pytest.raises(ValueError) as e:
            call()
        assert str(e.value) == said, str(e.value)
        spec = ["--param", "mu=1:2:lin:3" if "levels" in said else "mu=1e3,2e3"]
        assert cli.main(["sweep", scene_file, *spec, *args, "-o", str(tmp_path / "never"), "--no-progress"]) == 2
        assert capsys.readouterr().err.strip() == f"warp-esph: error: {cli_said}"


def test_a_sample_that_cannot_step_at_its_fps_is_a_row_without_a_run_s_advice():
    """A sample refused by its stable step (where another sample can run, the sweep runs and
    this one is a failed row) gave a run's advice in its reason, 'give dt= or substeps=': a
    sweep has no substeps. The row says the reason alone."""
    from warp_esph.sweep import _run_sample

    plan = _plan(_box(), ["mu=1e9,1e3"], "grid", None, 0, 1, None, 0.01, None, 1.0, "float32", "cpu", 1, 100, None)
    row = _run_sample(plan.scene, plan.tasks[0][1])
    assert row["status"] == "failed", row
    assert re.fullmatch(r"StepRefusal: the stable step 4\.5e-06 s is not allowed: a frame \(1/fps = 100 s\) would take "
                        r"\S+ steps, more than 1e\+06; the stiffest material \(p-wave speed \S+ m/s\) or the most "
                        r"viscous one needs it", row["reason"]), row["reason"]


def test_a_sample_stopped_at_a_far_mesh_tool_is_a_row_without_a_run_s_advice(monkeypatch):
    """A sample stopped at a mesh tool beyond float32's resolution gave the Python advice
    'use dtype=float64' in its row, where a refused start's row gave its reason alone: the
    table serves the command (--dtype) too, so every row is the reason without advice."""
    from warp_esph import tools
    from warp_esph.sweep import _run_sample

    b = SceneBuilder(spacing=0.02)
    b.add_box((80.0, 0.03, 0.0), (0.06, 0.06, 0.06), Material.preset("dough"), name="block")
    b.add_tool("mesh", mesh=tools.box_mesh((100.0, 0.05, 100.0)), name="belt", friction=0.0,
               motion=tools.Velocity((-15.0, 0.0, 0.0), position=(0.0, 0.01 - 0.05, 0.0)))
    # finalize refuses this mesh in float32 already; the stop is what is looked at here.
    monkeypatch.setattr(SceneBuilder, "_check_mesh_tool_reach", lambda self, scalar: None)
    plan = _plan(Scene("belt", "", b, frames=2, fps=30.0), ["mu=1e4"], "grid", None, 0, 2, None, 30.0, None, 1.0,
                 "float32", "cpu", 1, 100, None)
    row = _run_sample(plan.scene, plan.tasks[0][1])
    assert row["status"] == "failed", row
    assert re.fullmatch(r"the simulation stopped after step \d+ \(frame 1, t = 0\.03333 s\): the particles met mesh tool "
                        r"'belt' far from its origin \(the faces they are at reach 100 m from it\), where float32 .*: particles "
                        r"that touch it would be put inside it", row["reason"]), row["reason"]


def test_a_sample_stopped_by_a_scripted_tool_too_fast_is_a_row_without_a_run_s_advice():
    """A ``tools.Scripted`` tool that a step moves more than a spacing stops the run; its
    row said 'give a slower motion or a smaller dt=' inside the stop's reason (the advice was
    not apart): the reason alone now, as the refused start's row."""
    from warp_esph import tools
    from warp_esph.sweep import _run_sample

    b = SceneBuilder(spacing=0.01)
    b.add_box((0.0, 0.03, 0.0), (0.04, 0.04, 0.04), Material.preset("clay"), name="blk")
    b.add_ground()
    # 0.1 m in the step from t = 2 ms (frame 3), 1000 m/s.
    b.add_tool("box", half_extents=(0.01, 0.05, 0.05), name="hammer",
               motion=tools.Scripted(lambda t: ((0.1 if t <= 0.002 + 1e-9 else 0.2, 0.03, 0.0), tools.IDENTITY)))
    plan = _plan(Scene("hammer", "", b, frames=5, fps=1000.0), ["mu=1e5"], "grid", None, 0, 5, None, 1000.0, 1e-4, 1.0,
                 "float32", "cpu", 1, 100, None)
    row = _run_sample(plan.scene, plan.tasks[0][1])
    assert row["status"] == "failed", row
    assert re.fullmatch(r"the simulation stopped in step 21, in frame 3: tool 'hammer': its Scripted motion moves its points "
                        r"at up to 1e\+03 m/s .* so at most 100 m/s", row["reason"]), row["reason"]


def test_the_python_sweep_takes_and_refuses_the_precisions_finalize_does():
    """``sweep(dtype=...)`` read only the names 'float32'/'float64' (and what has that
    ``__name__``): 'f8' and 'double', which ``finalize``, ``fit`` and ``scalar_type`` take,
    were refused as '--dtype = 'f8' is not allowed: must be one of ...'. It reads them with
    ``scalar_type`` now, and refuses what that refuses in its words."""
    import warp as wp

    from warp_esph._types import scalar_type

    def planned(dtype):
        return _plan(_box(), ["mu=1e3"], "grid", None, 0, 1, None, 30.0, 1 / 300, 1.0, dtype, "cpu", 1, 100, None)

    for given, name in (("f8", "float64"), ("double", "float64"), (np.float64, "float64"), (np.dtype("f8"), "float64"),
                        (wp.float64, "float64"), ("float64", "float64"), ("f4", "float32"), (np.float32, "float32")):
        assert [task.dtype for _, task in planned(given).tasks] == [name], given
    for bad in ("float", float, "f2", None, np.float64(1.0), "int32"):
        with pytest.raises(ValueError) as wanted:
            scalar_type(bad)
        with pytest.raises(ValueError, match=f"^{re.escape(str(wanted.value))}$"):
            planned(bad)


def test_bad_input_raises_value_error_in_python():
    with pytest.raises(ValueError, match="flow_rate.*LO < HI"):
        sweep(_box(), ["flow_rate=5:5:lin:2"])
    with pytest.raises(ValueError, match="unknown parameter"):
        parse_param("density=1:2:lin:2")


@pytest.mark.parametrize("spec", ["pair_repulsion=0,1", "paste.pressure_force=0,1", "0.density=1000:1200:lin:2"])
def test_a_material_setting_given_as_a_swept_parameter_is_said_to_be_a_setting(spec, scene_file, tmp_path, capsys):
    """``--param pair_repulsion=...`` (or any field of ``Material`` that is not per particle)
    was refused as an unknown name, as a typo is: it is a setting of the material, made
    where the material is (``Material(...)``; the scene's material table), in fit's words."""
    name = spec.partition("=")[0]
    field = name.rsplit(".", 1)[-1]
    fields = "mu, lam, yield_stress, flow_rate, hardening, pressure_stiffness, viscosity"
    where = r"^params entry '{}' is not allowed: unknown parameter; name one of {}, .*\); {} is a material setting, "
    for params in ([spec], {name: spec.partition("=")[2]}):
        with pytest.raises(ValueError, match=where.format(re.escape(name), fields, field) + "not a swept parameter: set it in "
                           rf"the Material \(Material\(\.\.\., {field}=\.\.\.\)\)$"):
            sweep(scene_file, params, frames=1)
    assert cli.main(["sweep", scene_file, "--param", spec, "-o", str(tmp_path / "never"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.endswith(
        f"; {field} is a material setting, not a swept parameter: set it in the scene's material table ({field} = ...)\n"), err
    assert err.startswith(f"warp-esph: error: --param {name!r} is not allowed: unknown parameter; name one of {fields}, "), err
    assert not os.path.exists(tmp_path / "never")
    # A name that is no field at all keeps the plain refusal.
    with pytest.raises(ValueError, match=r"e\.g\. dough\.yield_stress, 0\.yield_stress\)$"):
        parse_param("stiffness=1,2")


def test_a_range_of_numpy_numbers_is_taken_and_one_wider_than_a_float_is_refused():
    """``Param`` bounds of numpy numbers (a range from ``np.linspace`` or a table) were refused
    as 'need LO < HI' for LO = 1 < HI = 10; they are the floats they hold. A lin range whose
    width overflows a float (lam from -1.7e308 to 1.7e308) drew inf for every random sample,
    and its grid was [nan, inf, 1.7e308], without a word."""
    from warp_esph.sweep import Param  # noqa: PLC0415

    p = parse_param(Param("yield_stress", np.int64(1), np.float32(10.0), "lin", 2))
    assert (p.lo, p.hi) == (1.0, 10.0) and p.levels().tolist() == [1.0, 10.0]
    with pytest.raises(ValueError, match=r"^params entry yield_stress: LO = True, HI = 10\.0 is not allowed: LO and HI must be numbers$"):
        parse_param(Param("yield_stress", True, 10.0, "lin", 2))
    for spec, sample, samples in (("lam=-1.7e308:1.7e308", "random", 3), ("lam=-1.7e308:1.7e308:lin:3", "grid", None)):
        with pytest.raises(ValueError, match=r"^params entry lam: LO = -1\.7e\+308, HI = 1\.7e\+308 is not allowed: on a lin "
                                             r"scale HI - LO must be a finite number \(at most 1\.8e\+308\)$"):
            sample_points([spec], sample, samples)
    assert [p["lam"] for p in sample_points(["lam=-8e307:8e307:lin:3"])] == [-8e307, 0.0, 8e307]


def test_reading_a_file_that_is_no_sweep_table_names_it_and_what_it_must_be(tmp_path, serial):
    """``SweepTable.read_csv`` of an empty file raised StopIteration, of another CSV
    "'status' is not in list", of a file that is not text the codec's message: none named
    the file or what it must be."""
    wanted = "must be a sweep table written by SweepTable.to_csv"
    for name, content, why in (("empty.csv", b"", r"its header is \[\]"), ("other.csv", b"a,b\n1,2\n", r"its header is \['a', 'b'\]"),
                               ("binary.csv", b"\xff\xfe\x00", r"it is not CSV text \('utf-8' codec can't decode")):
        path = tmp_path / name
        path.write_bytes(content)
        with pytest.raises(ValueError, match=rf"^path = {re.escape(repr(str(path)))} is not allowed: {wanted} .*; {why}"):
            SweepTable.read_csv(path)
    assert _rows(SweepTable.read_csv(serial.to_csv(tmp_path / "t.csv"))) == _rows(serial)


def test_a_plot_names_what_it_cannot_draw_and_is_written_where_it_says(serial, tmp_path):
    """``plot`` dropped quantities and log_params the table lacks without a word (all of them:
    matplotlib's 'Number of rows must be a positive integer, not 0'), read a single name
    letter by letter, and, given a path without an extension, wrote path + '.png' and
    returned the path it had not written."""
    pytest.importorskip("matplotlib")
    from warp_esph.sweep import plot  # noqa: PLC0415

    for kwargs, message in ((dict(quantities=["max_heigth"]), r"quantities = \['max_heigth'\] is not allowed: the table has no "
                                                              r"column 'max_heigth'; choose from sample, status, yield_stress"),
                            (dict(quantities=[]), r"quantities = \[\] is not allowed: give at least one; choose from sample"),
                            (dict(log_params=["flow_rate"]), r"log_params = \['flow_rate'\] is not allowed: the table has no "
                                                             r"column 'flow_rate'; choose from yield_stress$")):
        with pytest.raises(ValueError, match=f"^{message}"):
            plot(serial, tmp_path / "p.png", **kwargs)
    assert not (tmp_path / "p.png").exists()
    out = plot(serial, tmp_path / "picture", quantities="max_height", log_params="yield_stress")
    assert out == str(tmp_path / "picture") and sorted(os.listdir(tmp_path)) == ["picture"]
    with Image.open(out) as im:
        assert im.format == "PNG"


def test_a_function_the_workers_cannot_be_sent_is_refused_before_any_item(tmp_path):
    """``parallel_map`` and ``sweep(extra=)`` with a lambda and worker processes failed every
    item (sample) with pickle's message, as if each had failed on its own; a function that is
    none, or an item that is no tuple of arguments, was a TypeError from the first worker."""
    from warp_esph.sweep import parallel_map  # noqa: PLC0415

    with pytest.raises(ValueError, match=r"^fn = <function .* is not allowed with 2 worker processes: it must be "
                                         r"importable by name \(a module-level function\) to reach them \(Can't pickle"):
        parallel_map(lambda x: x, [(1,), (2,)], workers=2, on_error=lambda i, why: why)
    with pytest.raises(ValueError, match=r"^extra = <function .* is not allowed with 2 worker processes"):
        sweep(_box(), ["yield_stress=10,100"], frames=1, workers=2, extra=lambda model, state, seed: {"q": 1.0})
    with pytest.raises(ValueError, match=r"^fn = 3 is not allowed: must be callable as fn\(\*item\)$"):
        parallel_map(3, [(1,)], workers=1)
    with pytest.raises(ValueError, match=r"^items\[1\] = 4\.0 is not allowed: each item must be a tuple of fn's arguments "
                                         r"\(e\.g\. \(4\.0,\)\)$"):
        parallel_map(math.sqrt, [(4.0,), 4.0], workers=1)
    # In this process a lambda needs no sending.
    assert parallel_map(lambda x: 2 * x, [(1,), (2,)], workers=1) == [2, 4]
    assert sweep(_box(), ["yield_stress=10"], frames=1, workers=1, extra=lambda model, state, seed: {"q": 1.0}).rows[0]["q"] == 1.0


def _extra_seed(model, state, seed):
    """An ``extra`` column function: the sample seed it is handed."""
    return {"handed": seed}


def test_a_python_sweep_refuses_a_seed_a_grid_without_extra_never_reads():
    """As ``warp-esph sweep`` refuses ``--seed`` with ``--sample grid``: ``sweep(..., seed=3)`` of a
    grid ran every sample exactly as without it. With ``extra`` the seed is read (it seeds the
    sample seeds ``extra`` is handed), so it is taken there."""
    from warp_esph.sweep import _sample_seed

    for seed in (3, 0):
        with pytest.raises(ValueError, match=rf"^seed = {seed} is not allowed with sample = 'grid' and no extra: it "
                                             r"seeds the draws of sample = 'random' and 'lhs' and the sample seeds "
                                             r"handed to extra, and a grid without extra reads neither$"):
            sweep(_box(), ["yield_stress=10"], seed=seed, frames=1, workers=1)
    handed = [sweep(_box(), ["yield_stress=10"], frames=1, workers=1, extra=_extra_seed, **kw).rows[0]["handed"]
              for kw in ({}, {"seed": 3})]
    assert handed == [_sample_seed(0, 0), _sample_seed(3, 0)] and handed[0] != handed[1]


@pytest.fixture(scope="module")
def dying_worker_sweep():
    """Six samples on two worker processes whose ``extra`` kills its worker in sample 0 and
    raises in sample 1 (``_extra_that_fails``): one pool for the two tests that read it."""
    return sweep(_box(), ["yield_stress=10,20,40,80,160,320"], frames=4, workers=2, extra=_extra_that_fails)


def test_a_failing_sample_is_a_row_and_the_sweep_goes_on(dying_worker_sweep):
    # In this process: the exception of sample 1 is its row's reason; samples 0 and 2 run.
    table = sweep(_box(), ["yield_stress=10,100,1000"], frames=2, workers=1, extra=_extra_that_fails)
    assert [r["status"] for r in table.rows] == ["ok", "failed", "ok"]
    assert table.rows[1]["reason"] == "TypeError: a bug in extra"
    assert table.rows[0]["top_x"] > 0 and "top_x" in table.columns
    # A worker process that dies: its sample (and any other it took down) is a failed row.
    # (With workers, the sweep of the next test: its samples 0 and 1 are these two's.)
    table = dying_worker_sweep
    assert [r["sample"] for r in table.rows[:2]] == [0, 1]
    assert table.rows[0]["status"] == "failed" and "worker process died" in table.rows[0]["reason"]
    assert table.rows[0]["yield_stress"] == 10.0 and table.rows[1]["status"] == "failed"


def test_a_second_signal_while_a_stopped_sweep_writes_its_table_waits_for_it(tmp_path):
    """A stopped sweep writes the table of the samples finished; a second signal there (a
    second Ctrl-C, or ``timeout``, which signals the command and then its process group) ended
    the process at once: no table of the stopped sweep, the last partial one left beside a
    stray ``.sweep.<pid>.part.csv``. Run as the console script, the only place a second signal
    ends the process."""

    (tmp_path / "s.toml").write_text(SCENE_TOML)
    script = tmp_path / "twice.py"
    script.write_text(textwrap.dedent("""
        import os, signal, sys
        import warp_esph.sweep as s
        from warp_esph.cli import console_main

        real_execute, real_write = s._execute, s.write_outputs

        def execute(plan, workers, ray, record, *rest):
            def first_then_stop(row):
                record(row)
                os.kill(os.getpid(), signal.SIGTERM)  # the first signal, after one sample
            return real_execute(plan, workers, ray, first_then_stop, *rest)

        def write(table, folder, meta=None, *args, **kwargs):
            if meta and meta.get("interrupted"):
                os.kill(os.getpid(), signal.SIGTERM)  # the second, as the stopped sweep writes its table
            return real_write(table, folder, meta, *args, **kwargs)

        s._execute, s.write_outputs = execute, write
        sys.argv = ["warp-esph", "sweep", "s.toml", "--param", "yield_stress=10,100,1000", "--frames", "1",
                    "--workers", "1", "--no-progress", "-o", "sw"]
        console_main()
    """))
    done = run_script(script, tmp_path, timeout=120)
    assert done.returncode == 143, done.stderr
    assert done.stderr.splitlines()[-1] == "warp-esph: terminated: the table keeps the 1 of 3 samples finished", done.stderr
    assert sorted(os.listdir(tmp_path / "sw")) == ["sweep.csv", "sweep.json", "sweep.parquet", "sweep.png"]
    meta = json.loads((tmp_path / "sw" / "sweep.json").read_text())
    assert meta.get("interrupted") is True and "partial" not in meta
    assert len(SweepTable.read_csv(tmp_path / "sw" / "sweep.csv").rows) == 1


def test_workers_started_from_a_script_without_a_main_guard_say_so(tmp_path):
    """Spawned workers start by importing the script that runs: one without an
    ``if __name__ == "__main__":`` guard runs its parallel call again there and every worker
    dies starting. The failure says that, not 'a crash in native code or out of memory'."""

    script = tmp_path / "unguarded.py"
    script.write_text("import math\nfrom warp_esph.sweep import parallel_map\n"
                      "print(parallel_map(math.sqrt, [(4.0,), (9.0,)], workers=2, on_error=lambda i, why: why))\n")
    done = run_script(script, tmp_path, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "could not start" in done.stdout and "unguarded.py" in done.stdout and "__main__" in done.stdout, done.stdout
    guarded = tmp_path / "guarded.py"
    guarded.write_text("import math\nfrom warp_esph.sweep import parallel_map\n\nif __name__ == '__main__':\n"
                       "    print(parallel_map(math.sqrt, [(4.0,), (9.0,)], workers=2, on_error=lambda i, why: why))\n")
    done = run_script(guarded, tmp_path, timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == "[2.0, 3.0]", (done.stdout, done.stderr)


def test_a_worker_that_dies_under_python_dash_m_fails_its_item_alone(tmp_path):
    """``python -m warp_esph sweep``: the main module is a package's ``__main__.py``, which
    spawned workers never run (multiprocessing skips it by name), and whose source need not
    say ``__main__``. It was taken for a script without a main guard: one worker that died
    (out of memory, a crash) failed every sample left with 'the worker processes could not
    start', and a resumed sweep kept those failed rows. Now the item that killed its worker
    fails alone and the others run."""
    import subprocess

    pkg = tmp_path / "runner"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "items.py").write_text("import os\n\n\ndef dies_first(i):\n    if i == 0:\n        os._exit(7)\n    return i\n")
    (pkg / "__main__.py").write_text("from warp_esph.sweep import parallel_map\nfrom runner.items import dies_first\n\n"
                                     "print(parallel_map(dies_first, [(i,) for i in range(4)], workers=2, "
                                     "on_error=lambda i, why: why))\n")
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=repo + os.pathsep + os.environ.get("PYTHONPATH", ""))
    done = subprocess.run([sys.executable, "-m", "runner"], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    assert "could not start" not in done.stdout, done.stdout
    assert "worker process died running this item alone" in done.stdout and done.stdout.rstrip().endswith(", 1, 2, 3]"), \
        done.stdout


# ------------------------------------------------------------------ input found misread or refused without a name
@pytest.mark.parametrize("args, words", [
    # N = 1e9 levels were allocated (7.5 GiB) before the count was compared.
    (["--param", "yield_stress=1:2:lin:1000000000"], ["1000000000 (yield_stress)", "--max-samples = 10000"]),
    (["--param", "yield_stress=1:2:lin:99999999999999999999"], ["99999999999999999999 (yield_stress)", "--max-samples"]),
    # '' was taken as no address: the plan's line came first, then Ray's own error.
    (["--param", "yield_stress=10,100", "--ray", ""], ["--ray = ''", "HOST:PORT"]),
])
def test_sweep_refuses_before_the_plan_line(scene_file, capsys, args, words, tmp_path):
    rc = cli.main(["sweep", scene_file, *args, "-o", str(tmp_path / "never"), "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("warp-esph: error:"), err
    for w in words:
        assert w in err[0], (w, err[0])


def test_what_the_scene_or_the_output_refuses_is_bad_input_before_any_sample(scene_file, capsys, tmp_path):
    """A scene that ``run`` refuses (its box starts inside the ground) ran every sample to the
    same refusal and exited 3; a folder in the way of ``sweep.csv`` was found after every
    sample had run, with a raw ``[Errno 21]``; a body named ``1`` next to material 1 took
    ``--param 1.mu`` as the material's, silently."""
    inside = tmp_path / "inside.toml"
    inside.write_text(SCENE_TOML.replace("center = [0.0, 0.06, 0.0]", "center = [0.0, 0.0, 0.0]"))
    (tmp_path / "taken" / "sweep.csv").mkdir(parents=True)
    two = tmp_path / "two.toml"
    two.write_text('''
[scene]
name = "two"
spacing = 0.02
frames = 2

[materials.a]
preset = "toothpaste"

[materials.b]
preset = "dough"

[[bodies]]
shape = "box"
name = "1"
material = "a"
center = [0.0, 0.06, 0.0]
size = [0.06, 0.06, 0.06]

[[bodies]]
shape = "box"
name = "0"
material = "b"
center = [0.3, 0.06, 0.0]
size = [0.06, 0.06, 0.06]
''')
    cases = [
        ([str(inside), "--param", "yield_stress=10,100", "-o", str(tmp_path / "a")], ["start inside plane0"]),
        ([scene_file, "--param", "yield_stress=10,100", "-o", str(tmp_path / "taken")], ["sweep.csv' is a folder"]),
        ([str(two), "--param", "1.mu=12345", "-o", str(tmp_path / "b")], ["'1' names both material 1 and body '1'"]),
    ]
    for argv, words in cases:
        rc = cli.main(["sweep", *argv, "--no-progress"])
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and len(err) == 1, err
        for w in words:
            assert w in err[0], (w, err[0])
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
    assert not (tmp_path / "taken" / "sweep.json").exists()


def test_the_command_s_missing_param_and_frames_beside_duration_are_said_as_its_other_refusals(tmp_path, capsys):
    """Without --param the command said 'params = [] is not allowed', a Python argument nobody
    typed, and --frames beside --duration was argparse's 'argument --duration: not allowed with
    argument --frames', naming no value. Both are one line naming the options, before any sample."""
    out = tmp_path / "sw"
    for argv, line in (([], "--param is required: give at least one --param NAME=LO:HI:SCALE:N (e.g. yield_stress=100:1000:log:8)"),
                       (["--param", "yield_stress=10,100", "--frames", "2", "--duration", "1"],
                        "--frames = 2 and --duration = 1.0 are not allowed together: give one")):
        rc = cli.main(["sweep", "dough_drop", "--scale", "0.3", "--workers", "1", "-o", str(out), "--no-progress", *argv])
        assert rc == 2 and capsys.readouterr().err.strip().splitlines() == [f"warp-esph: error: {line}"]
    assert not out.exists()


def test_a_param_of_a_material_the_scene_has_not_is_refused_saying_not_allowed_once(tmp_path, capsys):
    """'--param 5.yield_stress is not allowed: material 5 is not allowed: indices are 0..0': the
    refusal of the material was wrapped in one of the parameter, and said it twice."""
    out = tmp_path / "sw"
    for name, line in (("5", "material 5 is not allowed: indices are 0..0"),
                       ("nobody", "material 'nobody' is not allowed: give a material index or a body name (dough)")):
        rc = cli.main(["sweep", "dough_drop", "--scale", "0.3", "--workers", "1", "-o", str(out), "--no-progress",
                       "--param", f"{name}.yield_stress=10,100"])
        assert rc == 2 and capsys.readouterr().err.strip().splitlines() == [
            f"warp-esph: error: --param {name}.yield_stress: {line}"]
    assert not out.exists()


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"  # a zombie has ended
    except FileNotFoundError:
        return False


def _assert_ended(pids):
    """Waits for the processes ``pids`` to end, at most 30 s (the items of ``_waits_in`` wait
    120 s), and asserts that they did."""
    for _ in range(600):
        if not any(_alive(pid) for pid in pids):
            break
        time.sleep(0.05)
    assert not [pid for pid in pids if _alive(pid)]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_the_worker_processes_end_with_the_process_that_runs_the_pool(tmp_path):
    """A sweep killed outright (SIGKILL, out of memory), or ended at once by a second Ctrl-C
    (timeout's, which signals the command and then its process group) before it had stopped
    its workers, left them running: they ignore SIGINT, went on with their samples and then
    waited forever for the next, each holding its memory and the terminal's pipes (a
    'warp-esph sweep ... | tail' never returned). A worker now ends once the process that
    started it is gone."""
    notes = tmp_path / "notes"
    notes.mkdir()
    code = ("import sys; sys.path.insert(0, sys.argv[1]); from pool_items import _waits_in; "
            "from warp_esph.sweep import parallel_map; parallel_map(_waits_in, [(0, sys.argv[2]), (1, sys.argv[2])], workers=2)")
    parent = subprocess.Popen([sys.executable, "-c", code, os.path.dirname(__file__), str(notes)], stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    try:
        for _ in range(1200):  # both items in flight (at most 60 s)
            if all((notes / f"{i}.pid").exists() for i in (0, 1)) or parent.poll() is not None:
                break
            time.sleep(0.05)
        workers = [int((notes / f"{i}.pid").read_text()) for i in (0, 1)]
        parent.kill()
        parent.wait()
        _assert_ended(workers)
    finally:
        (notes / "release").touch()
        parent.kill()
        for i in (0, 1):  # (without the fix they wait forever, once released, for another item)
            if (notes / f"{i}.pid").exists() and _alive(int((notes / f"{i}.pid").read_text())):
                os.kill(int((notes / f"{i}.pid").read_text()), signal.SIGKILL)


#: The script of test_a_worker_whose_parent_died_while_it_started_up_ends_too: a pool of two
#: workers, each held in its start (spawn imports this file as ``__mp_main__`` in it) until
#: the test, having killed the pool's process, writes ``go``.
_PARENT_DIES_AT_START = """
import os, sys, time
notes = os.environ["WARP_ESPH_TEST_NOTES"]
if __name__ == "__mp_main__":
    open(os.path.join(notes, f"held_{os.getpid()}"), "w").close()
    while not os.path.exists(os.path.join(notes, "go")):
        time.sleep(0.05)
elif __name__ == "__main__":
    sys.path.insert(0, sys.argv[1])
    from pool_items import _waits_in
    from warp_esph.sweep import parallel_map
    parallel_map(_waits_in, [(0, notes), (1, notes)], workers=2)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_worker_whose_parent_died_while_it_started_up_ends_too(tmp_path):
    """A worker took the process to watch from ``os.getppid()`` in its own start, after
    importing Warp (seconds): a sweep killed in that time left it watching its new parent, init,
    so it lived on as before the watch, its sample finished for no one. It watches the pid of
    the process that made the pool."""
    notes = tmp_path / "notes"
    notes.mkdir()
    script = tmp_path / "parent.py"
    script.write_text(_PARENT_DIES_AT_START)
    parent = subprocess.Popen([sys.executable, str(script), os.path.dirname(__file__)], stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL, env=dict(os.environ, WARP_ESPH_TEST_NOTES=str(notes)))
    workers = []
    try:
        for _ in range(1200):  # both workers held in their start (at most 60 s)
            workers = [int(p.name[5:]) for p in notes.glob("held_*")]
            if len(workers) == 2 or parent.poll() is not None:
                break
            time.sleep(0.05)
        assert len(workers) == 2
        parent.kill()
        parent.wait()
        (notes / "go").touch()
        _assert_ended(workers)
    finally:
        (notes / "go").touch()
        (notes / "release").touch()
        parent.kill()
        for pid in workers:
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)


def _extra_taking_a_column(model, state, seed):
    return {"status": "hacked", "top": 1.0}


def test_python_sweep_inputs_are_value_errors_and_extra_cannot_overwrite_the_row():
    for params, needle in ((None, "params = None is not allowed"), (123, "params = 123 is not allowed"),
                           ({"yield_stress": None}, "value None is not allowed: must be a finite number"),
                           ({"yield_stress": ["x"]}, "value 'x' is not allowed"),
                           ({"yield_stress": [10.0, float("nan")]}, "value nan is not allowed")):
        with pytest.raises(ValueError, match=needle):
            sweep(_box(), params, frames=1, workers=1)
    table = sweep(_box(), {"yield_stress": [100.0]}, frames=1, workers=1, extra=_extra_taking_a_column)
    row = table.rows[0]
    assert row["status"] == "failed" and "['status'] (the table's own)" in row["reason"]


def _sweep_three_samples(scene_file, out) -> int:
    """``warp-esph sweep`` of 3 one-frame samples, one worker, into ``out``: its exit status."""
    return cli.main(["sweep", scene_file, "--param", "yield_stress=10,100,1000", "--frames", "1", "--workers", "1",
                     "-o", str(out), "--no-progress"])


def test_a_sweep_keeps_the_samples_finished_while_it_runs(scene_file, tmp_path, monkeypatch):
    """The table is rewritten as samples finish (here after each one), so a sweep killed
    outright (SIGKILL, out of memory) keeps what it had; before, nothing was written until
    the end."""
    from warp_esph import sweep as sweep_module

    seen = []
    real = sweep_module.write_outputs

    def spy(table, folder, meta=None, *a, **k):
        seen.append((len(table), bool(meta and meta.get("partial"))))
        return real(table, folder, meta, *a, **k)

    monkeypatch.setattr(sweep_module, "PARTIAL_EVERY_S", 0.0)
    monkeypatch.setattr(sweep_module, "write_outputs", spy)
    out = tmp_path / "sw"
    assert _sweep_three_samples(scene_file, out) == 0
    assert seen == [(1, True), (2, True), (3, True), (3, False)]
    assert len(SweepTable.read_csv(out / "sweep.csv")) == 3


def test_a_table_with_a_row_cut_short_is_refused_not_resumed_as_an_ok_row(scene_file, tmp_path, capsys):
    """A sweep.csv whose last row was cut short (a damaged copy, a disk that filled in another
    program's write) was read with the missing cells as empty: --resume kept the row as 'ok',
    its summary empty and its last number cut to the digits left, and exited 0. A row of
    another cell count than the header's is refused, naming the file and the row."""
    out = tmp_path / "sw"
    assert _sweep_three_samples(scene_file, out) == 0
    text = (out / "sweep.csv").read_text()
    header, *rows = text.splitlines()
    cut = "\n".join([header, rows[0], rows[1][: len(rows[1]) // 2]]) + "\n"
    (out / "sweep.csv").write_text(cut)
    (out / "sweep.parquet").unlink(missing_ok=True)
    capsys.readouterr()
    assert cli.main(["sweep", scene_file, "--param", "yield_stress=10,100,1000", "--frames", "1", "--workers", "1",
                     "-o", str(out), "--no-progress", "--resume"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and re.fullmatch(rf"warp-esph: error: path = '{re.escape(str(out / 'sweep.csv'))}' is not allowed: "
                                          r"must be a sweep table written by SweepTable\.to_csv .*; its row 2 below the header "
                                          rf"has \d+ cells where the header has {len(header.split(','))} \(a row cut short or "
                                          r"run together: the file is damaged\)", err[0]), err
    assert (out / "sweep.csv").read_text() == cut
    with pytest.raises(ValueError, match=r"its row 2 below the header has \d+ cells"):
        SweepTable.read_csv(out / "sweep.csv")


def _sweep_signalled_at_the_second_sample(scene_file, tmp_path, monkeypatch, capsys, signal_it):
    """``warp-esph sweep`` of 3 one-frame samples in this process, ``signal_it()`` called
    as the second sample starts; returns (status, stderr, the table's rows, samples begun)."""
    from warp_esph import sweep as sweep_module

    real, runs = sweep_module._run_sample, []

    def run_and_signal(scene, task):
        runs.append(1)
        if len(runs) == 2:
            signal_it()
        return real(scene, task)

    monkeypatch.setattr(sweep_module, "_run_sample", run_and_signal)
    out = tmp_path / "sw"
    status = _sweep_three_samples(scene_file, out)
    return status, capsys.readouterr().err, len(SweepTable.read_csv(out / "sweep.csv")), len(runs)


def test_a_terminated_sweep_keeps_its_finished_samples_and_says_terminated(scene_file, tmp_path, monkeypatch, capsys):
    """SIGTERM in a sweep exits 143 with the table of the samples finished; its line said
    'interrupted', as for Ctrl-C. Its sweep.json names the signal too, as a stopped fit's
    fit.json does (it said only 'interrupted': true)."""
    import signal

    status, err, rows, _ = _sweep_signalled_at_the_second_sample(scene_file, tmp_path, monkeypatch, capsys,
                                                                 lambda: os.kill(os.getpid(), signal.SIGTERM))
    assert status == 143, err
    assert err.splitlines()[-1] == "warp-esph: terminated: the table keeps the 1 of 3 samples finished"
    assert rows == 1
    meta = json.loads((tmp_path / "sw" / "sweep.json").read_text())
    assert meta["interrupted"] is True and meta["signal"] == "SIGTERM"


def test_a_signal_whose_table_of_the_samples_finished_fails_to_write_is_still_reported(scene_file, tmp_path, monkeypatch,
                                                                                       capsys):
    """SIGTERM mid-sweep, and the table of the samples finished could not be written (a full
    disk): the error reached the command's handler as bad input, exit 2 with the bare
    '[Errno 28] ...', the signal dropped. It exits 143, the one line saying both."""
    import errno
    import signal

    from warp_esph import sweep as sweep_module

    def full(self, path):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(sweep_module, "PARTIAL_EVERY_S", 1e9)
    monkeypatch.setattr(SweepTable, "to_csv", full)
    real, runs = sweep_module._run_sample, []

    def run_and_signal(scene, task):
        runs.append(1)
        if len(runs) == 2:
            os.kill(os.getpid(), signal.SIGTERM)
        return real(scene, task)

    monkeypatch.setattr(sweep_module, "_run_sample", run_and_signal)
    out = tmp_path / "sw"
    assert _sweep_three_samples(scene_file, out) == 143
    err = capsys.readouterr().err
    assert err.splitlines()[-1] == (f"warp-esph: terminated: cannot write the table of the 1 of 3 samples finished in {out}: "
                                    f"[Errno 28] No space left on device: '{out / 'sweep.csv'}' (the tables in {out} do "
                                    "not keep them all)"), err


def test_a_signal_in_a_finalizer_stops_the_sweep_after_that_sample(scene_file, tmp_path, monkeypatch, capsys):
    """A SIGTERM that landed in a finalizer (``__del__``), where it cannot be raised, was only
    recorded: the sweep ran every sample before saying 'terminated'. It now stops the sweep
    once the sample it landed in is finished and kept."""
    import signal

    class Finalized:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGTERM)

    status, err, rows, runs = _sweep_signalled_at_the_second_sample(scene_file, tmp_path, monkeypatch, capsys,
                                                                    lambda: Finalized())
    assert status == 143, err
    assert err.splitlines()[-1] == "warp-esph: terminated: the table keeps the 2 of 3 samples finished"
    assert rows == 2 and runs == 2


def test_a_table_that_cannot_be_written_leaves_no_working_file_and_the_old_table_whole(tmp_path, monkeypatch):
    """A full disk while sweep.csv (sweep.json, sweep.parquet) was written left an empty or cut
    sweep.csv.tmp beside the table; the write failing now removes it, names the table and
    keeps the earlier table as it was."""
    import errno

    from warp_esph import sweep as sweep_module
    from warp_esph.sweep import SUMMARY_COLUMNS, write_outputs

    q = SUMMARY_COLUMNS[0]
    table = SweepTable(columns=["sample", "yield_stress", "status", q],
                       rows=[{"sample": k, "yield_stress": 10.0 * (k + 1), "status": "ok", q: 1.0} for k in range(3)],
                       params=["yield_stress"])
    (tmp_path / "sweep.csv").write_text("an earlier sweep's table\n")
    real = sweep_module.csv.writer

    class Full:
        def __init__(self, f):
            self.w, self.n = real(f), 0

        def writerow(self, row):
            self.n += 1
            if self.n == 3:  # the header and a row written, then the disk is full
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            self.w.writerow(row)

    monkeypatch.setattr(sweep_module.csv, "writer", Full)
    with pytest.raises(OSError, match="No space left on device") as caught:
        write_outputs(table, tmp_path, meta={"partial": False}, plot_figure=False)
    assert caught.value.filename == str(tmp_path / "sweep.csv")
    # sweep.json is written first (a table is never left without its record); no working file.
    assert sorted(os.listdir(tmp_path)) == ["sweep.csv", "sweep.json"]
    assert (tmp_path / "sweep.csv").read_text() == "an earlier sweep's table\n"
    monkeypatch.setattr(sweep_module.csv, "writer", real)

    def no_room(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(sweep_module.json, "dump", no_room)
    with pytest.raises(OSError, match="No space left on device"):
        write_outputs(table, tmp_path, meta={"partial": False}, plot_figure=False)
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".") or p.name.endswith(".tmp")]
    assert (tmp_path / "sweep.csv").read_text() == "an earlier sweep's table\n"  # sweep.json failed before it


def test_a_sweep_whose_tables_cannot_be_written_at_its_end_is_a_failed_write(scene_file, tmp_path, monkeypatch, capsys):
    """A full disk at the sweep's final tables was exit 2 (bad input) with a bare
    '[Errno 28] ...': now one line naming the folder, what ran and what is on disk, exit 4."""
    import errno

    from warp_esph import sweep as sweep_module

    real = sweep_module.write_outputs

    def full(table, folder, meta=None, *a, **k):
        if meta and meta.get("partial"):
            return real(table, folder, meta, *a, **k)
        raise OSError(errno.ENOSPC, "No space left on device", os.path.join(folder, "sweep.csv.tmp"))

    monkeypatch.setattr(sweep_module, "PARTIAL_EVERY_S", 0.0)
    monkeypatch.setattr(sweep_module, "write_outputs", full)
    out = tmp_path / "sw"
    status = cli.main(["sweep", scene_file, "--param", "yield_stress=10,100", "--frames", "1", "--workers", "1",
                       "-o", str(out), "--no-progress"])
    err = capsys.readouterr().err
    assert status == cli.EXIT_WRITE_FAILED, err
    last = err.strip().splitlines()[-1]  # after the plan line
    assert last.startswith(f"warp-esph: error: cannot write the sweep's tables in {out}: [Errno 28] No space left"), err
    assert last.endswith("(2 samples ran; the tables in " + str(out) + " are not this sweep's whole result)") \
        and "Traceback" not in err
    assert len(SweepTable.read_csv(out / "sweep.csv")) == 2  # the partial table of both samples
    # Only the picture failing: the tables stand whole and the sweep is no failed one.
    monkeypatch.setattr(sweep_module, "write_outputs", real)

    def no_room(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device", "sweep.png")

    monkeypatch.setattr(sweep_module, "plot", no_room)
    (out / "sweep.png").write_bytes(b"an earlier sweep's picture")
    capsys.readouterr()
    assert cli.main(["sweep", scene_file, "--param", "yield_stress=10,100", "--frames", "1", "--workers", "1",
                     "-o", str(out), "--no-progress"]) == 0
    assert "no plot: it could not be written ([Errno 28] No space left on device" in capsys.readouterr().out
    assert len(SweepTable.read_csv(out / "sweep.csv")) == 2 and not (out / "sweep.png").exists()


def test_values_matplotlib_cannot_lay_out_still_leave_the_tables_and_the_record(tmp_path, monkeypatch):
    """A sweep of yield_stress over 1e307..1.7e308 ran every sample, then matplotlib's axes
    raised 'arange: cannot compute length', exit 2 with no sweep.json. The plot is said to
    be missing (an earlier sweep's picture removed, the figure closed) and everything else is
    written."""
    pytest.importorskip("matplotlib")
    from warp_esph.sweep import SUMMARY_COLUMNS, write_outputs

    q = SUMMARY_COLUMNS[0]
    table = SweepTable(columns=["sample", "yield_stress", "status", q],
                       rows=[{"sample": 0, "yield_stress": 1e307, "status": "ok", q: 1.0},
                             {"sample": 1, "yield_stress": 1.7e308, "status": "ok", q: 2.0}],
                       params=["yield_stress"])
    import matplotlib.pyplot as plt  # noqa: PLC0415

    (tmp_path / "sweep.png").write_bytes(b"an earlier sweep's picture")
    open_before = len(plt.get_fignums())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # matplotlib's overflow note
        lines = write_outputs(table, tmp_path, meta={"partial": False})
    assert len(plt.get_fignums()) == open_before  # the failed figure closed
    assert any(line.startswith("no plot: matplotlib could not draw these values") for line in lines), lines
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["sweep.csv", "sweep.json"]
                                                                + (["sweep.parquet"] if any("parquet" in x and "wrote" in x for x in lines) else []))
    # Without matplotlib too, an earlier picture is not left beside tables it does not show.
    (tmp_path / "sweep.png").write_bytes(b"an earlier sweep's picture")
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    lines = write_outputs(table, tmp_path, meta={"partial": False})
    assert any(line.startswith("no plot: matplotlib is not installed") for line in lines)
    assert not (tmp_path / "sweep.png").exists()


def test_write_outputs_into_a_file_is_a_value_error_naming_it(tmp_path):
    """``write_outputs`` into a path that is a file raised a bare ``FileExistsError`` from
    ``os.makedirs`` (the CLI checks its --output before the samples; the Python API did not)."""
    from warp_esph.sweep import SUMMARY_COLUMNS, write_outputs

    q = SUMMARY_COLUMNS[0]
    table = SweepTable(columns=["sample", "yield_stress", "status", q],
                       rows=[{"sample": 0, "yield_stress": 10.0, "status": "ok", q: 1.0}], params=["yield_stress"])
    taken = tmp_path / "results"
    taken.write_text("a file\n")
    with pytest.raises(ValueError, match=re.escape(f"folder = {str(taken)!r} is not allowed: it is a file; the sweep's "
                                                   "tables (sweep.csv, sweep.parquet, sweep.png, sweep.json) are written "
                                                   "into a folder")):
        write_outputs(table, taken, plot_figure=False)
    assert taken.read_text() == "a file\n"
    assert [os.path.basename(line.split()[-1]) for line in write_outputs(table, tmp_path / "new", plot_figure=False)
            if line.startswith("wrote")][:1] == ["sweep.csv"]


def test_the_tables_are_written_into_a_folder_named_in_bytes_that_are_not_utf8(tmp_path):
    """pyarrow reads a file name as a UTF-8 URI: a sweep -o $'\\xfc' ran every sample, wrote
    sweep.csv, then failed sweep.parquet with "'utf-8' codec can't encode ...", exit 2, its
    sweep.json and sweep.png never written."""
    pq = pytest.importorskip("pyarrow.parquet")
    from warp_esph.sweep import SUMMARY_COLUMNS, write_outputs

    q = SUMMARY_COLUMNS[0]
    table = SweepTable(columns=["sample", "yield_stress", "status", q],
                       rows=[{"sample": k, "yield_stress": 10.0 * (k + 1), "status": "ok", q: 0.5 * k} for k in range(3)],
                       params=["yield_stress"])
    folder = tmp_path / os.fsdecode(b"\xfc")  # a name Linux holds, which Python keeps as a surrogate escape
    write_outputs(table, folder, meta={"partial": False}, plot_figure=False)
    assert {"sweep.csv", "sweep.parquet", "sweep.json"} <= set(os.listdir(folder))
    with open(folder / "sweep.parquet", "rb") as fh:
        back = pq.read_table(fh)
    assert back.column("yield_stress").to_pylist() == [10.0, 20.0, 30.0]
    assert back.column(q).to_pylist() == [0.0, 0.5, 1.0]


def test_a_signal_after_the_last_sample_keeps_the_whole_tables_and_says_so(scene_file, tmp_path, monkeypatch, capsys):
    """Every sample ran, then a SIGTERM (or Ctrl-C) landed while the final tables were
    written, or under the plot: the line said 'terminated' alone, a table could be cut short
    of the partial one, and an earlier sweep's sweep.png stayed beside the new tables. The
    tables are now finished first, the stale picture removed, and the line says what is kept."""
    import signal

    from warp_esph import sweep as sweep_module

    real_csv = SweepTable.to_csv

    def to_csv_terminated(self, path):
        if len(self) == 2:  # the final table: the partial one after the first sample has 1 row
            os.kill(os.getpid(), signal.SIGTERM)
        return real_csv(self, path)

    monkeypatch.setattr(sweep_module, "PARTIAL_EVERY_S", 1e9)
    monkeypatch.setattr(SweepTable, "to_csv", to_csv_terminated)
    out = tmp_path / "sw"
    argv = ["sweep", scene_file, "--param", "yield_stress=10,100", "--frames", "1", "--workers", "1", "-o", str(out),
            "--no-progress"]
    out.mkdir()
    # The signal held until the tables are whole stops the command before the plot: an earlier
    # sweep's picture must not stay beside the new tables either.
    (out / "sweep.png").write_bytes(b"an earlier sweep's picture")
    assert cli.main(argv) == 143
    err = capsys.readouterr().err
    assert err.splitlines()[-1] == f"warp-esph: terminated: the tables in {out} keep all 2 samples; sweep.png is not written"
    assert len(SweepTable.read_csv(out / "sweep.csv")) == 2
    assert json.loads((out / "sweep.json").read_text())["samples"] == 2 and not (out / "sweep.png").exists()
    monkeypatch.setattr(SweepTable, "to_csv", real_csv)

    def plot_interrupted(*a, **k):
        raise KeyboardInterrupt

    (out / "sweep.png").write_bytes(b"an earlier sweep's picture")
    monkeypatch.setattr(sweep_module, "plot", plot_interrupted)
    assert cli.main(argv) == 130
    err = capsys.readouterr().err
    assert err.splitlines()[-1] == f"warp-esph: interrupted: the tables in {out} keep all 2 samples; sweep.png is not written"
    assert len(SweepTable.read_csv(out / "sweep.csv")) == 2 and not (out / "sweep.png").exists()


def test_a_signal_held_while_the_final_tables_fail_to_write_is_reported(scene_file, tmp_path, monkeypatch, capsys):
    """A SIGTERM held while the final tables were written, whose write then failed (a full
    disk), was dropped: the sweep exited 4 as a plain failed write. The signal wins (143,
    130 for Ctrl-C) and the one line says both."""
    import errno
    import signal

    from warp_esph import sweep as sweep_module

    def to_csv_terminated_then_full(self, path):
        os.kill(os.getpid(), signal.SIGTERM)  # held: the tables are being written
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(sweep_module, "PARTIAL_EVERY_S", 1e9)
    monkeypatch.setattr(SweepTable, "to_csv", to_csv_terminated_then_full)
    out = tmp_path / "sw"
    assert cli.main(["sweep", scene_file, "--param", "yield_stress=10,100", "--frames", "1", "--workers", "1",
                     "-o", str(out), "--no-progress"]) == 143
    err = capsys.readouterr().err
    assert err.splitlines()[-1] == (f"warp-esph: terminated: cannot write the sweep's tables in {out}: [Errno 28] No "
                                    f"space left on device: '{out / 'sweep.csv'}' (2 samples ran; the tables in {out} "
                                    "are not this sweep's whole result)"), err


def test_a_signal_held_while_the_final_tables_raise_a_value_error_is_reported(scene_file, tmp_path, monkeypatch, capsys):
    """As above, where the table's write raises a ValueError, not an OSError: the signal was
    dropped and the sweep exited 2 with the error alone. The signal wins (143) and the one
    line says both; without a signal the error stays exit 2."""
    import signal

    from warp_esph import sweep as sweep_module

    def to_csv_terminated_then_bad(self, path):
        os.kill(os.getpid(), signal.SIGTERM)  # held: the tables are being written
        raise ValueError("a value the table cannot hold")

    monkeypatch.setattr(sweep_module, "PARTIAL_EVERY_S", 1e9)
    monkeypatch.setattr(SweepTable, "to_csv", to_csv_terminated_then_bad)
    command = ["sweep", scene_file, "--param", "yield_stress=10,100", "--frames", "1", "--workers", "1",
               "-o", str(tmp_path / "sw"), "--no-progress"]
    assert cli.main(command) == 143
    err = capsys.readouterr().err
    assert err.splitlines()[-1] == "warp-esph: terminated: a value the table cannot hold", err

    def to_csv_bad(self, path):
        raise ValueError("a value the table cannot hold")

    monkeypatch.setattr(SweepTable, "to_csv", to_csv_bad)
    assert cli.main(command) == 2
    assert capsys.readouterr().err.splitlines()[-1] == "warp-esph: error: a value the table cannot hold"


def test_a_duration_shorter_than_a_frame_records_the_one_frame_it_ran_and_a_long_one_says_frames_and_steps(
        scene_file, tmp_path, capsys):
    """A duration is rounded to whole frames, at least one: ``--duration 1e-320`` ran one frame
    while sweep.json said ``"frames": null``. A duration beyond a run's steps compared its
    frames with 'the 1e+10 steps' as if they were steps."""
    out = tmp_path / "short"
    assert cli.main(["sweep", scene_file, "--param", "paste.yield_stress=10000", "--duration", "1e-320", "--workers", "1",
                     "-o", str(out), "--no-progress"]) == 0
    meta = json.loads((out / "sweep.json").read_text())
    assert (meta["frames"], meta["duration"]) == (1, 1e-320)
    (row,) = SweepTable.read_csv(out / "sweep.csv").rows
    assert row["steps"] == round(1 / 30 / row["dt"])  # one frame's steps
    capsys.readouterr()
    assert cli.main(["sweep", scene_file, "--param", "paste.yield_stress=10000", "--duration", "1e300", "--workers", "1",
                     "-o", str(tmp_path / "long"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err == ("warp-esph: error: --duration = 1e+300 is not allowed: at 30 fps it is 3e+301 frames of at least one "
                   "step each, more than the 1e+10 steps a run may take\n")


def test_the_solver_column_shows_where_auto_switches_models(tmp_path):
    """``fit="auto"`` resolves by the sample's values: ``flow_rate = 0`` runs the
    rest-configuration model with the corrected fit and the control, ``flow_rate > 0`` the
    linear incremental fit. The ``solver`` column says which ran (before, only the sweep's
    requested ``"auto"`` was recorded); a table written before the column still reads."""
    table = sweep(_box(), ["flow_rate=0,5"], frames=1, workers=1)
    assert [r["status"] for r in table.rows] == ["ok", "ok"]
    assert list(table.column("solver")) == ["rest curvature_corrected c=0.05", "incremental linear c=0"]
    back = SweepTable.read_csv(table.to_csv(tmp_path / "t.csv"))
    assert back.column("solver").tolist() == table.column("solver").tolist()
    old = SweepTable([c for c in table.columns if c != "solver"],
                     [{k: v for k, v in r.items() if k != "solver"} for r in table.rows], table.params)
    assert "solver" not in SweepTable.read_csv(old.to_csv(tmp_path / "old.csv")).columns


def test_the_parquet_table_has_no_value_where_the_csv_has_none(tmp_path):
    """A diverged sample has no summary: its CSV cells are empty (no value, read back as None),
    but its Parquet cells were NaN, a number, so a mean over the Parquet column (pyarrow,
    polars, DuckDB) was NaN where the CSV's skipped the failed sample. Both now say the same:
    no value, and the mean is the ok sample's."""
    pq = pytest.importorskip("pyarrow.parquet")
    import pyarrow.compute as pc

    # dt = 1/300 s is stable for mu = 1e3 Pa and 20x above the limit for mu = 1e6 Pa.
    table = sweep(_box(), ["mu=1000,1000000"], frames=2, dt=1 / 300, workers=1)
    assert [r["status"] for r in table.rows] == ["ok", "failed"]
    back = SweepTable.read_csv(table.to_csv(tmp_path / "t.csv"))
    par = pq.read_table(table.to_parquet(tmp_path / "t.parquet"))
    assert par.column_names == back.columns
    assert par.to_pylist() == back.rows
    for q in ("max_height", "kinetic_energy"):
        assert pc.mean(par[q]).as_py() == table.rows[0][q]


def test_a_sweep_whose_samples_all_ran_has_no_reason_in_its_parquet_table(serial, tmp_path):
    """Where every sample ran, no row has a reason or a warning: the CSV's cells are empty, but
    the Parquet table's were the text 'nan' (the empty column read as numbers, then written as
    text), so a filter for the failed samples ('reason is not null') found every one."""
    pq = pytest.importorskip("pyarrow.parquet")
    assert serial.all_ok and not any(r["reason"] or r["warnings"] for r in serial.rows)
    par = pq.read_table(serial.to_parquet(tmp_path / "t.parquet"))
    assert par["reason"].null_count == par["warnings"].null_count == len(serial)
    assert par.to_pylist() == SweepTable.read_csv(serial.to_csv(tmp_path / "t.csv")).rows


def _extra_numpy(model, state, seed):
    """An ``extra`` as one is written: numpy's float32 and int64, not Python numbers."""
    y = state.x.numpy()[:, 1]
    return {"top_y": y.max(), "above_5cm": np.sum(y > 0.05)}


def test_extra_columns_of_numpy_numbers_are_the_same_numbers_in_every_table(tmp_path):
    """An ``extra`` returning numpy numbers (``y.max()`` is a float32, ``np.sum(mask)`` an
    int64) made Parquet columns of text ('0.0475') and CSV cells of float32's shortest text,
    read back as another float; an int column read back as floats, and Parquet wrote it as
    doubles. The table, its CSV read back and its Parquet now hold the same numbers."""
    table = sweep(_box(), ["yield_stress=10,10000"], frames=4, workers=1, extra=_extra_numpy)
    x = [r["top_y"] for r in table.rows]
    n = [r["above_5cm"] for r in table.rows]
    assert all(type(v) is float for v in x) and all(type(v) is int for v in n), table.rows
    # A higher yield stress slumps less: its top stays higher, with more particles above 5 cm.
    assert x[0] < x[1] and n[0] <= n[1]
    back = SweepTable.read_csv(table.to_csv(tmp_path / "t.csv"))
    assert back.rows == table.rows
    pq = pytest.importorskip("pyarrow.parquet")
    par = pq.read_table(table.to_parquet(tmp_path / "t.parquet"))
    assert str(par.schema.field("top_y").type) == "double" and str(par.schema.field("above_5cm").type) == "int64"
    assert par.to_pylist() == table.rows


@pytest.mark.parametrize("lo, hi, mid", [(100.0, 1e4, 1e3), (1e-200, 1e-150, 1e-175), (1e200, 1e300, 1e250)])
def test_one_log_level_is_the_geometric_midpoint_of_any_range(lo, hi, mid):
    """``NAME=LO:HI:log:1`` is sqrt(LO HI), inside the range: the product LO HI underflowed to 0
    (1e-200 x 1e-150; the sample ran with a yield stress of 0, outside the range) or
    overflowed to inf (1e200 x 1e300), where sqrt(LO) sqrt(HI) is the number."""
    (point,) = sample_points([f"yield_stress={lo!r}:{hi!r}:log:1"])
    y = point["yield_stress"]
    assert lo < y < hi and y == pytest.approx(mid, rel=1e-12, abs=0.0)


def test_a_worker_that_dies_takes_down_only_the_samples_it_ran_beside(dying_worker_sweep):
    """A sample that kills its worker process (a crash in native code, out of memory) broke
    the pool, and every sample not finished then failed with it, the many never started too:
    one crash in a long sweep left its remaining rows 'a worker process died'. The samples not
    yet handed to a worker now run in a fresh pool, as on Ray, where only the task fails; those
    the broken pool failed beside it (which one died cannot be told; a sample queued next to it
    failed too, whenever it was in flight at the crash, so which rows failed depended on timing)
    run again alone, and only the sample that dies alone fails."""
    table = dying_worker_sweep
    status = [(r["status"], r["reason"]) for r in table.rows]
    assert status[0][0] == "failed" and "worker process died running this item alone" in status[0][1], status
    assert status[1] == ("failed", "TypeError: a bug in extra"), status
    assert [s for s, _ in status[2:]] == ["ok"] * 4, status
    # The fresh pool's samples are the same runs: the slump still follows the yield stress.
    top = table.column("max_height")[2:]
    assert top[0] < top[1] < top[2] < top[3]


def test_an_item_in_flight_when_another_kills_its_worker_runs_again_alone(tmp_path):
    """Item 3 was running (or queued) in the other worker when item 0 killed its own: the
    broken pool failed it too, a row lost to the timing of another. It runs again alone and
    returns; item 0, which dies alone too, is the one that fails."""
    from warp_esph.sweep import parallel_map

    out = parallel_map(_dies_first, [(i, str(tmp_path)) for i in range(5)], workers=2, on_error=lambda i, why: why)
    assert out[1:] == [1, 2, 3, 4], out
    assert "worker process died running this item alone" in out[0], out[0]
    with pytest.raises(RuntimeError, match="item 0: a worker process died"):
        parallel_map(_dies_first, [(0, str(tmp_path)), (1, str(tmp_path))], workers=2)


def test_without_on_error_the_item_that_kills_its_worker_is_the_one_named(tmp_path):
    """Without ``on_error`` a dead worker raised at once, naming the lowest item in flight:
    item 0, still running beside item 1 when item 1 killed its worker, was named, and the
    message (and which item) depended on what happened to be in flight. The items in flight
    run again alone first, as with ``on_error``, and the one that dies alone is named."""
    from warp_esph.sweep import parallel_map

    marker = str(tmp_path / "item 1 ran")
    with pytest.raises(RuntimeError, match=r"^item 1: a worker process died running this item alone"):
        parallel_map(_dies_second, [(0, marker), (1, marker)], workers=2)


def test_a_sample_whose_value_does_not_hold_in_float32_names_the_command_s_dtype_too():
    """A sample value that float32 does not hold is a failed row whose reason advised
    'use dtype=float64', Python's spelling, in the table warp-esph sweep writes too, where
    the option is --dtype float64: the reason names both."""
    from warp_esph.sweep import _run_sample

    plan = _plan(_box(), ["mu=1e4,1e39"], "grid", None, 0, 1, None, 30.0, None, 1.0, "float32", "cpu", 1, 100, None)
    rows = [_run_sample(plan.scene, t) for _, t in plan.tasks]
    assert [r["status"] for r in rows] == ["ok", "failed"], rows
    assert rows[1]["reason"] == ("ValueError: material 0 (body 'paste'): Material.mu = 1e+39 is not allowed in float32: must be at most 3.4e+38; "
                                 "use dtype=float64 (--dtype float64) or a smaller value"), rows[1]["reason"]


# ------------------------------------------------------------------ resuming a stopped sweep
def _stopped_after(k: int):
    """An ``on_result`` that stops the sweep (as Ctrl-C does) once ``k`` samples finished."""
    finished = []

    def stop(row):
        finished.append(row["sample"])
        if len(finished) == k:
            raise KeyboardInterrupt

    return stop


def test_a_python_sweep_stopped_after_one_sample_resumes_to_the_table_of_one_run_straight_through(serial, tmp_path):
    """A stopped sweep kept nothing and had to run every sample again. Its KeyboardInterrupt
    now carries the samples finished, and ``resume=`` runs only the others: the table is the
    one run straight through gives, from the table itself, its Parquet file or its folder."""
    from warp_esph.sweep import write_outputs

    with pytest.raises(KeyboardInterrupt) as stopped:
        sweep(_box(), [YIELD], frames=FRAMES, workers=1, on_result=_stopped_after(1))
    part = stopped.value.table
    assert [r["sample"] for r in part.rows] == [0]
    write_outputs(part, tmp_path / "sw", plot_figure=False)
    for source in (part, tmp_path / "sw", tmp_path / "sw" / "sweep.csv", tmp_path / "sw" / "sweep.parquet"):
        ran = []
        whole = sweep(_box(), [YIELD], frames=FRAMES, workers=1, resume=source, on_result=lambda r: ran.append(r["sample"]))
        assert ran == [1, 2], source
        assert whole.columns == serial.columns and _rows(whole) == _rows(serial), source
        assert whole.rows[0]["wall_s"] == part.rows[0]["wall_s"]  # the row kept, not run again


def test_a_resumed_sweep_runs_its_failed_samples_again_only_when_asked(serial, monkeypatch):
    """``retry_failed``: a sample that failed in the stopped run (its worker died) runs again;
    without it the failed row is kept as it is, as the table's other rows are."""
    from warp_esph import sweep as sweep_module

    real = sweep_module._run_sample

    def dies_at_sample_1(scene, task):
        if task.index == 1:
            return {"sample": 1, "status": "failed", **task.values, "seed": task.seed, "reason": "a worker died"}
        return real(scene, task)

    monkeypatch.setattr(sweep_module, "_run_sample", dies_at_sample_1)
    first = sweep(_box(), [YIELD], frames=FRAMES, workers=1)
    monkeypatch.setattr(sweep_module, "_run_sample", real)
    assert [r["status"] for r in first.rows] == ["ok", "failed", "ok"]
    ran = []
    kept = sweep(_box(), [YIELD], frames=FRAMES, workers=1, resume=first, on_result=lambda r: ran.append(r["sample"]))
    assert ran == [] and _rows(kept) == _rows(first)
    again = sweep(_box(), [YIELD], frames=FRAMES, workers=1, resume=first, retry_failed=True,
                  on_result=lambda r: ran.append(r["sample"]))
    assert ran == [1] and _rows(again) == _rows(serial)
    with pytest.raises(ValueError, match="^retry_failed is not allowed without resume"):
        sweep(_box(), [YIELD], frames=FRAMES, workers=1, retry_failed=True)


def test_a_table_of_another_sweep_is_refused_naming_what_differs(serial):
    """Resuming must not mix two sweeps' rows: other frames, levels, sampling or seed,
    another scene or precision, each is refused before any sample runs, by name."""
    assert serial.identity is not None
    cases = [
        (dict(frames=FRAMES + 1), "frames = 10 there, 11 here"),
        (dict(params=["yield_stress=10:10000:log:4"]), "params = [yield_stress=10.0:10000.0:log:3] there, "
                                                       "[yield_stress=10.0:10000.0:log:4] here; samples = 3 there, 4 here"),
        (dict(params=["yield_stress=10:10000:log"], sample="lhs", samples=3, seed=1),
         "params = [yield_stress=10.0:10000.0:log:3] there, [yield_stress=10.0:10000.0:log] here; sample = \"grid\" "
         "there, \"lhs\" here; seed = 0 there, 1 here"),
        (dict(dtype="float64"), "dtype = \"float32\" there, \"float64\" here"),
    ]
    for change, words in cases:
        args = {"params": [YIELD], "frames": FRAMES, **change}
        with pytest.raises(ValueError, match=re.escape(f"its table is of another sweep: {words};")):
            sweep(_box(), args.pop("params"), workers=1, resume=serial, **args)
    other = _box()
    other.builder.add_sphere((0.3, 0.1, 0.0), 0.04, Material.preset("toothpaste"), name="blob")
    with pytest.raises(ValueError, match=r"^resume = <SweepTable of 3 rows> is not allowed: its table is of another "
                                         r"sweep: model = \"125 particles, [0-9a-f]+\" there, \"1[0-9]+ particles, "):
        sweep(other, [YIELD], frames=FRAMES, workers=1, resume=serial)
    plain = SweepTable(serial.columns, serial.rows, serial.params)  # as read from a CSV file alone
    with pytest.raises(ValueError, match="it holds no record of the sweep that wrote it"):
        sweep(_box(), [YIELD], frames=FRAMES, workers=1, resume=plain)
    garbled = SweepTable(serial.columns, serial.rows, serial.params, ["not", "a", "record"])  # a sweep.json edited by hand
    with pytest.raises(ValueError, match="it holds no record of the sweep that wrote it"):
        sweep(_box(), [YIELD], frames=FRAMES, workers=1, resume=garbled)


def test_a_terminated_cli_sweep_resumed_gives_the_table_of_one_run_straight_through(scene_file, tmp_path, monkeypatch,
                                                                                   capsys, three_sample_sweep):
    """``warp-esph sweep ... --resume`` after a SIGTERM at the second of 3 samples runs the
    two it lacks and writes the table (CSV and Parquet) an uninterrupted run writes."""
    import signal

    from warp_esph import sweep as sweep_module

    status, err, rows, _ = _sweep_signalled_at_the_second_sample(scene_file, tmp_path, monkeypatch, capsys,
                                                                 lambda: os.kill(os.getpid(), signal.SIGTERM))
    assert status == 143 and rows == 1, err
    real, ran = sweep_module._run_sample, []

    def counted(scene, task):
        ran.append(task.index)
        return real(scene, task)

    monkeypatch.setattr(sweep_module, "_run_sample", counted)
    out = tmp_path / "sw"
    assert cli.main(["sweep", scene_file, "--param", "yield_stress=10,100,1000", "--frames", "1", "--workers", "1",
                     "-o", str(out), "--no-progress", "--resume"]) == 0
    assert ran == [1, 2]
    assert "3 samples (grid) of yield_stress on 1 worker -> " in capsys.readouterr().err  # ('1 worker(s)' before)
    straight = SweepTable.read_csv(three_sample_sweep / "sweep.csv")  # the same sweep, run straight through
    for table in (SweepTable.read_csv(out / "sweep.csv"), SweepTable.read_parquet(out / "sweep.parquet")):
        assert table.columns == straight.columns and _rows(table) == _rows(straight)
    record = json.loads((out / "sweep.json").read_text())
    assert record["resumed"] == {"kept": 1, "retry_failed": False} and record["sweep"]["frames"] == 1


@pytest.fixture(scope="module")
def three_sample_sweep(tmp_path_factory):
    """The output folder of one finished 3-sample sweep of ``SCENE_TOML``, which each case
    below copies: the table a resume is asked of (the scene file is recorded by its digest)."""
    folder = tmp_path_factory.mktemp("three_sample_sweep")
    path = folder / "box.toml"
    path.write_text(SCENE_TOML)
    assert cli.main(["sweep", str(path), "--param", "yield_stress=10,100,1000", "--frames", "1", "--workers", "1",
                     "-o", str(folder / "sw"), "--no-progress"]) == 0
    return folder / "sw"


@pytest.mark.parametrize("change, words", [
    (["--frames", "2"], "--resume of --output = '{out}' is not allowed: its table is of another sweep: frames = 1 there, "
                        "2 here; resume it with the settings it was run with, or run this sweep anew without resuming"),
    (["--param", "yield_stress=10,100"], "its table is of another sweep: params = [yield_stress=10.0,100.0,1000.0] "
                                         "there, [yield_stress=10.0,100.0] here; samples = 3 there, 2 here;"),
    (["--hourglass", "0.2"], "its table is of another sweep: solver = {{\"fit\": null, \"contact_ramp\": 1.0, "
                             "\"hourglass\": null, \"fit_weight\": \"{weight}\"}} there, {{\"fit\": null, "
                             "\"contact_ramp\": 1.0, \"hourglass\": 0.2, \"fit_weight\": \"{weight}\"}} here;"),
    (["--edit-scene"], "its table is of another sweep: scene_file = "),
    (["--elsewhere"], "--resume of --output = '{out}' is not allowed: there is no such file or folder, so there is "
                      "nothing to resume; run the sweep without it"),
    (["--no-resume", "--retry-failed"], "--retry-failed is not allowed without --resume"),
])
def test_the_command_refuses_to_resume_a_table_of_another_sweep_before_any_sample(scene_file, tmp_path, monkeypatch,
                                                                                   capsys, change, words,
                                                                                   three_sample_sweep):
    from warp_esph import sweep as sweep_module

    out = tmp_path / "sw"
    shutil.copytree(three_sample_sweep, out)
    before = (out / "sweep.csv").read_bytes()
    capsys.readouterr()
    monkeypatch.setattr(sweep_module, "_run_sample", lambda *a: pytest.fail("a sample ran"))
    args = {"--param": "yield_stress=10,100,1000", "--frames": "1"}
    flags = ["--resume"]
    if change == ["--edit-scene"]:
        with open(scene_file, "a") as f:
            f.write("\n# edited\n")
    elif change == ["--elsewhere"]:
        out = tmp_path / "none"
    elif change[0] == "--no-resume":
        flags = change[1:]
    else:
        args[change[0]] = change[1]
    argv = ["sweep", scene_file, *[x for kv in args.items() for x in kv], "--workers", "1", "-o", str(out),
            "--no-progress", *flags]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    # The scene names no fit weight: the record shows the default's.
    assert err.count("\n") == 1 and words.format(out=out, weight=DEFAULT_FIT_WEIGHT) in err, err
    assert (tmp_path / "sw" / "sweep.csv").read_bytes() == before


def test_a_sweep_that_ran_poly6_by_default_is_told_to_resume_with_fit_weight_poly6(scene_file, tmp_path, monkeypatch,
                                                                                  capsys):
    """A sweep begun before the biweight became the default (2026-12-06) with no weight named
    ran poly6 and recorded it (``solver``'s ``fit_weight``: every sweep record holds it, the
    option being older than the record). The same command now names the biweight and another
    model, and is refused; the refusal named the model and the solver's dict alone, read as
    another scene. It names the option that resumes it, and with that option the table's rows
    are kept and no sample runs again."""
    from warp_esph import sweep as sweep_module

    args = ["sweep", scene_file, "--param", "yield_stress=10,100", "--frames", "1", "--workers", "1", "--no-progress"]
    # The record a pre-switch run of the same command wrote: poly6, named by the option now.
    assert cli.main([*args, "-o", str(tmp_path / "whole"), "--fit-weight", "poly6"]) == 0
    assert json.loads((tmp_path / "whole" / "sweep.json").read_text())["sweep"]["solver"]["fit_weight"] == "poly6"
    shutil.copytree(tmp_path / "whole", tmp_path / "sw")
    capsys.readouterr()
    monkeypatch.setattr(sweep_module, "_run_sample", lambda *a: pytest.fail("a sample ran"))
    assert cli.main([*args, "-o", str(tmp_path / "sw"), "--resume"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "its table is of another sweep: model = " in err, err
    assert "resume it with the settings it was run with (its fit weight: --fit-weight poly6; a sweep begun before " \
           "2026-12-06 that named none ran poly6, the default then)" in err, err
    with pytest.raises(ValueError, match=re.escape("(its fit weight: the scene's fit_weight = 'poly6', "
                                                   "SceneBuilder(fit_weight=...) or [solver] fit_weight; a sweep begun")):
        sweep(scene_file, ["yield_stress=10,100"], frames=1, workers=1, resume=str(tmp_path / "sw"))
    assert cli.main([*args, "-o", str(tmp_path / "sw"), "--resume", "--fit-weight", "poly6"]) == 0
    assert "2 kept from its table, 0 to run" in capsys.readouterr().err
    assert _rows(SweepTable.read_csv(tmp_path / "sw" / "sweep.csv")) == _rows(SweepTable.read_csv(tmp_path / "whole" / "sweep.csv"))


@pytest.mark.parametrize("label", [3.0, 1.0, 3.5, True, "4", 0, 5, None])
def test_a_sweep_table_s_fingerprint_version_reads_one_way(three_sample_sweep, scene_file, tmp_path, monkeypatch, capsys,
                                                         label):
    """``sweep --resume`` of a table whose record's ``fingerprint_version`` was edited: 3.0 is
    version 3 (this scene's record of 3 is its record of 4), whose rows are kept (it was refused
    as another record format's); 1.0, a version but none of this record format's, is refused as
    another format's, named as read (1); a bool, a string, 3.5, 0, a version newer than this
    build's or null is refused in one line naming the field, its value and what is allowed,
    exit 2, the table untouched. Seen failing with ``_resumed_rows`` reading the version as the
    file has it (3.0 refused, the rest refused as another format's, naming no field), with
    ``checkpoint.read_fingerprint_version`` taking a bool (True read as version 1, another
    format's), and (1.0, shown as 1.0) with the format's check reading the file's value."""
    from warp_esph import sweep as sweep_module

    out = tmp_path / "sw"
    shutil.copytree(three_sample_sweep, out)
    record = json.loads((out / "sweep.json").read_text())
    record["sweep"]["fingerprint_version"] = label
    (out / "sweep.json").write_text(json.dumps(record))
    before = (out / "sweep.csv").read_bytes()
    capsys.readouterr()
    monkeypatch.setattr(sweep_module, "_run_sample", lambda *a: pytest.fail("a sample ran"))
    argv = ["sweep", scene_file, "--param", "yield_stress=10,100,1000", "--frames", "1", "--workers", "1", "-o", str(out),
            "--no-progress", "--resume"]
    if label == 3.0:
        assert cli.main(argv) == 0
        assert "3 kept from its table, 0 to run" in capsys.readouterr().err
        return
    if label == 1.0 and isinstance(label, float):  # not True, which == 1.0
        # A version, but not one a table of this record format was written with: refused as
        # another format's, naming the version as read (1, as every check reads it).
        assert cli.main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "(record format 2, model fingerprint 1); this is" in err, err
        assert (out / "sweep.csv").read_bytes() == before
        return
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.endswith(
        f"--resume of --output = '{out}' is not allowed: its record has fingerprint_version = {json.dumps(label)} (must be an "
        "integer from 1 to 4, the versions this warp_esph reads); rerun without --resume\n"), err
    assert (out / "sweep.csv").read_bytes() == before


# ------------------------------------------------------------------ CUDA samples on Ray
def test_a_cuda_sweep_s_ray_tasks_see_a_gpu_where_ray_hides_them_from_tasks_that_ask_none(monkeypatch):
    """Older Ray (as Ray with RAY_ACCEL_ENV_VAR_OVERRIDE_ON_ZERO=1, set here) sets
    CUDA_VISIBLE_DEVICES='' in a task that asks for no GPU: a device='cuda' sweep's tasks,
    which asked for one CPU only, found no GPU, every sample failing. Each asks for a GPU, and
    its task sees the one Ray gave it (a cluster declaring one GPU; this machine may have none,
    so the samples' own rows are not read)."""
    ray = pytest.importorskip("ray")
    from warp_esph import sweep as sweep_module
    from warp_esph.sweep import parallel_map

    asked = []
    real = sweep_module._ray_tasks

    def spy(session, fn, items, on_result, on_error, resources):
        asked.append(resources)
        return real(session, fn, items, on_result, on_error, resources)

    monkeypatch.setattr(sweep_module, "_ray_tasks", spy)
    monkeypatch.setenv("RAY_ACCEL_ENV_VAR_OVERRIDE_ON_ZERO", "1")
    ray.init(num_cpus=1, num_gpus=1, include_dashboard=False, log_to_driver=False)
    try:
        sweep(_box(), ["mu=1e4"], frames=1, device="cuda", ray="auto")
        seen = parallel_map(os.getenv, [("CUDA_VISIBLE_DEVICES",)], ray="auto", ray_resources=asked[0])
    finally:
        ray.shutdown()
    assert seen == ["0"], asked


def test_a_resumed_sweep_stopped_again_keeps_the_rows_it_resumed_from(scene_file, tmp_path, monkeypatch, capsys):
    """The tables a resumed sweep writes on a stop (and as samples finish) hold the rows it
    kept as well as those it ran, so that a second stop loses neither; a third run finishes."""
    import signal

    from warp_esph import sweep as sweep_module

    status, err, rows, _ = _sweep_signalled_at_the_second_sample(scene_file, tmp_path, monkeypatch, capsys,
                                                                 lambda: os.kill(os.getpid(), signal.SIGTERM))
    assert status == 143 and rows == 1, err
    monkeypatch.setattr(sweep_module, "PARTIAL_EVERY_S", 0.0)
    out = tmp_path / "sw"
    argv = ["sweep", scene_file, "--param", "yield_stress=10,100,1000", "--frames", "1", "--workers", "1", "-o", str(out),
            "--no-progress", "--resume"]
    real = sweep_module._run_sample

    def stop_at_the_second_run(scene, task):
        if task.index == 2:
            os.kill(os.getpid(), signal.SIGTERM)
        return real(scene, task)

    monkeypatch.setattr(sweep_module, "_run_sample", stop_at_the_second_run)
    assert cli.main(argv) == 143
    assert capsys.readouterr().err.splitlines()[-1] == "warp-esph: terminated: the table keeps the 2 of 3 samples finished"
    assert [r["sample"] for r in SweepTable.read_csv(out / "sweep.csv").rows] == [0, 1]
    monkeypatch.setattr(sweep_module, "_run_sample", real)
    assert cli.main(argv) == 0
    assert [r["sample"] for r in SweepTable.read_csv(out / "sweep.csv").rows] == [0, 1, 2]


def test_a_sample_gone_non_finite_is_a_failed_row_naming_step_frame_and_particle():
    """A sample whose run goes non-finite (a 27-particle float32 cube at mu 2.4e6 Pa, 20 steps
    of a dt 17 x its stable step, within its first frame) is a failed row whose reason names
    the step, the frame and the first non-finite particle, as a finite blow-up's does; the
    other sample runs."""
    b = SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.0, 0.0), (0.06, 0.06, 0.06), Material(mu=1e3, lam=1.5e3, density=1000.0), name="cube")
    dt = 0.5 * b.finalize().stable_dt()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # the stiff sample's dt past its stable step, on purpose
        table = sweep(b, {"mu": [1e3, 2.4e6], "lam": [1.5e3]}, frames=1, fps=1.0 / (20 * dt), dt=dt, workers=1)
    assert [r["status"] for r in table.rows] == ["ok", "failed"]
    assert re.fullmatch(r"the simulation diverged after step 20 \(frame 1, .*\): non-finite position or velocity "
                        r"\(particle (\d+) is the first of \d+ bad particles\), at particle \1 of body 'cube'; the "
                        r"sample's stable step is \S+ s", table.rows[1]["reason"]), table.rows[1]["reason"]


# ------------------------------------------------------------------ values no sample can use
def _rubber_box() -> Scene:
    """The test box of an elastic material (rubber: yield_stress = inf, flow_rate = 0)."""
    b = SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.06, 0.0), (0.1, 0.1, 0.1), Material.preset("rubber"), name="paste")
    b.add_ground(friction=0.5)
    return Scene("rubber_box", "a small box of rubber", b, frames=FRAMES, fps=30.0)


def _no_sample_runs(monkeypatch):
    import warp_esph.sweep as sweep_module

    def never(*_):
        raise AssertionError("a sample ran")

    monkeypatch.setattr(sweep_module, "_run_sample", never)


@pytest.mark.parametrize("specs, words", [
    (["yield_stress=10,100"], ["params entry yield_stress is not allowed", "material 0 (body 'paste')", "flow_rate = 0"]),
    (["hardening=0,1000"], ["params entry hardening is not allowed", "flow_rate = 0"]),
    (["paste.yield_stress=10:100:log:2", "hardening=0,10"], ["params entry paste.yield_stress is not allowed"]),
    (["flow_rate=10,100"], ["params entry flow_rate is not allowed", "yield_stress = inf"]),
])
def test_a_plastic_parameter_of_a_material_no_sample_lets_flow_is_refused_before_any_sample(monkeypatch, specs, words):
    """On an elastic material a yield stress, a flow rate alone or a hardening does nothing
    (measured: rubber's rows of yield_stress 10 and 100, hardening 0 and 1000, were the same
    to the bit, on the rest model and on the linear fit alike), and the sweep ran every
    sample and exited 0, a table of one result many times. It is refused before any sample,
    naming the parameter and what keeps the material from flowing."""
    _no_sample_runs(monkeypatch)
    with pytest.raises(ValueError) as e:
        sweep(_rubber_box(), specs, frames=1, workers=1)
    for w in words:
        assert w in str(e.value), (w, str(e.value))
    # Swept together, a yield stress and a flow rate make it plastic in some sample: taken.
    plan = _plan(_rubber_box(), ["yield_stress=10,100", "flow_rate=0,50", "hardening=0,10"], "grid", None, 0, 1, None,
                 30.0, None, 1.0, "float32", "cpu", 1, 100, None)
    assert len(plan.tasks) == 8


def test_a_sweep_every_sample_of_which_the_material_refuses_is_refused_before_any_sample(monkeypatch, scene_file,
                                                                                        tmp_path, capsys):
    """lam below -2 mu / 3 in every sample: each sample failed alone with the same refusal and
    the command exited 3 with a table of failures. Now it is bad input before any sample
    (exit 2), naming the parameter, the value and what the material allows; a sweep one of
    whose samples the material takes still runs (the others are failed rows)."""
    _no_sample_runs(monkeypatch)
    with pytest.raises(ValueError, match=r"^params entry lam is not allowed: the material refuses every sample's values "
                                         r"\(sample 0, lam = -1e\+09: material 0 \(body 'paste'\): Material\.lam = -1000000000\.0 is not "
                                         r"allowed: "
                                         r"must be > -2 mu / 3 = "):
        sweep(_box(), ["lam=-1e9,-2e9"], frames=1, workers=1)
    rc = cli.main(["sweep", scene_file, "--param", "hardening=-1e9", "--workers", "1", "--no-progress", "-o",
                   str(tmp_path / "never")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "--param hardening is not allowed" in err[0] and "-2 mu" in err[0], err
    assert not os.path.exists(tmp_path / "never")
    assert len(_plan(_box(), ["lam=-1e9,1000"], "grid", None, 0, 1, None, 30.0, None, 1.0, "float32", "cpu", 1, 100,
                     None).tasks) == 2


@pytest.mark.parametrize("specs, named, shown", [
    (["lam=-1e9,-2e9", "yield_stress=10,100"], "entry lam is", "lam = -1e+09: material 0 (body 'paste'): Material.lam = "),
    (["yield_stress=10,100", "hardening=-1e9"], "entry hardening is", "hardening = -1e+09: material 0 (body 'paste'): Material.hardening = "),
    (["yield_stress=10", "mu=1e308", "lam=1e308"], "entries mu, lam are", "mu = 1e+308, lam = 1e+308: material 0 (body 'paste'): Material.mu = "),
])
def test_a_sweep_the_material_refuses_names_only_the_parameters_the_refusal_is_about(monkeypatch, specs, named, shown):
    """Every swept parameter was named ('--param lam, yield_stress are not allowed') where the
    material's refusal is about one field of it: the caller was told to change a yield stress
    that every sample could keep. The refusal's fields (``Material.lam = ...``) are mapped back
    to the parameters that set them, and only theirs are named and shown."""
    _no_sample_runs(monkeypatch)
    with pytest.raises(ValueError) as e:
        sweep(_box(), specs, frames=1, workers=1)
    assert str(e.value).startswith(f"params {named} not allowed: the material refuses every sample's values (sample 0, "
                                   f"{shown}"), str(e.value)


# ------------------------------------------------------------------ a sample's own exception, wherever it runs
@pytest.fixture(scope="module")
def failing_everywhere():
    """``failing_everywhere(extra)``: the rows of a 2-sample sweep whose every sample fails
    in ``extra`` (one of ``SAMPLE_EXTRAS``), in this process and with two worker processes.
    One sweep of six samples, two per function, runs each way (one pool for the three tests);
    a test reads its function's two rows, numbered as the samples of a sweep of its own."""
    values = [10.0 * 2**k * f for k in range(len(SAMPLE_EXTRAS)) for f in (1.0, 10.0)]  # (a sweep takes each once)
    runs = {w: sweep(_box(), {"yield_stress": values}, frames=1, workers=w, extra=_extra_by_sample) for w in (1, 2)}

    def rows(extra):
        k = SAMPLE_EXTRAS.index(extra)
        return tuple([dict(r, sample=r["sample"] - 2 * k) for r in _rows(runs[w])[2 * k: 2 * k + 2]] for w in (1, 2))

    return rows


def test_a_sample_s_exception_the_parent_cannot_rebuild_is_its_reason_with_workers_too(failing_everywhere):
    """With worker processes, an exception that pickle cannot rebuild in the parent broke the
    pool: each sample ran again alone, broke it again, and its row said a worker process died
    'a crash in native code or out of memory', where the same sweep in one process said
    the exception. Each row now says the exception, as in one process."""
    here, there = failing_everywhere(_extra_raising_what_pickle_cannot_rebuild)
    assert [r["reason"] for r in here] == ["_TwoPartError: extra: no column today"] * 2
    assert [r["sample"] for r in here] == [0, 1]
    assert there == here


def test_a_sample_that_calls_sys_exit_is_a_failed_row_and_the_sweep_goes_on(failing_everywhere):
    """A sample whose code calls ``sys.exit`` (an ``extra`` function here) ended the whole sweep
    with SystemExit, in this process and with worker processes alike, and its samples finished
    were lost with it (on Ray it was a row saying the worker crashed). It is that sample's
    failed row, ``SystemExit: 4``, the same wherever it runs, and the other samples run."""
    here, there = failing_everywhere(_extra_that_exits)
    assert [(r["status"], r["reason"]) for r in here] == [("failed", "SystemExit: 4")] * 2
    assert there == here


@pytest.mark.parametrize("workers", [1, 2])
def test_parallel_map_without_on_error_raises_an_item_s_sys_exit_as_an_item_error_naming_it(workers):
    """Without ``on_error`` an item's ``sys.exit`` raised ``SystemExit`` in this process (the
    caller's program ended as if it had exited itself) and an ``ItemError`` from worker
    processes: one failure, two exceptions. Both raise ``ItemError`` naming the item and the
    exit's code, the words ``on_error`` is given."""
    from warp_esph.sweep import ItemError, parallel_map

    with pytest.raises(ItemError, match=r"^item 1: SystemExit: 5$"):
        parallel_map(_exits_at, [(0,), (1,)], workers=workers)
    assert parallel_map(_exits_at, [(0,), (1,)], workers=workers, on_error=lambda i, why: why) == [0, "SystemExit: 5"]


def test_an_extra_column_that_is_no_number_or_text_fails_its_sample_the_same_wherever_it_runs(failing_everywhere):
    """An ``extra`` value that is neither a number nor text (a function) was an ok row holding
    the object in one process (its CSV cell the object's repr) and a failed row with pickle's
    words in worker processes: two tables of one sweep. It is a failed row naming the column
    in both."""
    here, there = failing_everywhere(_extra_of_a_function)
    assert [r["status"] for r in here] == ["failed"] * 2
    assert here[0]["reason"] == ("ValueError: extra returned how = a function: a column's value must be "
                                 "a number, text or None"), here[0]["reason"]
    assert there == here


def test_a_parameter_of_every_material_leaves_an_elastic_particle_floor_as_built():
    """``yield_stress`` alone sets every material, and it set the elastic floor's too (the
    body's material made elastic, ``add_particle_floor(elastic=True)``), so the floor under a
    swept body flowed: a row was not the run of the body's value on the floor the scene built.
    As in ``fit`` (every material, ``Model.set_material`` of the body's), the floor is left
    as built: the row is a plain run with the body's yield stress set, to the last bit."""
    from warp_esph.simulate import resolve_timestep, simulate

    def scene():
        b = SceneBuilder(spacing=0.02)
        b.add_box((0.0, 0.05, 0.0), (0.08, 0.06, 0.06), Material.preset("toothpaste"), name="paste",
                  velocity=(0.4, -0.5, 0.0))
        b.add_particle_floor("paste", elastic=True, margin=0.02)
        return Scene("paste_on_floor", "toothpaste on an elastic floor", b, frames=2, fps=30.0)

    table = sweep(scene(), ["yield_stress=5"], frames=2, workers=1)
    model = scene().builder.finalize()
    walls = {b.floor_material for b in model.bodies if b.floor_material >= 0}
    assert walls and all(not math.isfinite(model.materials[k].yield_stress) for k in walls)
    for k in range(len(model.materials)):
        if k not in walls:
            model.set_material(k, model.materials[k].replace(yield_stress=5.0))
    _, dt = resolve_timestep(model, 30.0)
    state = simulate(model, 2, fps=30.0, dt=dt, progress=False)
    x = state.x.numpy().astype(np.float64)
    assert table.rows[0]["status"] == "ok" and table.rows[0]["dt"] == dt
    assert table.rows[0]["max_height"] == float(x[:, 1].max())


def test_a_sample_whose_tool_lifts_the_body_is_no_blow_up():
    """The end-of-run energy check took a moving tool's work for a blow-up ('nothing does work
    on the bodies'): a clay blob a floor tool lifts at 4 m/s for 0.3 s gains 1.2 m of height,
    more than 10 x its energy scale, and every sample failed. A tool that moves does work, as
    a force field does: the check is left to ``simulate``'s monitor, which counts it. The
    blob ends on the floor, 1.2 m up."""
    from warp_esph import tools

    b = SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.03, 0.0), (0.06, 0.06, 0.06), Material.preset("clay"), name="blob")
    b.add_tool("plane", position=(0.0, 0.0, 0.0), friction=0.5, motion=tools.Velocity((0.0, 4.0, 0.0)), name="lift")
    table = sweep(Scene("lift", "a blob a rising floor lifts", b, frames=9, fps=30.0), ["yield_stress=1e3,1e4"], workers=1)
    assert [r["status"] for r in table.rows] == ["ok", "ok"], [r["reason"] for r in table.rows]
    assert (table.column("centroid_height") > 1.2).all() and (table.column("centroid_height") < 1.3).all()


def _far_scripted_tool_scene():
    """A putty box beside a scripted sphere that never touches it (3 m off), 10 frames: a sample
    at 5x its stable step blows up where the monitor cannot see it (the blow-up tests)."""
    from warp_esph import tools

    def pose(t):
        return (3.0, 0.5, 0.0), (0.0, 0.0, 0.0, 1.0)

    b = SceneBuilder(spacing=0.1)
    b.add_box((0.0, 0.5, 0.0), (0.3, 0.3, 0.3), Material.preset("putty"), name="paste")
    b.add_ground()
    b.add_tool("sphere", radius=0.05, motion=tools.Scripted(pose), name="far")
    return Scene("far", "a blow-up beside a scripted tool", b, frames=10, fps=30.0)


def test_energy_growth_passes_a_body_at_rest_in_zero_gravity():
    """Without gravity or a start speed the energy scale ``KE0 + M |g| L`` is 0 J, so any
    kinetic energy at all, the round-off of a body at rest (float32: 1.8e-10 J over 20 steps
    at half the stable step, before isotropic.svd; here positions 0.1 um off at random, 3.1e-12 J),
    was a blow-up, and ``fit`` failed the trial and the torch
    bridge raised on a healthy run; the floor ``0.5 M (0.1 c_P)^2`` the monitor allows a
    rest-configuration body stands under the scale. A speed well past it is still one."""
    from warp_esph.rollout import Rollout
    from warp_esph.simulate import energy_growth

    b = SceneBuilder(spacing=0.1, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.5, 0.0), (0.3, 0.3, 0.3), Material.preset("putty"), name="paste")
    model = b.finalize(requires_grad=True)
    rollout = Rollout(model, steps=20, dt=0.5 * model.stable_dt(), taped=False)
    # Positions 0.1 um off at random move it, as float32's round-off at rest did before
    # isotropic.svd; not a start strain F0, whose stored energy the monitor counts in the scale.
    rng = np.random.default_rng(0)
    rollout.forward(x0=model.particle_x0 + 1.0e-7 * rng.uniform(-1.0, 1.0, model.particle_x0.shape))
    assert np.abs(rollout.final_state().v.numpy()).max() > 0.0  # it moved: the case checked
    assert rollout.bounds_hit() is None
    x0 = model.particle_x0
    fast = np.tile([model.wave_speeds(model.parameter_values()).max(), 0.0, 0.0], (model.particle_count, 1))
    hit = energy_growth(model, x0, model.particle_v0, x0, fast)
    assert hit is not None and "blew up" in hit[0]


def test_a_blow_up_beside_a_scripted_tool_fails_its_sample():
    """A scripted motion has no speed known beforehand, so ``simulate``'s monitor runs only its
    non-finite check there, and the end-of-run energy check is the one that sees a finite
    blow-up: leaving every moving tool's scene to the monitor let a sample 5x above its stable
    step end as an ok row at 1.7e35 J beside a scripted sphere that never touched it. The
    check counts what the tool can do (its fastest point over the run's poses, and the lift it
    gives, which is no growth), so the stable sample stays ok."""
    table = sweep(_far_scripted_tool_scene(), ["paste.mu=1000,1000000"], workers=1, dt=1.0 / 300.0)
    assert [r["status"] for r in table.rows] == ["ok", "failed"], [r["reason"] for r in table.rows]
    assert "kinetic + gravitational energy grew by" in table.rows[1]["reason"], table.rows[1]["reason"]


def test_the_finite_blow_up_fit_and_torch_fail_fails_its_sample():
    """The run ``blowup_cases`` describes, as a sweep's sample (1 frame at 10 fps, ``DT``: its
    ``STEPS`` steps): failed by ``simulate.energy_growth``, the test ``fit`` and the torch
    bridge apply to the same run (test_fit, test_torch), and ok at the stable stiffness."""
    from blowup_cases import BLOWN_MU, DT, HEALTHY_MU, STEPS, scripted_box_builder

    scene = Scene("far", "a blow-up beside a scripted tool", scripted_box_builder(), frames=1, fps=10.0)
    table = sweep(scene, [f"paste.mu={HEALTHY_MU:g},{BLOWN_MU:g}"], workers=1, dt=DT)
    assert [r["steps"] for r in table.rows] == [STEPS, STEPS]
    assert [r["status"] for r in table.rows] == ["ok", "failed"], [r["reason"] for r in table.rows]
    # simulate stops it at the frame the energy grew past the limit (the one frame here).
    assert table.rows[1]["reason"].startswith("the simulation diverged after step 30 (frame 1, ")
    assert ": kinetic + gravitational energy grew by " in table.rows[1]["reason"]


def _rise(t):
    return (0.0, 0.4 * t, 0.0), (0.0, 0.0, 0.0, 1.0)


def test_a_sample_whose_scripted_tool_lifts_the_body_is_no_blow_up():
    """The lift of ``test_a_sample_whose_tool_lifts_the_body_is_no_blow_up`` by a slow scripted
    floor (0.4 m/s for 3 s): the 1.2 m of height it gives is its work, not growth (counted as
    growth, 11.8 J/kg against 10 x the scale's 0.95 J/kg). One sample: a second of another
    yield stress ran the same check on the same path."""
    from warp_esph import tools

    b = SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.03, 0.0), (0.06, 0.06, 0.06), Material.preset("clay"), name="blob")
    b.add_tool("plane", friction=0.5, motion=tools.Scripted(_rise), name="lift")
    table = sweep(Scene("lift", "a blob a scripted floor lifts", b, frames=90, fps=30.0), ["yield_stress=1e3"], workers=1)
    assert [r["status"] for r in table.rows] == ["ok"], [r["reason"] for r in table.rows]
    assert (table.column("centroid_height") > 1.2).all() and (table.column("centroid_height") < 1.3).all()


# ------------------------------------------------------------------ what a resumed table must share with its sweep
def _floored(kind: str = "plastic", field: bool = False) -> Scene:
    """27 particles of toothpaste on a particle floor (``kind``: plastic, ghost or elastic),
    with a compression field where ``field``."""
    b = SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.04, 0.0), (0.06, 0.06, 0.06), Material.preset("toothpaste"), name="paste")
    b.add_particle_floor("paste", margin=0.0, layers=1, ghost=kind == "ghost", elastic=kind.startswith("elastic"))
    if kind == "elastic_stiffer":
        # The floor's own material made another: the body's is the same, the particles are too.
        k = b._bodies[-1].floor_material
        b._materials[k] = b._materials[k].replace(mu=2.0 * b._materials[k].mu)
    if field:
        b.add_compression_field((0.0, 0.0, 0.0), 50.0)
    return Scene("floored", "a box on a particle floor", b, frames=2, fps=30.0)


@pytest.mark.parametrize("base, changed", [
    (dict(kind="plastic"), dict(kind="ghost")),
    (dict(kind="plastic"), dict(kind="plastic", field=True)),
    (dict(kind="elastic"), dict(kind="elastic_stiffer")),
])
def test_a_table_of_the_same_particles_in_another_scene_is_refused(monkeypatch, base, changed):
    """The identity's model digest held the particles, their materials and the colliders: a
    ghost floor where the table's was plastic (the same particles and materials) or a force
    field added resumed without a word, its rows mixed with the other scene's. Each is
    refused now, naming the model, before any sample runs; the two scenes' tables differ,
    so the mixed table would have been wrong."""
    specs = ["yield_stress=10,1000"]
    first = sweep(_floored(**base), specs, frames=2, workers=1)
    other = sweep(_floored(**changed), specs, frames=2, workers=1)
    assert _rows(first) != _rows(other)  # what a resume would have mixed
    _no_sample_runs(monkeypatch)
    with pytest.raises(ValueError, match=r"^resume = <SweepTable of 2 rows> is not allowed: its table is of another "
                                         r"sweep: model = \"[0-9]+ particles, [0-9a-f]+\" there, \"[0-9]+ particles, "
                                         r"[0-9a-f]+\" here; resume it"):
        sweep(_floored(**changed), specs, frames=2, workers=1, resume=first)


# ------------------------------------------------------------------ a refusal names the material it is about
def _two_materials() -> Scene:
    """A box of toothpaste (material 0) beside a sphere of dough (material 1), far apart."""
    b = SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.04, 0.0), (0.06, 0.06, 0.06), Material.preset("toothpaste"), name="paste")
    b.add_sphere((0.3, 0.04, 0.0), 0.03, Material.preset("dough"), name="blob")
    b.add_ground(friction=0.5)
    return Scene("two", "two bodies of two materials", b, frames=1, fps=30.0)


def test_a_refusal_of_one_material_names_that_material_s_parameter_alone(monkeypatch):
    """Both materials' lam swept, the dough's below -2 mu / 3 in every sample: the refusal's
    field (``Material.lam``) was mapped to the parameters by field name alone, so it named
    ``paste.lam`` too, a value the toothpaste takes in every sample. It names the material
    refused and its parameter only."""
    _no_sample_runs(monkeypatch)
    with pytest.raises(ValueError) as e:
        sweep(_two_materials(), ["paste.lam=1000,2000", "blob.lam=-1e9,-2e9"], frames=1, workers=1)
    said = str(e.value)
    assert said.startswith("params entry blob.lam is not allowed: the material refuses every sample's values (sample 0, "
                           "blob.lam = -1e+09: material 1 (body 'blob'): Material.lam = -1000000000.0 is not allowed"), said
    assert "paste.lam" not in said, said


def test_a_failed_row_of_a_refused_material_names_that_material():
    """A sample whose value one of two materials refuses is a failed row; its reason said
    ``Material.lam = ...`` alone, not which of the two materials (both had a lam swept)."""
    from warp_esph.sweep import _run_sample

    plan = _plan(_two_materials(), ["paste.lam=1000", "blob.lam=1000,-1e9"], "grid", None, 0, 1, None, 30.0, None, 1.0,
                 "float32", "cpu", 1, 100, None)
    rows = [_run_sample(plan.scene, t) for _, t in plan.tasks]
    assert [r["status"] for r in rows] == ["ok", "failed"], rows
    assert rows[1]["reason"].startswith("ValueError: material 1 (body 'blob'): Material.lam = -1000000000.0 is not "
                                        "allowed"), rows[1]["reason"]


def _extra_height(model, state, seed):
    """An ``extra`` column: the highest particle (m)."""
    return {"top": float(state.x.numpy()[:, 1].max())}


def test_a_blown_up_sample_s_row_holds_no_summary_of_its_blown_up_state():
    """A sample the end-of-run energy check finds blown up was a failed row that still held the
    blown-up state's summary (a highest particle at 1.4e17 m, 1.7e35 J) and its ``extra``
    columns: ``table.column('max_height')``, documented NaN where a sample failed, handed them
    on as numbers beside the ok rows', and the CSV wrote them. The row keeps its reason and
    guard counts; its summary and extra cells are empty, as a diverged sample's are."""
    from warp_esph.sweep import SUMMARY_COLUMNS

    table = sweep(_far_scripted_tool_scene(), ["paste.mu=1000,1000000"], workers=1, dt=1.0 / 300.0, extra=_extra_height)
    # Stopped by simulate at the frame whose energy grew past energy_growth's limit.
    assert [r["status"] for r in table.rows] == ["ok", "failed"] and "energy grew by" in table.rows[1]["reason"]
    for name in (*SUMMARY_COLUMNS, "top"):
        col = table.column(name)
        assert np.isfinite(col[0]) and np.isnan(col[1]), (name, col)
    assert table.rows[1]["guard_inverted"] is not None  # what the guards did is kept


# ------------------------------------------------------------------ a table another version wrote
def test_a_table_another_version_wrote_is_refused_naming_both_versions(monkeypatch, tmp_path):
    """A table of the same scene written by an earlier version (its record without a format,
    its model digest made otherwise) was refused as another scene's, ``model = ... there,
    ... here``, and one of another version with the same record resumed, mixing two
    versions' results. Each is refused now in one line naming both versions and what to do."""
    import warp_esph
    from warp_esph.sweep import RECORD_FORMAT, write_outputs

    specs = ["yield_stress=10,1000"]
    first = sweep(_box(), specs, frames=1, workers=1)
    assert first.identity["format"] == RECORD_FORMAT and first.identity["version"] == warp_esph.__version__
    _no_sample_runs(monkeypatch)
    # Format 1: no format key, another digest, the version in sweep.json beside the record alone.
    old = {k: v for k, v in first.identity.items() if k not in ("format", "fingerprint_version", "version")}
    old["model"] = "125 particles, 0123456789abcdef"
    write_outputs(SweepTable(first.columns, first.rows, first.params, old), tmp_path / "old", {"version": "0.0.9"},
                  plot_figure=False)
    with pytest.raises(ValueError, match=re.escape(
            f"this table was written by warp_esph 0.0.9 (record format 1, model fingerprint 1); this is warp_esph "
            f"{warp_esph.__version__} (record format {RECORD_FORMAT}, model fingerprint ")) as refused:
        sweep(_box(), specs, frames=1, workers=1, resume=tmp_path / "old")
    assert "model = " not in str(refused.value) and str(refused.value).endswith(
        "rerun without resume (or resume it with the version that wrote it)")
    # The same record format and model, another version: refused too, the version named.
    other = SweepTable(first.columns, first.rows, first.params, {**first.identity, "version": "0.0.9"})
    with pytest.raises(ValueError, match=re.escape(
            f"this table was written by warp_esph 0.0.9 (record format {RECORD_FORMAT}); this is warp_esph "
            f"{warp_esph.__version__} (record format {RECORD_FORMAT}): another version may compute other results")):
        sweep(_box(), specs, frames=1, workers=1, resume=other)
    # The command's refusal says its option.
    from warp_esph.sweep import _check_record_format

    with pytest.raises(ValueError, match=r"^--resume of --output = 'sw' is not allowed: .*, or rerun without --resume$"):
        _check_record_format(other.identity, first.identity, "--resume of --output", "'sw'")


# ------------------------------------------------------------------ a column's type survives its tables
def _extra_codes(model, state, seed):
    """An ``extra`` with a text column whose every value looks like a number ("042")."""
    y = state.x.numpy()[:, 1]
    return {"code": f"{seed % 100:03d}", "above_5cm": int(np.sum(y > 0.05))}


def test_a_resumed_sweep_keeps_an_extra_s_numeric_looking_text_as_text(tmp_path):
    """An ``extra``'s text "042" was read back from the CSV as the number 42, so a resumed
    table held 42 where one run straight through holds "042", and wrote it so. The columns'
    types are kept beside the CSV (``sweep.json``'s ``column_types``) and read back by."""
    pytest.importorskip("pyarrow")
    from warp_esph.sweep import write_outputs

    specs = ["yield_stress=10,1000"]
    straight = sweep(_box(), specs, frames=1, workers=1, extra=_extra_codes)
    assert all(isinstance(r["code"], str) and r["code"].startswith("0") for r in straight.rows), straight.rows
    with pytest.raises(KeyboardInterrupt) as stopped:
        sweep(_box(), specs, frames=1, workers=1, extra=_extra_codes, on_result=_stopped_after(1))
    write_outputs(stopped.value.table, tmp_path / "part", plot_figure=False)
    for source in (tmp_path / "part", tmp_path / "part" / "sweep.parquet"):
        whole = sweep(_box(), specs, frames=1, workers=1, extra=_extra_codes, resume=source)
        assert _rows(whole) == _rows(straight), source
        assert whole.types() == straight.types() and whole.types()["code"] == "text"


def test_a_column_of_mixed_values_reads_back_as_the_table_of_all_rows(tmp_path):
    """A column's type is decided by all its rows (text beside numbers is text, an int beside
    floats a float), and the table of a resumed sweep, whose first rows were read back from a
    partial table written when that column held ints alone, equals the table of all rows as
    run: the same rows, CSV text and Parquet values."""
    pq = pytest.importorskip("pyarrow.parquet")
    from warp_esph.sweep import _resume_table, _table, write_outputs

    rows = [{"sample": 0, "status": "ok", "seed": 1, "n": 5, "x": 0, "code": "007"},
            {"sample": 1, "status": "ok", "seed": 2, "n": "n/a", "x": 0.5, "code": "08"}]
    whole = _table(rows, [])
    assert [r["n"] for r in whole.rows] == ["5", "n/a"] and [r["x"] for r in whole.rows] == [0.0, 0.5]
    write_outputs(_table(rows[:1], []), tmp_path / "part", plot_figure=False)
    for name in ("sweep.csv", "sweep.parquet"):
        kept, _ = _resume_table(str(tmp_path / "part" / name), "resume")
        assert kept.rows[0]["code"] == "007", name
        resumed = _table([{k: v for k, v in kept.rows[0].items() if v is not None}, rows[1]], [])
        assert resumed.rows == whole.rows and resumed.types() == whole.types(), name
        resumed.to_csv(tmp_path / "a.csv")
        whole.to_csv(tmp_path / "b.csv")
        assert (tmp_path / "a.csv").read_bytes() == (tmp_path / "b.csv").read_bytes()
        assert pq.read_table(resumed.to_parquet(tmp_path / "a.parquet")).equals(
            pq.read_table(whole.to_parquet(tmp_path / "b.parquet")))


# ------------------------------------------------------------------ a body the scene shows blowing up
def _with_exempt_blob() -> Scene:
    """A box of putty under a compression field beside a separate box, ``blob``, that the scene
    names as blowing up (``Scene.diverges``, as ``fig8_comparison`` names its plastic
    rest-configuration cube); the field keeps the end-of-run energy check off, as there."""
    b = SceneBuilder(spacing=0.1, bodies_interact=False)
    b.add_box((0.0, 0.5, 0.0), (0.3, 0.3, 0.3), Material.preset("putty"), name="paste")
    b.add_box((2.0, 0.5, 0.0), (0.3, 0.3, 0.3), Material.preset("putty"), name="blob")
    b.add_ground()
    b.add_compression_field((0.0, 0.5, 0.0), 1.0, body="paste")
    return Scene("exempt", "a body the scene shows blowing up", b, frames=10, fps=30.0, diverges=("blob",))


def test_a_sample_whose_exempt_body_blew_up_is_no_ok_row():
    """The body a scene shows blowing up is left out of the run's divergence monitor, and a
    force field keeps the end-of-run energy check off, so a sample whose exempt body blew up
    (finite: 1e6 Pa at 20 x its stable step) was an ok row whose summary was of the blown-up
    state. It fails now, its reason naming the body, its summary empty; a sample whose exempt
    body stayed sound is ok."""
    from warp_esph.sweep import SUMMARY_COLUMNS

    table = sweep(_with_exempt_blob(), ["blob.mu=1000,1000000"], workers=1, dt=1.0 / 300.0)
    assert [r["status"] for r in table.rows] == ["ok", "failed"], [r.get("reason") for r in table.rows]
    assert table.rows[1]["reason"].startswith("body 'blob', which the scene shows blowing up"), table.rows[1]["reason"]
    for name in SUMMARY_COLUMNS:
        col = table.column(name)
        assert np.isfinite(col[0]) and np.isnan(col[1]), (name, col)


def _extra_flag(model, state, seed):
    """An ``extra`` with a bool column, numpy's as one is written (``y.max() > h``)."""
    return {"tall": state.x.numpy()[:, 1].max() > 0.09}


def test_an_extra_s_bool_is_a_count_in_every_table(tmp_path):
    """A bool from ``extra`` was written 'True' to the CSV and read back as that text, and the
    Parquet column held 1.0: a resumed table differed from one run straight through. It is the
    count 1 or 0, an int column in both tables."""
    pq = pytest.importorskip("pyarrow.parquet")
    table = sweep(_box(), ["yield_stress=10,10000"], frames=4, workers=1, extra=_extra_flag)
    assert [type(r["tall"]) for r in table.rows] == [int, int] and {r["tall"] for r in table.rows} <= {0, 1}
    assert SweepTable.read_csv(table.to_csv(tmp_path / "t.csv")).rows == table.rows
    par = pq.read_table(table.to_parquet(tmp_path / "t.parquet"))
    assert str(par.schema.field("tall").type) == "int64" and par.to_pylist() == table.rows


def test_a_table_cut_off_after_its_csv_still_resumes(serial, tmp_path, monkeypatch):
    """``write_outputs`` wrote sweep.csv, then the Parquet table (the first write imports pyarrow,
    a second or so) and then sweep.json: a sweep killed in between (measured: SIGKILL 6 s into a
    command's run) left a sweep.csv without its record, which ``--resume`` refuses, so every
    sample ran again. The record is written first: a table cut off after its CSV resumes."""
    from warp_esph import sweep as sweep_module

    part = SweepTable(serial.columns, serial.rows[:1], serial.params, serial.identity)

    def killed(self, path):
        raise KeyboardInterrupt  # stands for the kill that lands after the CSV

    monkeypatch.setattr(sweep_module.SweepTable, "to_parquet", killed)
    with pytest.raises(KeyboardInterrupt):
        sweep_module.write_outputs(part, tmp_path / "sw", plot_figure=False)
    monkeypatch.undo()
    assert not (tmp_path / "sw" / "sweep.parquet").exists()
    ran = []
    whole = sweep(_box(), [YIELD], frames=FRAMES, workers=1, resume=tmp_path / "sw",
                  on_result=lambda r: ran.append(r["sample"]))
    assert ran == [1, 2] and _rows(whole) == _rows(serial)


def test_a_new_sweep_cut_off_in_its_first_write_leaves_no_other_sweep_s_table_beside_its_record(serial, tmp_path,
                                                                                              monkeypatch):
    """With sweep.json written before the tables, a new sweep (no resume) over a folder holding
    another sweep's table, cut off after its record, would leave the other sweep's rows beside
    this sweep's record, and a resume keep them (the same values and seeds at other frames).
    The other sweep's tables are removed before the record is written."""
    from warp_esph import sweep as sweep_module

    other = SweepTable(serial.columns, serial.rows, serial.params, {**serial.identity, "frames": FRAMES + 1})
    sweep_module.write_outputs(other, tmp_path / "sw", plot_figure=False)

    def killed(self, path):
        raise KeyboardInterrupt  # stands for the kill that lands after the record

    monkeypatch.setattr(sweep_module.SweepTable, "to_csv", killed)
    with pytest.raises(KeyboardInterrupt):
        sweep_module.write_outputs(SweepTable(serial.columns, [], serial.params, serial.identity), tmp_path / "sw",
                                   plot_figure=False)
    monkeypatch.undo()
    assert not (tmp_path / "sw" / "sweep.csv").exists() and not (tmp_path / "sw" / "sweep.parquet").exists()
    _no_sample_runs(monkeypatch)
    with pytest.raises(ValueError, match="the folder holds no sweep.csv or sweep.parquet"):
        sweep(_box(), [YIELD], frames=FRAMES, workers=1, resume=tmp_path / "sw")


def test_a_csv_read_without_its_types_reads_each_column_as_one_type(tmp_path):
    """``SweepTable.read_csv`` without types read each cell alone: an extra's codes "007" and
    "abc" came back as the int 7 beside the text "abc", and "042" beside "015" as 42 and 15,
    where the table held text. A column is read by all its cells (a cell no number as
    ``to_csv`` writes one makes it text), or by the record ``write_outputs`` keeps beside a
    ``sweep.csv``, which alone tells a text "101" from the int; unknown types are refused."""
    from warp_esph.sweep import _table, write_outputs

    rows = [{"sample": 0, "status": "ok", "seed": 1, "code": "007", "lot": "042", "id": "101", "x": 0.5},
            {"sample": 1, "status": "ok", "seed": 2, "code": "abc", "lot": "015", "id": "102", "x": 2.0}]
    table = _table(rows, [])
    assert table.types()["code"] == table.types()["id"] == "text"
    back = SweepTable.read_csv(table.to_csv(tmp_path / "t.csv"))
    assert [r["code"] for r in back.rows] == ["007", "abc"] and [r["lot"] for r in back.rows] == ["042", "015"]
    assert [r["x"] for r in back.rows] == [0.5, 2.0] and [r["seed"] for r in back.rows] == [1, 2]
    assert [r["id"] for r in back.rows] == [101, 102]  # digits alone: only the record says they are text
    write_outputs(table, tmp_path / "out", plot_figure=False)
    assert SweepTable.read_csv(tmp_path / "out" / "sweep.csv").rows == table.rows
    with pytest.raises(ValueError, match=r"types\['id'\] = 'str' is not allowed: must be one of 'int', 'float', 'text'"):
        SweepTable.read_csv(tmp_path / "t.csv", {"id": "str"})


def _press_then_slide(t):
    """A plate over a 0.2 m block presses it 0.094 m (47 %) down in 0.3 s, then slides off
    sideways at 0.5 m/s."""
    return (0.5 * max(t - 0.3, 0.0), 0.225 - 0.094 * min(t / 0.3, 1.0), 0.0), (0.0, 0.0, 0.0, 1.0)


@pytest.mark.filterwarnings("ignore:tools .'plate'. follow tools.Scripted motions:UserWarning")
def test_a_sample_a_scripted_tool_pressed_and_released_is_no_blow_up():
    """A 4 x 4 x 4 rubber block without gravity, pressed 47 % by a scripted plate that then
    slides off, springs back: the sample's end (frame 20) holds 36 J of kinetic energy the
    plate's push stored as elastic energy. The end-of-run ``energy_growth`` counted a scripted
    tool's work as height and its speed alone and failed the sample (36.06 J against 34.3 J);
    the work simulate counted (the plate's reaction along its motion) now counts there too."""
    from warp_esph import tools

    b = SceneBuilder(spacing=0.05, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.1, 0.0), (0.2, 0.2, 0.2), Material.preset("rubber"), name="block")
    b.add_ground(friction=0.0)
    b.add_tool("box", half_extents=(0.2, 0.025, 0.2), motion=tools.Scripted(_press_then_slide), name="plate")
    table = sweep(Scene("spring", "a block a plate presses and releases", b, frames=20, fps=30.0), ["viscosity=2"],
                  workers=1)
    assert [r["status"] for r in table.rows] == ["ok"], [r["reason"] for r in table.rows]
    # It sprang back: more kinetic energy than the floor a body at rest may hold.
    from warp_esph.simulate import _energy_floor

    model = b.finalize()
    c_p = float(model.wave_speeds(model.parameter_values()).max())
    assert table.rows[0]["kinetic_energy"] > _energy_floor(float(model.particle_mass.numpy().sum()), c_p)


def test_a_swept_parameter_selects_a_scene_files_material_by_its_name(tmp_path, two_materials_scene):
    """``--param soft.yield_stress``: the material of table ``[materials.soft]`` (``clay.NAME``
    the preset a body names), as a body name or an index selects one; it was refused, 'give a
    material index or a body name'."""
    from warp_esph.scenes import load_scene_file
    from warp_esph.cli import option_flag
    from warp_esph.sweep import _assignments, parse_param

    (tmp_path / "two.toml").write_text(two_materials_scene)
    scene = load_scene_file(tmp_path / "two.toml")
    chosen = _assignments(scene, [parse_param("soft.yield_stress=50:100:log:2"), parse_param("clay.flow_rate=5")])
    assert [(field, idx) for _, field, idx in chosen] == [("yield_stress", [0]), ("flow_rate", [1])]
    with pytest.raises(ValueError, match=r"^--param hard.mu: material 'hard' is not allowed: give a "
                                         r"material index, a body name \(a, b\) or a material name of the scene file "
                                         r"\(soft, clay\)$"):
        _assignments(scene, [parse_param("hard.mu=1e4")], option_flag)


def test_a_blow_up_quotes_the_stable_step_of_the_solver_that_ran():
    """``energy_growth``'s message names the stable step of the solver that ran the steps
    (``Solver.stable_dt``: its fit and hourglass strength), which ``Rollout`` and ``sweep``
    pass: an elastic model whose default is the linear fit, run with
    ``Solver(fit="curvature_corrected")`` on the incremental composition, has half the wave
    limit as its step (``Model.CORRECTED_INCREMENTAL_STEP``); the model's own ``stable_dt()`` quoted
    twice the step the solver holds to."""
    from warp_esph import Solver
    from warp_esph.simulate import energy_growth

    b = SceneBuilder(spacing=0.1, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.5, 0.0), (0.3, 0.3, 0.3), Material.from_young(1.0e5, 0.3, density=1000.0), name="block")
    b.add_ground(0.0, images=True)
    model = b.finalize()
    model.fit = "linear"
    solver = Solver(model, fit="curvature_corrected", hourglass=0.05)
    assert model.corrected_incremental("curvature_corrected") and not model.corrected_incremental()
    x0 = model.particle_x0
    fast = np.tile([model.wave_speeds(model.parameter_values()).max(), 0.0, 0.0], (model.particle_count, 1))
    hit = energy_growth(model, x0, model.particle_v0, x0, fast, solver=solver)
    assert hit is not None and f"stable limit {solver.stable_dt():.3g} s" in hit[0], hit
    assert solver.stable_dt() < 0.6 * model.stable_dt(hourglass=0.05)
    plain = energy_growth(model, x0, model.particle_v0, x0, fast)
    assert f"stable limit {model.stable_dt():.3g} s" in plain[0]


def _thirds_box(ground: float) -> Scene:
    """``_box`` on a ground at ``ground``: at -1/3 (not a float32) the model's float32 plane is
    -0.33333334, which fingerprint version 3 records and version 2 did not (it recorded -1/3)."""
    b = SceneBuilder(spacing=0.02)
    b.add_box((0.0, ground + 0.06, 0.0), (0.1, 0.1, 0.1), Material.preset("toothpaste"), name="paste")
    b.add_ground(ground, friction=0.5)
    return Scene("paste_box", "a small box of toothpaste", b, frames=FRAMES, fps=30.0)


def test_a_table_of_fingerprint_version_2_resumes_where_the_scene_is_the_one_it_recorded(monkeypatch, tmp_path):
    """A half-done sweep's table written before the fingerprint's version 3 (its record's
    ``fingerprint_version`` 2, its model digest of version 2's scene record) was refused as
    another format's. It is compared with this scene's record of version 2, as a checkpoint of
    version 2 is: the same scene resumes it, running no sample again; the scene edited (its
    ground 1 cm lower) is refused, naming the model; a record of version 2 holding version 3's
    digest (which differs for this scene) is refused too."""
    from warp_esph.sweep import _model_digest, write_outputs

    specs = ["yield_stress=10,1000"]
    first = sweep(_thirds_box(-1.0 / 3.0), specs, frames=1, workers=1)
    assert first.identity["fingerprint_version"] == 4
    model = _thirds_box(-1.0 / 3.0).builder.finalize()
    v2, v3 = _model_digest(model, 2), _model_digest(model)
    assert v2 != v3 and first.identity["model"].endswith(v3)  # version 2 and 3 record this scene apart
    old = {**first.identity, "fingerprint_version": 2, "model": f"{model.particle_count} particles, {v2}"}
    write_outputs(SweepTable(first.columns, first.rows, first.params, old), tmp_path / "old", plot_figure=False)
    _no_sample_runs(monkeypatch)
    resumed = sweep(_thirds_box(-1.0 / 3.0), specs, frames=1, workers=1, resume=tmp_path / "old")
    assert _rows(resumed) == _rows(first) and resumed.identity == first.identity  # rewritten as this version's
    with pytest.raises(ValueError, match=r"its table is of another sweep: model = .* there, .* here"):
        sweep(_thirds_box(-1.0 / 3.0 - 0.01), specs, frames=1, workers=1, resume=tmp_path / "old")
    mislabelled = SweepTable(first.columns, first.rows, first.params, {**first.identity, "fingerprint_version": 2})
    with pytest.raises(ValueError, match=r"its table is of another sweep: model = "):
        sweep(_thirds_box(-1.0 / 3.0), specs, frames=1, workers=1, resume=mislabelled)


def _paste_on(tresca: bool, hardening: float = 0.0) -> Scene:
    """``_box``'s toothpaste (with ``hardening``) on the Tresca ground (K = 1), or on the
    frictional imaged ground."""
    b = SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.06, 0.0), (0.1, 0.1, 0.1), Material.preset("toothpaste").replace(hardening=hardening), name="paste")
    b.add_ground(friction=0.0 if tresca else 0.5, images=True, shear_cap=1.0 if tresca else None)
    return Scene("paste_box", "a small box of toothpaste", b, frames=FRAMES, fps=30.0)


def test_a_table_written_before_the_hardened_tresca_hold_is_refused_only_where_the_hold_changed(monkeypatch, tmp_path):
    """The Tresca ground's hold reads the hardened yield stress since 2026-12-07 (fingerprint
    version 4; the package's version unchanged): a half-done table of version 3 of a sweep on
    the Tresca ground with a nonzero hardening (the scene's, or a swept one) resumed, and its
    rows of the old hold were mixed with the new one's. It is refused in one line naming why;
    the same sweeps' tables of version 4 resume, and so do old ones of a sweep whose every
    sample runs hardening 0 on the Tresca ground (the two holds the same: the scene's
    hardening swept to 0 too) and of the imaged frictional ground with hardening. A version
    written 3.0 is version 3 (it was refused as another record format's). Seen failing with
    ``older_hold``'s check removed from ``_resumed_rows``, and (3.0) with the version read as
    the file has it, as before."""
    from warp_esph.sweep import write_outputs

    runs = [(True, 0.0, ["hardening=0,1000"], True), (True, 1000.0, ["yield_stress=10,1000"], True),
            (True, 0.0, ["yield_stress=10,1000"], False), (True, 1000.0, ["hardening=0"], False),
            (False, 1000.0, ["hardening=0,1000"], False)]
    firsts = [sweep(_paste_on(tresca, h), specs, frames=1, workers=1) for tresca, h, specs, _ in runs]
    _no_sample_runs(monkeypatch)
    for k, ((tresca, h, specs, refused), first) in enumerate(zip(runs, firsts)):
        assert first.identity["fingerprint_version"] == 4
        resumed = sweep(_paste_on(tresca, h), specs, frames=1, workers=1, resume=first)
        assert _rows(resumed) == _rows(first)
        old = SweepTable(first.columns, first.rows, first.params, {**first.identity, "fingerprint_version": 3})
        write_outputs(old, tmp_path / f"old{k}", plot_figure=False)
        # Written 3.0 (a hand edit of sweep.json): read as 3, the same as the file above.
        old = SweepTable(first.columns, first.rows, first.params, {**first.identity, "fingerprint_version": 3.0})
        write_outputs(old, tmp_path / f"float{k}", plot_figure=False)
        for label in ("old", "float"):
            if not refused:
                resumed = sweep(_paste_on(tresca, h), specs, frames=1, workers=1, resume=tmp_path / f"{label}{k}")
                assert _rows(resumed) == _rows(first) and resumed.identity == first.identity
                continue
            with pytest.raises(ValueError, match=r"^resume = .* is not allowed: it was written with fingerprint version 3, "
                                                 r"before the Tresca ground's hold read the hardened yield stress .*, and this "
                                                 r"scene has a Tresca ground \(shear_cap = 1\) under a hardening of 1000 Pa, so "
                                                 r"resumed it would mix the two holds; rerun without resume$"):
                sweep(_paste_on(tresca, h), specs, frames=1, workers=1, resume=tmp_path / f"{label}{k}")
