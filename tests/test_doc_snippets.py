"""The Python snippets the pages show, run as they are written: README.md's quick start,
docs/scene_format.md's loader, example file and lab material, docs/tools.md's press and docs/fitting.md's quick start and worlds, docs/cli.md's sweep;
and the pages' example command lines,
the CLI's and the benchmarks', parsed; every Python block's imports and the keywords of its calls of them. Each is read from its page, so a page whose snippet stops running (a renamed call, a
changed signature, a dropped option) fails here; only a loop count is cut, where the page's run
is longer than a test's, and the page is checked to hold the line that is cut."""

import pathlib
import re
import shlex

import numpy as np
import pytest

import warp as wp

import warp_esph as we
from warp_esph import cli
from warp_esph.cli import _build_parser
from warp_esph.usd import UsdFrames

ROOT = pathlib.Path(__file__).resolve().parent.parent


def _python_blocks(page: pathlib.Path) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", page.read_text(), flags=re.S | re.M)


def _shortened(code: str, line: str, short: str) -> str:
    # The cut must name a line the page holds, or the test would run a snippet of its own.
    assert code.count(line) == 1, f"the snippet no longer holds {line!r}"
    return code.replace(line, short)


def test_the_readme_quick_start_runs_and_drops_the_block(capsys):
    """README.md's Python section: a dough box built at y = 0.3 m over the ground, stepped
    (here 100 of the page's 1000 steps), printing its mean position and the guard counts."""
    code = _python_blocks(ROOT / "README.md")[0]
    code = _shortened(code, "for _ in range(1000):", "for _ in range(100):")
    exec(compile(code, "README.md", "exec"), {"__name__": "readme"})
    out = capsys.readouterr().out.strip().splitlines()[-1]
    mean = np.array([float(v) for v in re.match(r"\[([^\]]*)\]", out).group(1).split()])
    guards = eval(out[out.index("{"):])
    assert np.isfinite(mean).all()
    # It falls under gravity from where the page built it, straight down: the box and the
    # ground are symmetric about the vertical axis through its centre.
    assert mean[1] < 0.3 - 0.005
    assert abs(mean[0]) < 1e-4 and abs(mean[2]) < 1e-4
    assert tuple(guards) == we.GUARD_NAMES


def test_the_scene_format_snippet_writes_every_frame_of_the_scene(tmp_path, monkeypatch):
    """docs/scene_format.md's loader: a scene file read, built and run to a USD file that holds
    the initial frame and each of the scene's frames."""
    (tmp_path / "my_scene.toml").write_text(
        '[scene]\nspacing = 0.04\nframes = 3\n\n[[bodies]]\nshape = "box"\nmaterial = "dough"\n'
        'center = [0, 0.2, 0]\nsize = [0.12, 0.12, 0.12]\n\n[[colliders]]\ntype = "ground"\n')
    monkeypatch.chdir(tmp_path)
    code = _python_blocks(ROOT / "docs" / "scene_format.md")[0]
    exec(compile(code, "scene_format.md", "exec"), {"__name__": "scene_format"})
    frames = UsdFrames(tmp_path / "out.usdc")
    assert frames.frames == [0, 1, 2, 3]
    assert frames.arrays(3)["points"][:, 1].mean() < frames.arrays(0)["points"][:, 1].mean()


