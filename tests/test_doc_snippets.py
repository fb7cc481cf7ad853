"""The Python snippets the pages show, run as they are written: README.md's quick start,
docs/scene_format.md's loader and docs/tools.md's press; and the pages' example command lines,
parsed. Each is read from its page, so a page whose snippet stops running (a renamed call, a
changed signature, a dropped option) fails here; only a loop count is cut, where the page's run
is longer than a test's, and the page is checked to hold the line that is cut."""

import pathlib
import re
import shlex

import numpy as np
import pytest

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
