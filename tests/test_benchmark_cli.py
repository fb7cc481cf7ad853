"""The developer command lines under benchmarks/ refuse bad input before they run anything:
exit status 2 and one line on standard error that names the option (``benchmarks/_cli.py``).

Each module's ``main`` is called in-process through ``_cli.run`` (what its ``__main__`` runs),
with the functions that would simulate replaced by ones that fail the test if called; a few
commands also run as subprocesses, to check their ``__main__`` wiring. No simulation runs.
"""

import importlib
import json
import pathlib
import subprocess
import sys

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks import _cli  # noqa: E402

#: Per module, the functions that start the work: none may be called on bad input.
ENTRY_POINTS = {
    "fit_bench": ("measure", "measure_loss_only", "measure_rejected", "block_model"),
    "floors": ("_forward", "_taped"),
    "gradient_bench": ("measure", "block_model", "star_model"),
    "host_step": ("measure",),
    "kept_fits": ("measure",),
    "launches": ("measure", "measure_taped"),
    "mpm_slump": ("slump", "column", "squeeze", "table"),
    "splishsplash": ("worker",),
    "step": ("compile_kernels", "bench_warp_esph", "variant_rates", "bench_splishsplash"),
    "sweep_bench": ("run_sweep",),
    "table1": ("measure",),
    "worlds_bench": ("forward_case", "gradient_case"),
    "lab_bending_force": ("load_scene", "simulate"),
    "static_stiffness": ("beam", "cantilever", "_modes_table"),
    "validation": ("run_one",),
    "validation_report": ("write",),
}


@pytest.fixture
def refused(capsys, monkeypatch):
    """``refused(name, argv, *words)``: ``python -m benchmarks.<name> argv`` exits with status 2
    and one line on stderr, ``python -m benchmarks.<name>: error: ...``, holding every word; it
    prints nothing on stdout and calls none of the module's ``ENTRY_POINTS``. Returns the line."""

    def check(name, argv, *words):
        module = importlib.import_module(f"benchmarks.{name}")
        for attr in ENTRY_POINTS[name]:
            def ran(*args, _attr=attr, **kwargs):
                raise AssertionError(f"benchmarks.{name}.{_attr} ran on bad input {argv}")
            monkeypatch.setattr(module, attr, ran)
        prog = f"python -m benchmarks.{name}"
        capsys.readouterr()
        with pytest.raises(SystemExit) as exit_:
            _cli.run(module.main, prog, argv)
        out, err = capsys.readouterr()
        assert exit_.value.code == 2, (argv, err)
        lines = err.splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"{prog}: error: "), err
        assert "Traceback" not in err
        for word in words:
            assert word in lines[0], (word, lines[0])
        assert out == ""
        return lines[0]

    return check


@pytest.fixture
def files(tmp_path):
    """Bad inputs: a folder, a regular file, random bytes, an empty file, JSON of the wrong shape."""
    (tmp_path / "folder").mkdir()
    (tmp_path / "regular").write_text("x")
    (tmp_path / "garbage").write_bytes(b"\x8f\xff\x00\x12garbage")
    (tmp_path / "empty").write_bytes(b"")
    (tmp_path / "object.json").write_text(json.dumps({"a": 1}))
    (tmp_path / "nosuch.json").write_text(json.dumps([{"case": "nosuch", "resolution": "abc"}]))
    (tmp_path / "no_results.json").write_text(json.dumps({"results": []}))
    (tmp_path / "bad_resolution.json").write_text(json.dumps([{"case": "slump", "S": 0.2, "resolution": "abc"}]))
    return {p.name: str(p) for p in tmp_path.iterdir()} | {"missing": str(tmp_path / "missing.json"),
                                                            "nodir": str(tmp_path / "nodir" / "x.json"),
                                                            "under_file": str(tmp_path / "regular" / "val")}


# ------------------------------------------------------------------------------ the helpers
def test_the_checks_name_the_option_its_value_and_what_is_allowed():
    with pytest.raises(_cli.Refused, match=r"^--steps = 0 is not allowed: must be an integer >= 1$"):
        _cli.positive_int("0", "--steps")
    with pytest.raises(ValueError, match=r"^--steps = 'abc' is not allowed: must be an integer >= 1$"):
        _cli.positive_int("abc", "--steps")
    with pytest.raises(ValueError, match=r"^--dt = nan is not allowed: must be a finite number > 0$"):
        _cli.positive_float("nan", "--dt")
    with pytest.raises(ValueError, match=r"^--x = 2 is not allowed: must be a finite number >= 0 and < 1$"):
        _cli.number(0.0, 1.0, hi_open=True)("2", "--x")
    with pytest.raises(ValueError, match=r"--sizes = '5,abc' is not allowed: .*\('abc' is not one\)"):
        _cli.positive_int_list("5,abc", "--sizes")
    assert _cli.positive_int_list("5, 7", "--sizes") == [5, 7]
    assert _cli.nonnegative_int("0", "--warmup") == 0 and _cli.finite_float("-1.5", "--f") == -1.5
    with pytest.raises(ValueError, match=r"--device = 'gpu9' is not allowed: .*Warp's devices here: .*cpu"):
        _cli.check_device("gpu9")
    assert _cli.check_device("cpu") == "cpu"