def test_the_scene_format_example_file_loads_as_its_comments_say(tmp_path):
    """docs/scene_format.md's example scene file, written out whole beside a mesh where it names
    one (a cube at ``meshes/part.obj``, read relative to the file, not the working folder) and
    loaded at half its resolution: each value its comments state is the loaded scene's."""
    from warp_esph.scenes import load_scene_file  # noqa: PLC0415

    text = re.findall(r"^```toml\n(.*?)^```", (ROOT / "docs" / "scene_format.md").read_text(), flags=re.S | re.M)[0]
    (tmp_path / "meshes").mkdir()
    corners = [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
    quads = [(1, 2, 4, 3), (5, 7, 8, 6), (1, 5, 6, 2), (3, 4, 8, 7), (1, 3, 7, 5), (2, 6, 8, 4)]
    (tmp_path / "meshes" / "part.obj").write_text("".join(f"v {x} {y} {z}\n" for x, y, z in corners)
                                                  + "".join(f"f {a} {b} {c}\nf {a} {c} {d}\n" for a, b, c, d in quads))
    (tmp_path / "scene.toml").write_text(text)
    scene = load_scene_file(tmp_path / "scene.toml", scale=0.5)
    assert (scene.name, scene.frames, scene.fps, scene.dt) == ("dough_and_ball", 60, 30.0, None)
    assert scene.builder.spacing == pytest.approx(0.02)  # 0.01 at scale 0.5
    model = scene.builder.finalize()
    assert model.body_names == ["slab", "ball", "cylinder2", "star3", "part"]
    soft, bouncy, clay, dough = model.materials
    assert soft.mu == pytest.approx(1.5e4 / 2.6) and soft.lam == pytest.approx(1.5e4 * 0.3 / (1.3 * 0.4))
    assert soft.yield_stress == we.Material.preset("dough").yield_stress
    assert (bouncy.mu, bouncy.lam, bouncy.density, bouncy.yield_stress) == (7.0e4, 2.8e5, 1100.0, float("inf"))
    assert clay == we.Material.preset("clay") and dough == we.Material.preset("dough")


def test_the_scene_format_lab_material_is_the_one_from_rheology_gives(tmp_path):
    """docs/scene_format.md's material of a rheometer's values, given a body and loaded: the
    material ``Material.from_rheology`` makes of the values its table holds."""
    from warp_esph.scenes import load_scene_file  # noqa: PLC0415

    blocks = re.findall(r"^```toml\n(.*?)^```", (ROOT / "docs" / "scene_format.md").read_text(), flags=re.S | re.M)
    (table,) = [b for b in blocks if "shear_yield_stress" in b]
    (tmp_path / "lab.toml").write_text('[scene]\nspacing = 0.05\n\n' + table
                                       + '\n[[bodies]]\nshape = "sphere"\nmaterial = "paste"\ncenter = [0, 0.2, 0]\nradius = 0.1\n')
    (material,) = load_scene_file(tmp_path / "lab.toml").builder.finalize().materials
    assert material == we.Material.from_rheology(2.0e4, 0.3, shear_yield_stress=50.0, plastic_viscosity=10.0)


def test_the_tools_md_press_exerts_the_force_the_page_states():
    """docs/tools.md's first snippet, run whole (1000 steps of 312 particles): the plate's force
    on the sample at its end is the one the sentence after it states, pointing down."""
    page = (ROOT / "docs" / "tools.md").read_text()
    code = _python_blocks(ROOT / "docs" / "tools.md")[0]
    scope = {"__name__": "tools_md"}
    exec(compile(code, "tools.md", "exec"), scope)
    stated = re.search(r"\(`force` is about \(0, (-?[\d.]+), 0\) N at the end", page)
    assert stated, "docs/tools.md no longer states the plate's force after its snippet"
    force = np.asarray(scope["force"], dtype=float)
    assert force[1] == pytest.approx(float(stated.group(1)), rel=0.02)
    assert np.hypot(force[0], force[2]) < 1e-3 * abs(force[1])


def _dough_block(yield_stress: float, spacing: float) -> we.SceneBuilder:
    """docs/fitting.md's worlds scene (a dough block on the ground), at a given yield stress."""
    builder = we.SceneBuilder(spacing=spacing)
    builder.add_box((0, 0.1, 0), (0.12, 0.1, 0.1), we.Material.preset("dough", yield_stress=yield_stress), name="block")
    builder.add_ground()
    return builder


def test_the_fitting_md_quick_start_fits_and_leaves_the_model_holding_the_fit():
    """docs/fitting.md's quick start, on a builder and a target the page leaves to the reader (a
    36-particle dough block at the preset's yield stress; the target its run at 100 Pa), run as
    written but for 2 of its 30 L-BFGS iterations: the loss falls, the model holds the fitted
    values (the page says so), and the termination is one of the sentences the page lists."""
    from warp_esph.rollout import Rollout  # noqa: PLC0415

    truth = _dough_block(100.0, 0.03).finalize(dtype=wp.float64, requires_grad=True)
    target = Rollout(truth, steps=300, dt=1e-3, frames=[100, 200, 300]).forward()
    code = _shortened(_python_blocks(ROOT / "docs" / "fitting.md")[0], "iterations=30", "iterations=2")
    scope = {"__name__": "fitting_md", "builder": _dough_block(150.0, 0.03), "target": target}
    exec(compile(code, "fitting.md", "exec"), scope)
    result, model = scope["result"], scope["model"]
    assert result.loss < result.initial_loss
    fitted = model.materials[0]
    assert fitted.yield_stress == pytest.approx(float(result.params["yield_stress"][0]))
    assert fitted.flow_rate == pytest.approx(float(result.params["flow_rate"][0]))
    assert (fitted.yield_stress, fitted.flow_rate) != (150.0, 20.0)
    assert re.match(r"(converged|stalled|hit the iteration cap|stopped at once)", result.termination)
    assert set(result.diagnostics.summary().split()) >= {"yield_stress", "flow_rate"}


def test_the_fitting_md_quick_start_names_the_terminations_as_they_are_printed():
    """The quick start's comment on ``print(result.termination)`` lists what it prints: each
    entry is how one of ``FitResult.TERMINATION``'s sentences begins ('flat' and 'not
    informative' were the stop's code names; the sentences begin 'stopped at once' and
    'learned nothing')."""
    from warp_esph.fit import FitResult  # noqa: PLC0415

    code = _python_blocks(ROOT / "docs" / "fitting.md")[0]
    listed = re.search(r"print\(result\.termination\)\s*# (.*)", code).group(1).split(" / ")
    assert len(listed) >= 4
    for entry in listed:
        assert any(sentence.startswith(entry) for sentence in FitResult.TERMINATION.values()), entry


def test_the_fitting_md_worlds_snippet_gives_each_world_its_loss_and_gradient():
    """docs/fitting.md's worlds snippet, run whole (3 worlds of 150 particles, 200 steps), with the
    one name it leaves to the reader, ``targets``: each world's target the final positions of a
    one-world run at 150 Pa. The world at 150 Pa has no loss and no gradient; the one at 50 Pa
    a loss whose gradient says raise the yield stress, the one at 450 Pa lower it."""
    from warp_esph.rollout import Rollout  # noqa: PLC0415

    one = _dough_block(150.0, 0.02).finalize(dtype=wp.float64, requires_grad=True)
    final = Rollout(one, steps=200, dt=1e-3, frames=[200]).forward()
    scope = {"__name__": "fitting_md", "targets": [final] * 3}
    exec(compile(_python_blocks(ROOT / "docs" / "fitting.md")[5], "fitting.md", "exec"), scope)
    values = np.asarray(scope["rollout"].world_values, dtype=float)
    slopes = [float(np.asarray(g["yield_stress"]).ravel()[0]) for g in scope["rollout"].per_world(scope["grads"])]
    assert values[1] == pytest.approx(0.0, abs=1e-12) and slopes[1] == pytest.approx(0.0, abs=1e-15)
    assert values[0] > 0 and values[2] > 0
    assert slopes[0] < 0 < slopes[2]


def _command_lines():
    """Every ``warp-esph`` command of the pages' code blocks (docs/validation.md's are the
    benchmark's own), continuation lines joined and comments dropped."""
    for page in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        if page.name == "validation.md":
            continue
        for block in re.findall(r"^```[a-z]*\n(.*?)^```", page.read_text(), flags=re.S | re.M):
            for line in block.replace("\\\n", " ").splitlines():
                argv = shlex.split(line, comments=True)
                # The synopsis at the top of docs/cli.md ([OPTION], ...) is no command to run.
                if argv[:1] == ["warp-esph"] and not any(a.startswith("[") or a == "..." for a in argv):
                    yield page.name, argv[1:]


def test_the_pages_command_examples_are_command_lines_the_parser_takes():
    """Each example command a page shows parses as written: an option renamed or dropped, a
    choice that no longer exists, fails here (docs/cli.md's option lists are checked against
    the parsers by tests/test_docs.py; these are the examples a reader copies)."""
    commands = list(_command_lines())
    assert len(commands) >= 15 and {argv[0] for _, argv in commands} >= {"run", "render", "fit", "sweep", "scenes"}
    for page, argv in commands:
        try:
            _build_parser().parse_args(argv)
        except (SystemExit, cli._UsageError) as exc:
            pytest.fail(f"{page}: warp-esph {' '.join(argv)} is refused by the parser ({exc})")


def test_the_cli_md_sweep_snippet_runs_and_its_resume_runs_nothing_again(tmp_path, monkeypatch):
    """docs/cli.md's Python sweep, run as a script (``__main__``) with its sizes cut: 2 of its
    8 samples, 1 of its 30 frames, 1 worker (in this process) for 2. Its resume had named the
    folder the command writes, which the snippet never made, and stopped at a ValueError; it
    now resumes the table it has, whose samples all ran: the same rows come back, none run."""
    monkeypatch.chdir(tmp_path)
    code = _python_blocks(ROOT / "docs" / "cli.md")[0]
    assert code.count("yield_stress=100:1000:log:8") == 2 and code.count("frames=30") == 2
    code = code.replace("yield_stress=100:1000:log:8", "yield_stress=100:1000:log:2").replace("frames=30", "frames=1")
    code = _shortened(code, "workers=2", "workers=1")
    ran = []
    import warp_esph.sweep as sweep_module  # noqa: PLC0415

    run_sample = sweep_module.parallel_map

    def counted(fn, items, **kw):
        ran.extend(items)
        return run_sample(fn, items, **kw)

    monkeypatch.setattr(sweep_module, "parallel_map", counted)
    scope = {"__name__": "__main__"}
    exec(compile(code, "cli.md", "exec"), scope)
    table = scope["table"]
    assert len(ran) == 2, "the resume ran samples again"
    heights = table.column("max_height")
    assert len(heights) == 2 and np.all(np.isfinite(heights))
    assert (tmp_path / "sweep.csv").is_file()
    assert np.asarray(scope["starts"]).shape[0] == 8


class _Parsed(Exception):
    """Raised in place of a benchmark's run once its command line has parsed."""


def test_the_pages_benchmark_commands_are_command_lines_their_parsers_take(monkeypatch):
    """Each ``python -m benchmarks.NAME ...`` a page gives a reader to measure again (in a code
    block or inline code) parses with that benchmark's own parser, up to the run itself, which
    is stopped there: a renamed option or a dropped choice fails here. docs/validation.md's run
    column is a log (prose between options) and is left out, as are commands for a device this
    host lacks."""
    import argparse  # noqa: PLC0415
    import importlib  # noqa: PLC0415

    parse = argparse.ArgumentParser.parse_args

    def parse_then_stop(self, args=None, namespace=None):
        raise _Parsed(parse(self, args, namespace))

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", parse_then_stop)
    commands = []
    for page in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        if page.name == "validation.md":
            continue
        text = page.read_text()
        lines = re.findall(r"`(python -m benchmarks\.\w+[^`\n]*)`", text)
        for block in re.findall(r"^```[a-z]*\n(.*?)^```", text, flags=re.S | re.M):
            lines += [line.strip() for line in block.replace("\\\n", " ").splitlines()
                      if line.strip().startswith("python -m benchmarks.")]
        commands += [(page.name, shlex.split(line, comments=True)) for line in lines]
    assert len(commands) >= 20 and len({argv[2] for _, argv in commands}) >= 8
    wrong = []
    for page, argv in commands:
        if "cuda" in " ".join(argv) and not wp.is_cuda_available():
            continue
        try:
            importlib.import_module(argv[2]).main(argv[3:])
        except _Parsed:
            continue
        except SystemExit as exc:
            wrong.append(f"{page}: {' '.join(argv)} is refused ({exc})")
            continue
        wrong.append(f"{page}: {' '.join(argv)} ran past its parser")
    assert not wrong, "\n".join(wrong)


def _called_names(code: str):
    """Each call of a name the block imports (``fit(...)``, ``Rollout(...)``,
    ``ReactionForceLoss.from_csv(...)``, ``we.SceneBuilder(...)``) with its keyword names, and
    the block's imports, as ``(imports, [(dotted name, keywords, line)])``."""
    import ast  # noqa: PLC0415

    tree = ast.parse(code)
    imports = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            imports.update({a.asname or a.name: f"{node.module}.{a.name}" for a in node.names})
        elif isinstance(node, ast.Import):
            imports.update({a.asname or a.name: a.name for a in node.names})
    calls = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        parts, f = [], node.func
        while isinstance(f, ast.Attribute):
            parts.insert(0, f.attr)
            f = f.value
        if isinstance(f, ast.Name) and f.id in imports:
            calls.append((".".join([f.id, *parts]), [k.arg for k in node.keywords if k.arg], node.lineno))
    return imports, calls


def test_every_python_block_imports_what_the_package_has_and_calls_it_with_its_keywords():
    """The blocks that leave names to the reader (a ``model``, a ``target``: fitting.md's lower
    level, PyTorch, joint fits and force curves, tools.md's particle floor) are not run here;
    what they import must still be there, and each call of an imported name (``Rollout(...,
    checkpoint_every=...)``, ``Experiment(..., noise=...)``, ``ReactionForceLoss.from_csv(...)``)
    must take the keywords it is given: a renamed function or keyword fails here."""
    import importlib  # noqa: PLC0415
    import inspect  # noqa: PLC0415

    checked = 0
    for page in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for code in _python_blocks(page):
            imports, calls = _called_names(code)
            scope = {}
            for name, path in imports.items():
                module, _, attr = path.rpartition(".")
                try:
                    scope[name] = importlib.import_module(path)  # a module (import warp_esph as we)
                except ImportError:
                    assert hasattr(importlib.import_module(module), attr), f"{page.name}: {module} has no {attr} to import"
                    scope[name] = getattr(importlib.import_module(module), attr)
            for dotted, keywords, line in calls:
                target = scope[dotted.split(".")[0]]
                for part in dotted.split(".")[1:]:
                    assert hasattr(target, part), f"{page.name}: {dotted} (line {line} of its block) is not there"
                    target = getattr(target, part)
                params = inspect.signature(target).parameters
                if any(p.kind is p.VAR_KEYWORD for p in params.values()):
                    continue
                unknown = [k for k in keywords if k not in params]
                assert not unknown, f"{page.name}: {dotted} takes no keyword {unknown} (line {line} of its block)"
                checked += 1
    assert checked >= 25