def test_the_parser_names_a_checked_option_once(capsys):
    p = _cli.Parser(prog="python -m benchmarks.x")
    p.add_argument("--steps", type=_cli.positive_int, default=3)
    p.add_argument("count", nargs="?", type=_cli.positive_int, metavar="COUNT")
    assert p.parse_args([]).steps == 3
    for argv, line in ((["--steps", "0"], "--steps = 0 is not allowed: must be an integer >= 1"),
                       (["0"], "COUNT = 0 is not allowed: must be an integer >= 1"),
                       (["--bogus"], "unrecognized arguments: --bogus")):
        with pytest.raises(SystemExit) as e:
            p.parse_args(argv)
        assert e.value.code == 2
        assert capsys.readouterr().err == f"python -m benchmarks.x: error: {line}\n"


def test_run_turns_value_and_os_errors_into_one_line(capsys):
    def main(argv):
        raise OSError(2, "No such file or directory", "x.json")

    with pytest.raises(SystemExit) as e:
        _cli.run(main, "python -m benchmarks.x", [])
    assert e.value.code == 2
    assert capsys.readouterr().err == "python -m benchmarks.x: error: [Errno 2] No such file or directory: 'x.json'\n"
    assert _cli.run(lambda argv: 0, "p", []) == 0


# ------------------------------------------------------------------------------ each command
@pytest.mark.parametrize("argv,words", [
    (["--particles", "abc"], ["--particles = 'abc'"]),
    (["--checkpoint", "abc"], ["--checkpoint = 'abc'", "'sqrt'"]),
    (["--repeats", "-1"], ["--repeats = -1", ">= 1"]),
    (["--quick", "--particles", "abc"], ["--particles = 'abc'"]),
    (["--quick", "--particles", "500"], ["--particles", "--quick"]),
    (["--loss-only", "--checkpoint", "5"], ["--checkpoint = 5 is not allowed with --loss-only"]),
    (["--loss-only", "--repeats", "0"], ["--repeats = 0", ">= 1"]),
    (["--rejected", "--loss-only"], ["--loss-only is not allowed with --rejected"]),
    (["--rejected", "--checkpoint", "5"], ["--checkpoint = 5 is not allowed with --rejected"]),
])
def test_fit_bench(refused, argv, words):
    refused("fit_bench", argv, *words)


def test_fit_bench_checks_the_output_folder_before_it_runs(refused, files):
    refused("fit_bench", ["--json", files["nodir"]], "--json", "does not exist")


@pytest.mark.parametrize("argv,option", [(["--resolution", "0"], "--resolution = 0"), (["--steps", "-5"], "--steps = -5"),
                                         (["--repeat", "0"], "--repeat = 0"), (["--warmup", "0"], "--warmup = 0")])
def test_floors(refused, argv, option):
    refused("floors", argv, option)


@pytest.mark.parametrize("argv,option", [(["--sizes", "abc"], "--sizes = 'abc'"),
                                         (["--dtypes", "float16"], "--dtypes = 'float16'"),
                                         (["--steps", "0"], "--steps = 0"), (["--repeats", "0"], "--repeats = 0")])
def test_gradient_bench(refused, argv, option):
    refused("gradient_bench", argv, option)


def test_gradient_bench_measures_a_round_off_gradient_against_the_loss(monkeypatch, tmp_path, capsys):
    """``--sizes 512 --steps 2`` printed a float32 error of 2.8e+21 for mu: after 2 steps from
    rest its float64 gradient is round-off (3.5e-45, float32's -9.6e-23), and the error was
    divided by it. Each material error is now of the sensitivity p dL/dp, floored at 1e-6 of
    the loss; a real 1 % error of a gradient that moves the loss is still 1e-2. The measured
    gradients are these of that run (nothing is simulated)."""
    import types  # noqa: PLC0415

    module = importlib.import_module("benchmarks.gradient_bench")
    grads = {"float32": ({"mu": [-9.607182766140259e-24], "yield_stress": [2.02e-9], "flow_rate": [0.0]}, 3.0000153e-06),
             "float64": ({"mu": [3.455002716363131e-45], "yield_stress": [2.0e-9], "flow_rate": [0.0]}, 3.0e-06)}

    def block_model(size, dtype):
        return types.SimpleNamespace(dtype=dtype.__name__, materials=[types.SimpleNamespace(mu=1e4, yield_stress=100.0,
                                                                                            flow_rate=10.0)])

    def measure(model, steps, repeats, profile, hand=True, fused_tape=True):
        g, loss = grads[model.dtype]
        ratios = dict.fromkeys(("fused_ms_per_step", "taped_over_fused", "backward_over_fused", "gradient_over_fused",
                                "cpu_taped_over_fused", "cpu_backward_over_fused", "cpu_gradient_over_fused",
                                "taped_bytes_per_particle_step"), 1.0)
        return {"particles": 512, "adjoints": "hand-written", "dtype": model.dtype, "steps": steps, **ratios, "loss": loss,
                "grads": g, "grad_v0": np.ones((512, 3))}

    monkeypatch.setattr(module, "block_model", block_model)
    monkeypatch.setattr(module, "measure", measure)
    out = tmp_path / "g.json"
    assert module.main(["--sizes", "512", "--steps", "2", "--repeats", "1", "--json", str(out)]) == 0
    err = json.loads(out.read_text())[0]["float32_relative_error"]
    assert err["mu"] < 1e-6 and err["yield_stress"] == pytest.approx(1e-2) and err["flow_rate"] == 0.0, err
    assert "mu 3.2e-08, yield_stress 1.0e-02, flow_rate 0.0e+00, v0 0.0e+00" in capsys.readouterr().out


@pytest.mark.parametrize("argv,option", [(["--scenes", "ground,bogus"], "'bogus' is not one"), (["--side", "0"], "--side = 0"),
                                         (["--taped-steps", "0"], "--taped-steps = 0"), (["--blocks", "-1"], "--blocks = -1")])
def test_host_step(refused, argv, option):
    refused("host_step", argv, option)


@pytest.mark.parametrize("argv,option", [(["--rounds", "0"], "--rounds = 0"), (["--block", "-3"], "--block = -3")])
def test_kept_fits(refused, argv, option):
    refused("kept_fits", argv, option)


@pytest.mark.parametrize("argv,option", [(["--sizes", "abc"], "--sizes = 'abc'"), (["--steps", "0"], "--steps = 0"),
                                         (["--blocks", "0"], "--blocks = 0")])
def test_launches(refused, argv, option):
    refused("launches", argv, option)


@pytest.mark.parametrize("argv,option", [(["--S", "-1"], "--S = -1"), (["--S", "0.2", "--res", "0"], "--res = 0"),
                                         (["--S", "0.2", "--duration", "nan"], "--duration = nan"),
                                         (["--S", "0.2", "--aspect", "100", "--res", "4"], "--aspect = 100"),
                                         # options that ran nothing and exited 0
                                         ([], "nothing to run"), (["--res", "4", "--duration", "1"], "--res is not allowed without --S"),
                                         (["--S"], "--S is not allowed without values"),
                                         (["--near-yield-column", "--res", "0"], "--res = 0"),
                                         (["--near-yield-column", "--duration", "1"], "--duration is not allowed without --S"),
                                         (["--S", "0.2", "--duration", "9", "--max-duration", "8"], "--max-duration = 8"),
                                         (["--S", "0.2", "--floor-shear-cap", "-1"], "--floor-shear-cap = -1"),
                                         (["--S", "0.2", "--floor-shear-cap", "nan"], "--floor-shear-cap = nan"),
                                         (["--S", "0.2", "--floor-shear-cap", "1", "--floor-friction", "0.3"],
                                          "--floor-friction = 0.3 is not allowed with --floor-shear-cap"),
                                         (["--S", "0.2", "--floor-shear-cap", "1", "--floor-friction", "-1"],
                                          "--floor-friction = -1 is not allowed with --floor-shear-cap"),
                                         (["--floor-shear-cap", "1"], "--floor-shear-cap is not allowed without --S")])
def test_mpm_slump(refused, argv, option):
    refused("mpm_slump", argv, option)


@pytest.mark.parametrize("name,words", [("missing", ["no such file"]), ("garbage", ["not UTF-8"]),
                                        ("object.json", ["'slumps'"]), ("nosuch.json", ["no slump row"])])
def test_mpm_slump_table(refused, files, name, words):
    refused("mpm_slump", ["--table", files[name]], f"--table = {files[name]!r}", *words)


def test_splishsplash_refuses_bad_values_and_names_its_optional_package(refused, files):
    refused("splishsplash", ["--side", "0", "--dx", "0.01", "--dt", "1e-4", "--out", files["nodir"]], "--side = 0")
    refused("splishsplash", ["--side", "3", "--dx", "0.01", "--dt", "1e-4", "--out", files["nodir"]], "--out")
    try:
        import pysplishsplash  # noqa: F401
    except ImportError:
        refused("splishsplash", ["--side", "3", "--dx", "0.01", "--dt", "1e-4", "--out", str(pathlib.Path(files["regular"]).parent / "o.json")],
                "pysplishsplash", "pip install pysplishsplash")


@pytest.mark.parametrize("argv,option", [(["--sizes", "abc"], "--sizes = 'abc'"), (["--devices", "gpu9"], "--devices = 'gpu9'"),
                                         (["--steps", "0"], "--steps = 0"), (["--blocks", "0"], "--blocks = 0"),
                                         (["--variants", "--baseline-commit", "nosuchcommit"], "--baseline-commit = 'nosuchcommit'"),
                                         (["--fit-weight", "gauss"], "--fit-weight = 'gauss'")])
def test_step(refused, argv, option):
    refused("step", argv, option)


@pytest.mark.parametrize("argv,option", [(["--repeats", "0"], "--repeats = 0"), (["--scene", "nosuch"], "--scene = 'nosuch'"),
                                         (["--scale", "0"], "--scale = 0")])
def test_sweep_bench(refused, argv, option):
    refused("sweep_bench", argv, option)


@pytest.mark.parametrize("argv,words", [(["--rows", "nosuch"], ["--rows = 'nosuch'", "Fig. 5 (left)"]),
                                        (["--device", "gpu9"], ["--device = 'gpu9'"]), (["--steps", "0"], ["--steps = 0"]),
                                        (["--min-seconds", "nan"], ["--min-seconds = nan"])])
def test_table1(refused, argv, words):
    refused("table1", argv, *words)


@pytest.mark.parametrize("dtype", ["float16", "double", "vec3"])
def test_table1_measure_refuses_an_unknown_dtype_by_name_before_it_builds_the_scene(monkeypatch, dtype):
    """measure() looked ``dtype`` up in Warp: "double" raised AttributeError, "float16" and
    "vec3" reached finalize once the paper's scene was built. It is refused by name, as the
    lab tests refuse it, and nothing is built."""
    from warp_esph import scenes

    table1 = importlib.import_module("benchmarks.table1")
    monkeypatch.setattr(scenes, "paper_run_scene", lambda run: pytest.fail("built the scene of a refused dtype"))
    with pytest.raises(ValueError, match=rf"^dtype = '{dtype}' is not allowed: must be one of 'float32', 'float64'$"):
        table1.measure(scenes.TABLE1[0], "cpu", dtype, 0, 1, 0.0)


@pytest.mark.parametrize("argv,option", [(["--worlds", "0"], "--worlds = 0"), (["--device", "gpu9"], "--device = 'gpu9'"),
                                         (["--particles", "-5"], "--particles = -5"), (["--repeat", "0"], "--repeat = 0")])
def test_worlds_bench(refused, argv, option):
    refused("worlds_bench", argv, option)


@pytest.mark.parametrize("argv,option", [(["abc"], "SCALE = 'abc'"), (["-1"], "SCALE = -1"), (["0.3", "0"], "FRAMES = 0")])
def test_lab_bending_force(refused, argv, option):
    refused("lab_bending_force", argv, option)


def test_lab_bending_force_checks_its_environment(refused, monkeypatch):
    monkeypatch.setenv("FIT", "nosuch")
    refused("lab_bending_force", [], "FIT = 'nosuch'", "linear")
    monkeypatch.delenv("FIT")
    monkeypatch.setenv("HOURGLASS", "x")
    refused("lab_bending_force", [], "HOURGLASS = 'x'")


def test_static_stiffness_has_a_parser(refused, capsys):
    refused("static_stiffness", ["--bogus"], "--bogus")
    from benchmarks import static_stiffness

    with pytest.raises(SystemExit) as e:
        static_stiffness.main(["--help"])
    assert e.value.code == 0 and "--modes" in capsys.readouterr().out


@pytest.mark.parametrize("option", ["--merge", "--add"])
@pytest.mark.parametrize("name,words", [("missing", ["no such file"]), ("folder", ["folder"]), ("garbage", ["not UTF-8"]),
                                        ("empty", ["empty"]), ("object.json", ["'results'"])])
def test_validation_refuses_a_file_it_cannot_read_by_option_and_name(refused, files, tmp_path, option, name, words):
    argv = [option, files[name], "--no-report", "--out", str(tmp_path / "out")]
    if option == "--merge":
        argv += ["--only", "bar_frequency"]
    refused("validation", argv, f"{option} = {files[name]!r}", *words)
    assert not (tmp_path / "out" / "validation.json").exists()


@pytest.mark.parametrize("name,words", [("nosuch.json", ["result 0", "'nosuch'", "slump"]),
                                        ("bad_resolution.json", ["result 0", "resolution = 'abc'"]),
                                        ("no_results.json", ["nothing to add"])])
def test_validation_refuses_rows_it_cannot_add(refused, files, tmp_path, name, words):
    refused("validation", ["--add", files[name], "--no-report", "--out", str(tmp_path / "out")],
            f"--add = {files[name]!r}", *words)
    assert not (tmp_path / "out" / "validation.json").exists()


def test_validation_refuses_an_output_folder_it_cannot_make_and_lists_the_cases_of_the_plan(refused, files, tmp_path,
                                                                                            monkeypatch):
    good = tmp_path / "good.json"
    good.write_text(json.dumps([{"case": "slump", "S": 0.2, "resolution": 8}]))
    refused("validation", ["--add", str(good), "--out", files["under_file"]], f"--out = {files['under_file']!r}")
    refused("validation", ["--only", "nosuch", "--out", str(tmp_path)], "--only = 'nosuch'", "bar_frequency", "slump")
    # An empty --only (an unset shell variable) ran the whole plan; /proc passed os.access as root.
    refused("validation", ["--only", "", "--out", str(tmp_path)], "--only = '' is not allowed: give case names")
    refused("validation", ["--quick", "--only", "bar_frequency", "--out", "/proc"], "--out = '/proc'", "cannot take a new file")
    # A folder to make under one that takes no file: the refusal names the folder typed, not the
    # one probed ("--out = '/proc'"). os.access says yes as root; as another user it said no first.
    monkeypatch.setattr(_cli.os, "access", lambda *args, **kwargs: True)
    line = refused("validation", ["--quick", "--only", "bar_frequency", "--out", "/proc/x/y"],
                   "--out = '/proc/x/y' is not allowed: '/proc' cannot take a new file")
    assert "--out = '/proc' " not in line
    refused("validation", ["--merge", str(good), "--drop", "nosuch", "--out", str(tmp_path)], "--drop = 'nosuch'")


def test_validation_report(refused, files, capsys):
    refused("validation_report", [files["garbage"]], f"JSON = {files['garbage']!r}")
    refused("validation_report", [files["object.json"]], "'results'")
    refused("validation_report", [files["missing"]], "no such file")
    from benchmarks import validation_report

    with pytest.raises(SystemExit) as e:
        validation_report.main(["--help"])
    assert e.value.code == 0 and "JSON" in capsys.readouterr().out


# ------------------------------------------------------------------------------ as commands
@pytest.mark.parametrize("argv,option", [
    (["floors", "--repeat", "0"], "--repeat = 0"),
    (["launches", "--blocks", "0"], "--blocks = 0"),
    (["table1", "--steps", "0"], "--steps = 0"),
    (["sweep_bench", "--repeats", "0"], "--repeats = 0"),
    (["static_stiffness", "--bogus"], "--bogus"),
    (["step", "--steps", "0"], "--steps = 0"),
    (["splishsplash", "--side", "0", "--dx", "1", "--dt", "1", "--out", "x.json"], "--side = 0"),
    (["validation_report", "--bogus"], "--bogus"),
    # refused after the scene is built (its lattice is read): Warp must have started quietly
    (["lab_bending_force", "0.3", "9"], "SCALE = 0.3"),
])
def test_the_commands_exit_2_with_one_line(argv, option):
    proc = subprocess.run([sys.executable, "-m", f"benchmarks.{argv[0]}", *argv[1:]], cwd=ROOT, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.splitlines() == [proc.stderr.strip()] and option in proc.stderr, proc.stderr
    assert proc.stderr.startswith(f"python -m benchmarks.{argv[0]}: error: ") and proc.stdout == ""


def test_validation_as_a_command_names_a_file_it_cannot_read(files, tmp_path):
    proc = subprocess.run([sys.executable, "-m", "benchmarks.validation", "--add", files["garbage"], "--out", str(tmp_path)],
                          cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    assert f"--add = {files['garbage']!r} is not allowed" in proc.stderr
