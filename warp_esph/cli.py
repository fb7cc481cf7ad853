"""Command line: ``warp-esph run [SCENE] ...``, ``scenes``, ``render OUT.usd``, ``export OUT.usd``,
``fit SCENE --target FILE`` and ``sweep SCENE --param ...``.

Exit status: 0 success; 1 an unexpected error stopped a run, an export or a render mid-way
(one line naming it, where it was raised and what the output keeps); 2 bad input (unknown scene, bad option value, bad scene file,
unreadable or unwritable file, a model or picture more than the memory holds); 3 the simulation diverged (``SimulationError``; the
output keeps every frame finished before); 4 the output could not be written mid-run
(e.g. a full disk; it keeps every frame published before; ``export``, ``render``: the files
written before; ``fit``: its results, printed first); 5 ``fit`` stopped without converging (stalled, at
the iteration cap, a gradient of exactly zero or data that do not tell the values apart; not with
``--iterations 0``, which asks for no descent): every result is written as for a converged fit, and the last line
says how it stopped and what to change; 130 interrupted (Ctrl-C), 143 terminated
(SIGTERM): in both the output keeps every finished frame, and the last checkpoint
(``--checkpoint-every``) resumes the run (``--resume``). ``sweep`` exits 3 when at least
one sample failed (its row says why) and 130 when interrupted (the table keeps the
finished samples). Errors are one line on stderr,
``warp-esph: error: ...``.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import signal
import sys
import uuid
import warnings
from typing import NoReturn

PROG = "warp-esph"
# Kept here so the parser is built without importing the renderer (numpy, Pillow, pxr).
COLOR_CHOICES = ("body", "material", "alpha", "singular_values")
EXPORT_CHOICES = ("vtu", "ply")
EXIT_UNEXPECTED = 1  # an error of no kind the run expects stopped it mid-way (Python's status for one)
EXIT_BAD_INPUT = 2
EXIT_DIVERGED = 3
EXIT_WRITE_FAILED = 4
EXIT_NOT_CONVERGED = 5  # fit: stopped without converging, its results written
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143  # 128 + SIGTERM
EXIT_PIPE_CLOSED = 141  # 128 + SIGPIPE: what a shell reports for a writer whose reader left


class _UsageError(Exception):
    pass


def _typed(text: str):
    """A word typed after an option, for its refusal: shortened, as every refused value is (a
    5000-character --width wrote a 5 kB line)."""
    from .checks import shorten  # noqa: PLC0415

    return shorten(text)


def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{_typed(text)!r} is not allowed: must be an integer") from None


def _number(text: str) -> float:
    from .checks import read_number  # noqa: PLC0415

    try:
        # 1e400 said as typed in a refusal, not as the inf it reads as
        return read_number(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{_typed(text)!r} is not allowed: must be a number") from None


def refuse_underflow(flag: str, value) -> None:
    """Refuse a number typed that is not 0 but reads as 0.0 (``1e-400``, a ``TypedNumber``):
    it was taken as 0 without a word (``--hourglass 1e-400`` ran with the control off). One
    read as inf is left to the option's own check, which says it overflows."""
    from .checks import shorten, unheld_refusal  # noqa: PLC0415

    why = unheld_refusal(value, flag) if value == 0.0 else None
    if why:
        raise ValueError(f"{flag} = {shorten(value)} is not allowed: {why}")


class _Parser(argparse.ArgumentParser):
    """argparse that reports a usage error as one line and lets ``main`` exit 2; a value that is
    no number, or none of the names allowed, is said as every other refused value is,
    ``--frames = 'many' is not allowed: must be an integer`` (argparse's own words named no
    rule: ``argument --frames: invalid int value: 'many'``)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        # argparse looks its converters up here by the type given (groups share the registry).
        self.register("type", int, _integer)
        self.register("type", float, _number)
        # A value after its option that argparse took for an option: '--fps -inf' and '--dt -1e-3'
        # said 'expected one argument', where '--dt -1' was read as the number it is and refused
        # by name. No option of the CLI looks like a number, so every such word is a value.
        self._negative_number_matcher = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$|^-(inf|infinity|nan)$",
                                                   re.IGNORECASE)

    def _get_value(self, action, arg_string):
        value = super()._get_value(action, arg_string)
        # Every number option's converter (_number, --dt's) reads a number no float holds as a
        # TypedNumber: one that underflowed to 0.0 is refused here, where the option is known.
        if action.option_strings:
            try:
                refuse_underflow(action.option_strings[-1], value)
            except ValueError as e:
                raise argparse.ArgumentError(action, str(e)) from None
        return value

    def _check_value(self, action, value):
        if action.choices is not None and value not in action.choices:
            raise argparse.ArgumentError(action, f"{_typed(value)!r} is not allowed: must be one of "
                                                 + ", ".join(map(repr, action.choices)))

    def error(self, message):
        import re  # noqa: PLC0415

        # argparse puts 'argument --frames: ' before a converter's or a choice's line.
        said = re.fullmatch(r"argument (\S+): (.*)", message, re.S)
        if said:
            name = said[1].split("/")[-1]
            name = "the command" if name == "COMMAND" else name
            if said[2].startswith(f"{name} = "):  # a converter's line that names the option itself (--dt)
                message = said[2]
            elif said[2][:1] in "'\"":
                message = f"{name} = {said[2]}"
        raise _UsageError(message)


def _one_line(text) -> str:
    from .checks import long_words_cut  # noqa: PLC0415

    # A path a message names whole (an OSError's file, a writer's output) cut to its ends.
    return long_words_cut(" ".join(str(text).split()))


def _err(message) -> None:
    print(f"{PROG}: error: {_one_line(message)}", file=sys.stderr)


def option_flag(name: str) -> str:
    """The option a Python parameter is given by (``radius_scale`` -> ``--radius-scale``): the
    library's checks name their parameters, and a user of the CLI typed the option."""
    return "--" + name.replace("_", "-")


def _show_warning(message, category, filename, lineno, file=None, line=None):
    print(f"{PROG}: warning: {_one_line(message)}", file=sys.stderr)


def _build_parser() -> _Parser:
    from . import __version__  # noqa: PLC0415

    p = _Parser(prog=PROG, description="Point-based elastoplastic solids (Gerszewski et al. 2009) in NVIDIA Warp.")
    p.add_argument("--version", action="version", version=f"{PROG} {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    run = sub.add_parser("run", help="simulate a scene and write a USD file",
                         description="Simulate a built-in scene or a .toml scene file and write the frames to USD.")
    run.add_argument("scene", nargs="?", default=None, metavar="SCENE",
                     help="built-in scene name (see 'warp-esph scenes') or path to a .toml scene file; default: dough_drop")
    run.add_argument("-o", "--output", metavar="OUT.usd", help="output .usd/.usdc/.usda file; default: <scene>.usdc here")
    run.add_argument("--frames", type=int, metavar="N", help="number of frames after the initial one (default: the scene's)")
    run.add_argument("--fps", type=float, metavar="F", help="frames per second (default: the scene's)")
    run.add_argument("--dt", type=_dt_arg, metavar="DT",
                     help="time step in s; must divide 1/fps (default: the scene's dt, else the stable step); 'auto': an adaptive "
                          "(CFL) step per frame")
    run.add_argument("--adaptive-dt", action="store_true", help="the same as --dt auto")
    run.add_argument("--scale", type=float, default=1.0, metavar="S",
                     help="resolution scale: spacing / S, particle count ~ S^3 (default 1)")
    run.add_argument("--device", choices=("cpu", "cuda"), default="cpu", help="Warp device (default cpu)")
    run.add_argument("--dtype", choices=("float32", "float64"), default=None, help="precision (default float32)")
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    run.add_argument("--preview", action="store_true",
                     help="at the end, render the last frame to <output>.png beside the output (the whole name: a.usdc.png; software renderer; "
                          "with --surface it draws the surfaces)")
    run.add_argument("--surface", action="store_true",
                     help="also write a triangle surface per body and frame (UsdGeom.Mesh under /World/Surfaces)")
    run.add_argument("--export", choices=EXPORT_CHOICES, metavar="FORMAT",
                     help="at the end, also write every frame as vtu or ply files (meshio) into <output>_<FORMAT>/ "
                          "(the whole output name: a.usdc_vtu/)")
    run.add_argument("--checkpoint-every", type=int, metavar="N",
                     help="save the full state every N frames to <output>.checkpoint.npz (atomically)")
    run.add_argument("--resume", metavar="CHECKPOINT",
                     help="continue the run saved in CHECKPOINT (.npz), appending to its USD file; "
                          "the scene and its settings come from the checkpoint (--frames N: run to frame N instead)")
    _add_solver_arguments(run)
    sub.add_parser("scenes", help="list the built-in scenes", description="List the built-in scenes.")
    add_fit_arguments(sub.add_parser(
        "fit", help="fit material parameters of a scene to a target by gradient descent",
        description="Fit material parameters so the simulated scene reaches the target; writes JSON and USD."))

    ren = sub.add_parser("render", help="render frames of a USD output to PNG, GIF or MP4 (no display, no GPU)",
                         description="Render frames of a warp-esph USD file with the built-in software renderer "
                                     "(numpy + Pillow: no display, no GPU).")
    ren.add_argument("usd", metavar="OUT.usd", help="a USD file written by 'warp-esph run'")
    ren.add_argument("-o", "--output", metavar="DIR_OR_FILE",
                     help="a folder (PNG per frame), a .png (one frame; several side by side), a .gif, or an .mp4 "
                          "(needs ffmpeg); default: <OUT>.png (a.usdc.png), the last frame")
    ren.add_argument("--frames", metavar="SELECTION",
                     help="'all', 'first', 'last', N, -N, A:B, A:B:STEP or a comma list (default: all; last for a .png)")
    ren.add_argument("--color", choices=COLOR_CHOICES, default="body",
                     help="colour particles by body, material, alpha (plastic strain) or singular_values "
                          "(elastic strain max|ln sigma|) (default body)")
    ren.add_argument("--width", type=int, default=800, help="picture width in pixels (default 800)")
    ren.add_argument("--height", type=int, default=600, help="picture height in pixels (default 600)")
    ren.add_argument("--supersample", type=int, default=2, metavar="K", help="antialiasing: K x K samples per pixel (1-4, default 2)")
    ren.add_argument("--azimuth", type=float, metavar="DEG", help="camera azimuth about +y, from +z towards +x (default: the scene's, else 30)")
    ren.add_argument("--elevation", type=float, metavar="DEG", help="camera elevation (default: the scene's, else 20)")
    ren.add_argument("--zoom", type=float, default=1.0, help="> 1 moves the camera closer (default 1: fit all frames)")
    ren.add_argument("--radius-scale", type=float, default=1.0, metavar="S", help="draw particles S times their width (default 1)")
    ren.add_argument("--fit", choices=("all", "each"), default="all",
                     help="frame the bounds of all chosen frames with one camera (default), or each picture on its own")
    ren.add_argument("--columns", type=int, metavar="N", help="frames per row when several go into one .png (default up to 4)")
    ren.add_argument("--fps", type=float, help="playback rate of a .gif/.mp4, 0.01 to 1000 (default: the file's)")
    ren.add_argument("--no-label", action="store_true", help="no time label in the corner")
    ren.add_argument("--no-shadows", action="store_true", help="no shadows (faster)")
    ren.add_argument("--particles", "--no-surface", dest="particles", action="store_true",
                     help="draw particles even where the file holds surface meshes ('run --surface'); "
                          "by default a body with a surface is drawn as that surface (a file without any is drawn as "
                          "particles either way)")

    exp = sub.add_parser("export", help="write particle frames of a USD output as .vtu or .ply files (meshio)",
                         description="Write the particles of each frame of a warp-esph USD file as a .vtu or .ply file "
                                     "with point data velocity, alpha, singular_values, body_id, material_id.")
    exp.add_argument("usd", metavar="OUT.usd", help="a USD file written by 'warp-esph run'")
    exp.add_argument("--format", choices=EXPORT_CHOICES, default="vtu", help="file format (default vtu)")
    exp.add_argument("-o", "--output", metavar="DIR", help="output folder (default: <OUT>_<format>/ beside the file, e.g. a.usdc_vtu/)")
    exp.add_argument("--frames", metavar="SELECTION", help="frames, as for render (default: all)")
    _add_sweep_parser(sub)
    p.commands = tuple(sub.choices)  # named when none is given
    return p


def _add_solver_arguments(parser) -> None:
    """``--solver-fit``, ``--contact``, ``--hourglass`` and ``--fit-weight``: the scene's ``[solver]`` options, overridden."""
    parser.add_argument("--solver-fit", metavar="NAME",
                        help="fit of the solver: auto (where no material can flow and all use the variational force, the "
                             "rest-configuration model: the curvature_corrected total fit against each particle's rest "
                             "neighbourhood, with the hourglass control, tools allowed; in a scene with floor images or a ghost "
                             "floor the incremental curvature_corrected fit with the control; else linear), linear (the paper's) or "
                             "curvature_corrected (stiffer in bending near free surfaces); default: the scene's [solver] fit, "
                             "else auto")
    parser.add_argument("--contact", metavar="NAME",
                        help="contact law of colliders and tools: continuous (continuous in the state, so a loss is continuous "
                             "through contact) or instant (the whole inward velocity removed, the first law); default: the "
                             "scene's [solver] contact, else continuous")
    parser.add_argument("--hourglass", metavar="C",
                        help="strength (0 to 1000) of the hourglass control of the fit's zero-energy modes, for elastic solids "
                             "under concentrated loads (0.1 holds a pressed sphere indenter; warned of where a material can flow, whose flow "
                             "it holds back); 0: off; default: the scene's "
                             "[solver] hourglass, else 0.05 where the auto fit chose curvature_corrected and 0 otherwise")
    parser.add_argument("--fit-weight", metavar="NAME",
                        help="weights of the incremental fit: biweight (keeps a flowing material's stress through large "
                             "strain nearer the continuum's) or poly6 (the paper's eq. 7); default: the scene's "
                             "[solver] fit_weight, else biweight")


def _solver_options(args) -> dict:
    """The checked ``--solver-fit`` / ``--contact`` / ``--hourglass`` / ``--fit-weight`` as ``Model`` attribute values
    (only those given)."""
    from . import checks  # noqa: PLC0415
    from .model import CONTACTS, FITS  # noqa: PLC0415
    from .sim.smoothing import FIT_WEIGHTS  # noqa: PLC0415

    out = {}
    if getattr(args, "solver_fit", None) is not None:
        out["fit"] = checks.choice("--solver-fit", args.solver_fit, FITS)
    if getattr(args, "contact", None) is not None:
        out["contact_ramp"] = CONTACTS[checks.choice("--contact", args.contact, tuple(CONTACTS))]
    if getattr(args, "hourglass", None) is not None:
        out["hourglass"] = _hourglass_arg(args.hourglass)
    if getattr(args, "fit_weight", None) is not None:
        out["fit_weight"] = checks.choice("--fit-weight", args.fit_weight, FIT_WEIGHTS)
    return out


def _hourglass_arg(text) -> float:
    """``--hourglass`` as a number >= 0 (argparse's own type error would print the usage too)."""
    from .checks import read_number  # noqa: PLC0415

    try:
        value = read_number(text)
    except (TypeError, ValueError):
        value = float("nan")
    refuse_underflow("--hourglass", value)
    shown = _as_typed(text)
    from .checks import HOURGLASS_LIMIT, MAX_HOURGLASS  # noqa: PLC0415

    if not 0.0 <= value < float("inf"):
        raise ValueError(f"--hourglass = {shown} is not allowed: must be a finite number >= 0 (0: off)")
    if not value <= MAX_HOURGLASS:
        raise ValueError(f"--hourglass = {shown} is not allowed: {HOURGLASS_LIMIT}")
    return value


def _as_typed(text) -> str:
    """An option's text in a message: a number as typed, as the other numeric options show
    theirs ('--hourglass = -1', where it said '-1' in the text's quotes); a word quoted."""
    try:
        float(text)
    except (TypeError, ValueError):
        return repr(_typed(text))
    from .checks import shorten_text  # noqa: PLC0415

    return shorten_text(str(text).strip(), 60)  # 5000 digits are a number too


def _apply_solver_options(builder, options: dict) -> None:
    for name, value in options.items():
        setattr(builder, name, value)


def _add_sweep_parser(sub) -> None:
    sw = sub.add_parser("sweep", help="run a scene for many material values in parallel; a table and a plot",
                        description="Run a scene once per sample of material parameters (grid, random or Latin "
                                    "hypercube), on every core or a Ray cluster; write a table (CSV, Parquet) of summary "
                                    "quantities per sample and a plot. Exit 3 when some sample failed.")
    sw.add_argument("scene", metavar="SCENE", help="built-in scene name or .toml scene file")
    sw.add_argument("--param", action="append", metavar="NAME=LO:HI:SCALE:N",
                    help="a swept parameter: yield_stress=100:1000:log:8 (every material), dough.yield_stress=... "
                         "(a body's), 0.mu=... (material 0); LO:HI:SCALE for random/lhs; A,B,C or V; repeatable")
    sw.add_argument("--sample", choices=("grid", "random", "lhs"), default="grid", help="sampling (default grid)")
    sw.add_argument("--samples", type=int, metavar="N", help="number of samples for random and lhs")
    from .calibrate import _Given  # noqa: PLC0415 (imported for the fit parser anyway)

    sw.add_argument("--seed", type=int, default=0, metavar="S", action=_Given,
                    help="seed of random and lhs samples (default 0; not with grid, which draws nothing)")
    sw.add_argument("--max-samples", type=int, default=10000, metavar="N", help="refuse more samples (default 10000)")
    # Not a mutually exclusive group: argparse's refusal of both named no value; sweep's own says them.
    sw.add_argument("--frames", type=int, metavar="N", help="frames per sample (default: the scene's; not with --duration)")
    sw.add_argument("--duration", type=float, metavar="SEC", help="simulated seconds per sample (not with --frames)")
    sw.add_argument("--fps", type=float, metavar="F", help="frames per second (default: the scene's)")
    sw.add_argument("--dt", type=float, metavar="DT", help="time step; must divide 1/fps (default: the scene's dt, else each sample's stable step)")
    sw.add_argument("--scale", type=float, default=1.0, metavar="S", help="resolution scale of the scene (default 1)")
    sw.add_argument("--dtype", choices=("float32", "float64"), default="float32", help="precision (default float32)")
    sw.add_argument("-o", "--output", metavar="FOLDER", help="output folder (default: sweep_<scene>)")
    sw.add_argument("--workers", type=int, metavar="N", help="processes, one per core (default: every core; not with --ray, whose cluster places the samples)")
    sw.add_argument("--ray", metavar="ADDRESS", help="run the samples on the Ray cluster at ADDRESS (warp-esph[ray])")
    sw.add_argument("--resume", action="store_true",
                    help="keep the samples of the table in the output folder (a stopped run of this same sweep) and "
                         "run only those it lacks; a table of another scene, material, sampling or option is refused, "
                         "naming what differs (without --resume the sweep starts afresh and replaces the folder's tables)")
    sw.add_argument("--retry-failed", action="store_true", help="with --resume: run the table's failed samples again too")
    sw.add_argument("--no-progress", action="store_true", help="no progress bar")
    _add_solver_arguments(sw)


def _init_warp(device: str) -> None:
    """Initialise Warp without its banner; the native note a CPU machine prints about the
    missing CUDA driver is held back for a CPU run and reported as a warning for a CUDA run
    (``warp_esph.startup.init_warp``)."""
    from . import checks  # noqa: PLC0415
    from .startup import cuda_absence, init_warp  # noqa: PLC0415

    notes = init_warp(device, echo=False)
    if device != "cpu":
        import warp as wp  # noqa: PLC0415

        if not wp.is_cuda_available():
            # One line, not the driver's note and then the error; the reason read from Warp's
            # runtime, as its note is printed only at the start of the process.
            raise ValueError(f"--device = {checks.shorten(device)!r} is not allowed: Warp finds no CUDA device on this "
                             f"machine: {cuda_absence()} (use --device cpu)")
    for note in notes:
        if device != "cpu" or "CUDA" not in note:
            print(f"{PROG}: warning: {_one_line(note)}", file=sys.stderr)


def _stopped(args) -> str:
    """What stopped the command: 'terminated' for SIGTERM (exit 143), as the line said before the
    command was armed, else 'interrupted' (a SIGTERM mid-run was reported as Ctrl-C)."""
    signals = getattr(args, "signals", None)
    return "terminated" if signals is not None and signal.SIGTERM in signals.received else "interrupted"


def _signal_name(args) -> str:
    """The signal ``_stopped`` reports, by name ("SIGTERM", "SIGINT"), or "" where none was
    received (a ``KeyboardInterrupt`` raised otherwise)."""
    signals = getattr(args, "signals", None)
    if signals is None or not signals.received:
        return ""
    return "SIGTERM" if signal.SIGTERM in signals.received else "SIGINT"


def _signals_seen(args) -> int:
    """How many signals the command has received so far (``_held_signal_wins``' ``seen``)."""
    signals = getattr(args, "signals", None)
    return len(signals.received) if signals is not None else 0


def _held_signal_wins(args, seen: int, said: str) -> bool:
    """Where a Ctrl-C or SIGTERM came after ``seen`` (``_signals_seen``) and was never acted on,
    print ``said`` (a failure's one line) as the stop's line, 'warp-esph: terminated: ...', and
    return True: the caller exits 130 (143). A signal held while a file was written
    (``_Deferred``) is raised only when the write ends well, so a failed write dropped it and
    the command exited as the failure alone (4, or 2), though it had been asked to stop."""
    if _signals_seen(args) <= seen:
        return False
    print(f"{PROG}: {_stopped(args)}: {_one_line(said)}", file=sys.stderr)
    return True


def _arm(args) -> None:
    signals = getattr(args, "signals", None)
    if signals is not None:
        signals.arm()


def _cmd_scenes() -> int:
    from .scenes import DEFAULT_SCENE, scene_descriptions  # noqa: PLC0415

    descriptions = scene_descriptions()
    width = max(len(n) for n in descriptions)
    for name, text in descriptions.items():
        mark = " (default)" if name == DEFAULT_SCENE else ""
        print(f"{name:<{width}}  {text}{mark}")
    return 0


def _dt_arg(text: str):
    """``--dt``: seconds, or ``auto`` for the adaptive step."""
    from .checks import read_number  # noqa: PLC0415

    if text.strip().lower() == "auto":
        return "auto"
    try:
        return read_number(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--dt = {_typed(text)!r} is not allowed: must be a number of seconds or 'auto'") from None


def _stdout_closed() -> bool:
    """Whether this process's stdout is a pipe whose reader has left (writing to it fails):
    the kernel reports an error condition on its write end."""
    import select  # noqa: PLC0415

    try:
        poller = select.poll()
        poller.register(sys.stdout.fileno(), select.POLLOUT)
        return any(ev & (select.POLLERR | select.POLLHUP) for _, ev in poller.poll(0))
    except (OSError, ValueError, AttributeError):  # no descriptor (a captured stdout), no poll
        return False


def _drop_stdout():
    """Point stdout at the null device, so that flushing it at exit does not fail again on a
    closed pipe (a second 'Broken pipe' from the interpreter). For the installed command only:
    a caller of ``main`` keeps its own stdout."""
    try:
        fd = os.open(os.devnull, os.O_WRONLY)
        os.dup2(fd, sys.stdout.fileno())
        os.close(fd)
    except (OSError, ValueError, AttributeError):  # a stdout without a file descriptor (captured)
        pass


def _kept(writer, start_frame: int) -> str:
    """What an interrupted or failed run's file holds: the frames this run finished, and on a
    resumed run those of the run it continues too (from frame 0)."""
    if not os.path.isfile(writer.path):  # its folder removed during the run: nothing is kept
        return "nothing: the file is gone"
    if not start_frame:
        n = writer.frames_written
        if not n:  # stopped before the first frame was saved: it said 'the 0 frames finished'
            return "no frame: none was finished"
        return "the 1 frame finished" if n == 1 else f"the {n} frames finished"
    return f"frames 0..{writer.last_frame} finished" if writer.last_frame is not None else f"the frames before {start_frame}"


def _refuse_writing_over_inputs(scene, scene_arg, output: str, what: str) -> None:
    """Refuse a run whose USD output is a file its scene reads (a mesh body's or tool's
    ``.usdc``): the run replaced it, and the scene could not be run again. The path is checked
    as one first (``checks.output_place``): a NUL in it failed in ``realpath`` as a bare
    'embedded null byte'."""
    from . import checks  # noqa: PLC0415

    checks.output_place(what, output)
    # By real path, not file identity: the run replaces the output's name (os.replace), so a
    # hard link to a mesh is written as a file of its own and the mesh the scene reads is kept.
    read = {os.path.realpath(path): source for source, path in scene.inputs}
    source = read.get(os.path.realpath(output))
    if source is not None:
        raise ValueError(f"{what} = {checks.shown_path(output)} is not allowed: it is {source} of "
                         f"{checks.shown_path(os.fsdecode(scene_arg), False)}, which the run "
                         "would overwrite; give another --output")


def _run_advice() -> dict:
    """``warp-esph run``'s advice for a ``StepRefusal`` of a run's start, by the Python advice
    it replaces (which names ``dt=`` and ``fps=``)."""
    from .simulate import (  # noqa: PLC0415
        ADAPTIVE_ADVICE, ADAPTIVE_FALL_ADVICE, ADAPTIVE_FIELD_ADVICE, ADAPTIVE_HOURGLASS_ADVICE, ADAPTIVE_VISCOUS_ADVICE,
        ADAPTIVE_REPULSION_ADVICE, STABLE_ADVICE, STABLE_FIELD_ADVICE, STABLE_HOURGLASS_ADVICE, STABLE_REPULSION_ADVICE,
        START_ADVICE)
    from .tools import TOO_FAST_ADVICE  # noqa: PLC0415

    return {START_ADVICE: "; give a smaller velocity (or angular_velocity), a smaller --dt, or --dt auto (the adaptive step)",
            TOO_FAST_ADVICE: "; give a slower motion or a smaller --dt",
            ADAPTIVE_ADVICE: "; use a softer material, a larger spacing or a higher --fps",
            ADAPTIVE_VISCOUS_ADVICE: "; use a less viscous material, a larger spacing or a higher --fps",
            ADAPTIVE_HOURGLASS_ADVICE: "; use a smaller --hourglass (or [solver] hourglass), a larger spacing or a higher --fps",
            ADAPTIVE_FIELD_ADVICE: "; use a weaker compression field or a higher --fps",
            ADAPTIVE_REPULSION_ADVICE: "; use a smaller pair_repulsion or pressure_stiffness (the scene's material table), a "
                                       "larger spacing or a higher --fps",
            STABLE_REPULSION_ADVICE: ": use a smaller pair_repulsion or pressure_stiffness (the scene's material table), a "
                                     "larger spacing, a higher --fps, or give --dt",
            STABLE_ADVICE: ": use softer materials, a larger spacing, a higher --fps, or give --dt",
            STABLE_FIELD_ADVICE: ": use a weaker compression field, a higher --fps, or give --dt",
            STABLE_HOURGLASS_ADVICE: ": use a smaller --hourglass (or [solver] hourglass), a larger spacing, a higher --fps, or "
                                     "give --dt",
            ADAPTIVE_FALL_ADVICE: "; use a higher --fps (gravity adds up to |g| / fps to a speed within a frame) or a larger "
                                  "spacing"}


def _cmd_run(args) -> int:
    from . import checks  # noqa: PLC0415

    # Cheap checks first, so a typo is reported before anything is built.
    if args.frames is not None:
        checks.positive_int("--frames", args.frames)
    if args.fps is not None:
        checks.positive("--fps", args.fps)
    if args.adaptive_dt:
        if args.dt is not None and args.dt != "auto":
            raise ValueError(f"--dt = {args.dt!r} and --adaptive-dt are not allowed together: give one of them")
        args.dt = "auto"
    if args.dt is not None and args.dt != "auto":
        checks.positive("--dt", args.dt)
    scale = checks.positive("--scale", args.scale)
    if args.output is not None:
        from .usd import USD_EXTENSIONS  # noqa: PLC0415

        if os.path.splitext(args.output)[1].lower() not in USD_EXTENSIONS:
            raise ValueError(f"--output = {checks.shown_path(args.output)} is not allowed: the extension must be one of {', '.join(USD_EXTENSIONS)}")

    _init_warp(args.device)  # refuses --device cuda where Warp finds none
    from .scenes import load_scaled_scene  # noqa: PLC0415
    from .simulate import (SimulationError, StepRefusal, _check_run_start, check_step_count, divergence_advice, skipped_fits,  # noqa: PLC0415
                           coarse_bodies, shown_bodies,
                           far_mesh_advice, resolve_timestep, simulate)
    from .sim.solver import Solver  # noqa: PLC0415
    from .tools import TOO_FAST_ADVICE  # noqa: PLC0415
    from .usd import OutputInUse, UsdWriter  # noqa: PLC0415

    from .checkpoint import load_state, read_checkpoint, save_state  # noqa: PLC0415

    every = None if args.checkpoint_every is None else checks.positive_int("--checkpoint-every", args.checkpoint_every)
    options = _solver_options(args)
    start_frame, state, stable_step = 0, None, False
    if args.resume is not None:
        # The run record of the checkpoint decides everything the results depend on: a scene,
        # step, rate or scale given beside it would be ignored, so it is refused.
        given = [f"{name} = {_as_typed(value) if name == '--hourglass' else repr(value)}" for name, value, default in
                 (("SCENE", args.scene, None), ("--dt", args.dt, None), ("--fps", args.fps, None), ("--scale", args.scale, 1.0),
                  ("-o", args.output, None), ("--solver-fit", args.solver_fit, None), ("--contact", args.contact, None),
                  ("--hourglass", args.hourglass, None), ("--fit-weight", args.fit_weight, None),
                  ("--dtype", args.dtype, None), ("--surface", args.surface, False)) if value != default]
        if given:
            raise ValueError(f"{given[0]} is not allowed with --resume: the checkpoint's run decides it "
                             f"(give --resume, and --frames to extend the run)")
        meta, _ = read_checkpoint(args.resume, "--resume")
        run = meta.get("run", {})
        if not isinstance(run, dict) or not {"scene", "scale", "fps", "dt", "frames", "output", "dtype"} <= run.keys():
            raise ValueError(f"--resume = {checks.shown_path(args.resume)} is not allowed: the checkpoint was not written by "
                             "'warp-esph run'")
        _check_run_record(args.resume, run)
        args.scene, scale, args.dtype = _moved_with(args.resume, run["scene"]), run["scale"], run["dtype"]
        args.fps, args.dt, args.surface = run["fps"], run["dt"], run.get("surface", False)
        # A run that took the stable step (no dt given) takes it again, from the checkpoint's
        # state: one whose body flowed and was made elastic since keeps the corrected incremental
        # fit, at half the step it recorded (Model.stable_dt(state=)); with the same parameters
        # it is the step recorded.
        stable_step = run.get("dt_stable", False)
        args.output = _moved_with(args.resume, run["output"], output=True)
        frames_total = args.frames if args.frames is not None else run["frames"]  # --frames extends a run
        every = every or run.get("checkpoint_every")
        # the run's own, not the scene's now
        options = {k: run[k] for k in ("fit", "contact_ramp", "hourglass", "fit_weight") if k in run}
        # A record without a weight predates the option, when every run was poly6's; the
        # scene's weight now (the biweight by default) would be another model's fingerprint.
        options.setdefault("fit_weight", "poly6")
    args.dtype = args.dtype or "float32"
    scene = load_scaled_scene(args.scene, scale)
    _apply_solver_options(scene.builder, options)
    fps = args.fps if args.fps is not None else scene.fps
    dt = None if stable_step else args.dt if args.dt is not None else scene.dt
    stable_step = dt is None
    output = args.output or f"{scene.name}.usdc"
    if args.resume is None:
        # (a resumed run appends to its own output, which its scene did not read)
        _refuse_writing_over_inputs(scene, args.scene, output, "--output" if args.output else "the default output")
        checks.usd_output("--output" if args.output else "the default output", output)
        frames_total = args.frames if args.frames is not None else scene.frames

    model = scene.builder.finalize(device=args.device, dtype=args.dtype)
    if args.resume is not None:
        state, meta = load_state(args.resume, model, what="--resume")
        start_frame = meta["frame"]
    frames = frames_total - start_frame
    if frames < 1:
        if args.frames is not None:
            raise ValueError(f"--frames = {args.frames} is not allowed with --resume = {checks.shown_path(args.resume)}: the checkpoint is at "
                             f"frame {start_frame}; give more frames than that to extend the run")
        raise ValueError(f"--resume = {checks.shown_path(args.resume)} is not allowed: that run finished all {frames_total} frames")
    adaptive = dt == "auto"

    def flag(name):
        # The option where the value is the one typed (a resumed run's are its checkpoint's).
        return option_flag(name) if args.resume is None and getattr(args, name, None) is not None else name

    try:
        try:
            substeps, dt_shown = (resolve_timestep(model, fps, flag=flag, state=state) if adaptive else
                                  resolve_timestep(model, fps, dt=dt, flag=flag, state=state))
        except StepRefusal as e:
            # Its advice is Python's ('give dt= or substeps='): the command has --dt and --fps.
            raise ValueError(e.reason + _run_advice().get(e.advice, e.advice)) from None
    except ValueError as e:
        if (args.dt is None and args.resume is None and str(args.scene).lower().endswith(".toml")
                and not str(e).startswith("--")):  # an option typed is named as such, not as the file's
            raise ValueError(f"{checks.shown_path(args.scene, False)}: [scene] {e}") from None  # the file's dt and fps: name the file
        if (args.dt is None and args.resume is None and args.fps is not None and scene.dt is not None
                and "whole number of steps" in str(e)):
            # A built-in scene's own step (a figure's) at the --fps typed: the step is no option
            # to leave out, --dt or --fps is.
            from .simulate import scene_dt_refusal  # noqa: PLC0415

            raise scene_dt_refusal(f"{scene.name}'s dt", scene.dt, fps, f"--fps = {args.fps:g}", "--dt") from None
        raise
    dt_given = dt is not None and not adaptive
    dt_typed = dt
    if not adaptive:
        dt = dt_shown
    try:
        check_step_count(frames, substeps)
    except StepRefusal as e:
        # Its advice is Python's ('frames=', 'dt=', 'substeps='): the command has --frames and
        # --dt, and neither --dt nor --scale with --resume. Without a dt the step is the stable
        # one, and a --dt above it blows the run up: a larger spacing lengthens it.
        named = f"--frames = {args.frames!r}" if args.frames is not None else f"frames = {frames_total!r}"
        if args.frames is None and args.resume is None and str(args.scene).lower().endswith(".toml"):
            named = f"{checks.shown_path(args.scene, False)}: [scene] {named}"  # the file's frames: name the file, as for its dt and fps
        cure = ("" if args.resume is not None else " or a larger --dt" if dt_given else
                ", or a smaller --scale (a larger spacing, whose stable step is longer)")
        raise ValueError(f"{named} is not allowed: {e.detail}; give fewer --frames{cure}") from None
    solver = Solver(model)
    if dt_given:
        # Before check_dt, whose refusal names Python's dt, at 1/fps / steps, not the value given.
        from .sim.solver import resolvable_dt  # noqa: PLC0415

        named = flag("dt")
        if named == "dt" and args.resume is None and str(args.scene).lower().endswith(".toml"):
            named = f"{checks.shown_path(args.scene, False)}: [scene] dt"
        resolvable_dt(model, float(dt_typed), named, "the stable step", state=state)
    solver.check_dt(dt_shown, state)  # the stability warning, once, before the run (from a resumed run's state)
    try:
        # Before the writer replaces an earlier run's file; simulate does not repeat them.
        start = state if state is not None else model.state(requires_grad=False)
        checked = _check_run_start(model, start, frames, fps, dt, hourglass=solver.hourglass, start_frame=start_frame)
    except ValueError as e:
        said = str(e)
        if isinstance(e, StepRefusal):
            # Its advice is Python's ('a smaller dt=', 'dt='auto'', 'a higher fps='): the command
            # has --dt, --dt auto and --fps, and none of them with --resume.
            said = e.reason + ("" if args.resume is not None else _run_advice().get(e.advice, e.advice))
        if str(args.scene).lower().endswith(".toml"):
            # (the adaptive step's refusal may be a tool's, which names it). The body's own table,
            # as the file's other refusals name it: '[[bodies]]' alone left a reader counting.
            table = ""
            if said.startswith("initial velocity"):
                table = f"{scene.builder.origins.get(('body', getattr(e, 'body_index', None)), '[[bodies]]')}: "
            raise ValueError(f"{checks.shown_path(args.scene, False)}: {table}{said}") from None
        if said != str(e):
            raise ValueError(said) from None
        raise
    # Every file the run writes, checked before the run (a folder in the way of the reaction
    # log was found only after the whole run); named after the whole output path, as the writer does.
    stem = os.path.abspath(os.fspath(output))
    if args.resume is None:
        checks.output_place("--output", stem)
    elif not os.path.isfile(stem):
        # The writer refuses it; said here, before the force log's resume warned that the log
        # beside it was missing too (two lines for one cause, the warning first).
        raise FileNotFoundError(f"cannot append to {checks.shown_path(stem, False)}: no such file")
    if model.tools is not None or model.planes or model.spheres or model.boxes:
        for log_file in (stem + "_tools.csv", stem + "_tools.json"):
            checks.output_place("the reaction log", log_file)
    if every is not None:
        checks.output_place("--checkpoint-every's checkpoint", stem + ".checkpoint.npz")
    if args.export:
        checks.output_place(f"--export {args.export}'s folder", f"{stem}_{args.export}", folder=True)
        # Every frame of the run's file, as export_frames writes them after the run.
        checks.output_files(f"--export {args.export}'s folder", f"{stem}_{args.export}",
                            [f"frame_{f:05d}.{args.export}" for f in range(frames_total + 1)]
                            + ["frames.pvd"] * (args.export == "vtu"))
    if args.preview:
        checks.output_place("--preview's picture", stem + ".png")
    # Names the run in its file, checkpoints and force log: a checkpoint resumes onto its own run's only.
    run_id = run.get("run_id") if args.resume is not None else uuid.uuid4().hex
    # Tools (moving colliders, pinned sets) and static colliders: pose and mean reaction per
    # frame, beside the USD; a resumed run's earlier rows are read before anything is written.
    log = None
    if model.tools is not None or model.planes or model.spheres or model.boxes:
        from .tools import ReactionLog  # noqa: PLC0415

        log = ReactionLog(solver)
        log.run_id = run_id
        if args.resume is not None:
            log.resume(os.path.abspath(os.fspath(output)), start_frame)  # the finished frames of the run it continues
    _arm(args)  # from here an interrupt unwinds through the writer
    try:
        writer = UsdWriter(output, model, fps, surface=args.surface, view=getattr(scene, "view", None),
                           append=args.resume is not None, run_id=run_id)
    except OutputInUse as e:
        raise ValueError(f"--output = {checks.shown_path(output)} is not allowed: {e.reason}") from None
    except FileNotFoundError:
        raise  # the file to append to, or its folder, is not there: the input's fault
    except OSError as e:
        # The writer saves its first (empty) stage at once: a full disk there was exit 2, as bad input.
        _err(f"cannot write {checks.shown_path(output, False)}: {e.strerror or e} (no frame of this run was written)")
        return EXIT_WRITE_FAILED
    # From here the writer's working copies stand beside the output: whatever ends the command
    # before the run (a refused resume, an interrupt) must remove them, as the run's end does.
    try:
        if args.resume is not None and run_id is None and writer.file_run_id is not None:
            # A checkpoint of a run that named none, resumed onto a file a named run wrote since.
            raise ValueError(f"--resume = {checks.shown_path(args.resume)} is not allowed with {checks.shown_path(writer.path, False)}: the file holds the frames of "
                             f"another run (run id {writer.file_run_id!r}), written after the checkpoint's run")
        if args.resume is not None and (writer.last_frame is None or writer.first_frame != 0 or writer.last_frame < start_frame - 1):
            # The resumed frames must follow the file's: a file of a shorter run, written over the
            # one checkpointed, would keep a gap of frames nobody wrote.
            if writer.last_frame is None:
                held, gap = "no frames", f"0..{start_frame - 1}"
            else:
                held = f"frames {writer.first_frame}..{writer.last_frame}"
                gaps = []
                if writer.first_frame > 0:
                    gaps.append(f"0..{min(writer.first_frame, start_frame) - 1}")
                if writer.last_frame < start_frame - 1:
                    gaps.append(f"{max(writer.last_frame + 1, writer.first_frame)}..{start_frame - 1}")
                gap = " and ".join(gaps)
            raise ValueError(f"--resume = {checks.shown_path(args.resume)} is not allowed with {checks.shown_path(writer.path, False)}: the file holds {held} and the "
                             f"checkpoint is at frame {start_frame}; resuming would leave frames {gap} unwritten")
        # The whole output name: a.usdc and a.usda in one folder must not share a checkpoint.
        checkpoint_path = writer.path + ".checkpoint.npz"
        if args.resume is None:
            # The writer has just replaced the file an earlier run wrote there: that run's force log
            # stood beside this file until this run's was written. (Its checkpoint stays: a resume
            # of it onto this run's frames is refused by the run ids, and it resumes the earlier
            # run where that run's file is put back.)
            for stale in (writer.path + "_tools.csv", writer.path + "_tools.json"):
                if os.path.isfile(stale) or os.path.islink(stale):
                    os.remove(stale)
            # So are the frame files and picture this run is to write: a run that stopped early
            # (or was killed) left the earlier run's, of another length, beside its own file.
            if args.export:
                checks.remove_frame_files(f"{writer.path}_{args.export}", args.export)
            if args.preview and os.path.isfile(writer.path + ".png"):
                os.remove(writer.path + ".png")
        run_record = {"scene": args.scene if args.scene is not None else scene.name, "scale": scale, "fps": fps, "dt": dt,
                      "dt_stable": stable_step,
                      "frames": frames_total, "output": os.path.abspath(writer.path), "dtype": args.dtype,
                      "surface": bool(args.surface), "checkpoint_every": every, "fit": model.fit, "contact_ramp": model.contact_ramp,
                      "hourglass": model.hourglass, "fit_weight": model.fit_weight,
                      # What "fit" and "hourglass" resolved to (a resume reads only the requested ones),
                      # from the run's start: a resumed body that flowed keeps the incremental composition.
                      **solver.record(state)}
        if run_id is not None:  # (a checkpoint written before runs were named has none)
            run_record["run_id"] = run_id
        if args.scene is not None and os.path.exists(str(args.scene)):
            run_record["scene"] = os.path.abspath(args.scene)

        checkpointed = [start_frame if args.resume is not None else None]  # the frame the checkpoint file holds
        log_files = f"{writer.path}_tools.csv, .json"
        log_failed = [False]

        def write_log():
            # The whole output name, as for the checkpoint and preview: a.usdc and a.usda in one
            # folder must not share a force log.
            try:
                return log.write(writer.path)
            except OSError as e:
                log_failed[0] = True
                raise _BesideWriteError("the force log", log_files, e) from None

        def checkpoint(frame, current):
            if every is not None and frame > start_frame and frame % every == 0:
                # A Ctrl-C inside these writes waits for them (and then stops the run): one between
                # a working file's open() and its with block left the file to the garbage collector
                # ('unclosed file'), and the log and the checkpoint that resumes after its rows are
                # written together.
                with _Deferred(args, then_stop=True):
                    if log is not None:
                        # The rows up to this frame, before the checkpoint that resumes after them: the
                        # log was written only at the end, so a killed run's resume kept none of the rows
                        # before its checkpoint.
                        write_log()
                    # With the adaptive step the step count is not a function of the frame: -1.
                    try:
                        save_state(checkpoint_path, model, current, step=-1 if adaptive else frame * substeps,
                                   frame=frame, run=run_record)
                    except OSError as e:
                        raise _BesideWriteError("the checkpoint", checkpoint_path, e) from None
                    checkpointed[0] = frame

        def beside_failure(e) -> str:
            why = e.cause.strerror or str(e.cause)
            if e.what == "the checkpoint":
                # Not there (its folder removed; a resume from a copy elsewhere, before its first
                # save): it said 'it keeps frame N' of a file that did not exist.
                kept = checkpointed[0] is not None and os.path.isfile(checkpoint_path)
                held = f"it keeps frame {checkpointed[0]}" if kept else "no checkpoint of this run is left there"
            else:
                held = "it is left as it was"  # written by renaming over
            return f"cannot write {e.what} {e.path}: {why} ({held}; {writer.path} keeps {_kept(writer, start_frame)})"

        log_done = [False]
        log_unexpected = [False]  # the log's last write failed with an error of no kind expected
        tool_files = None

        def write_final_log():
            """The force log's last write, once (the interrupted run's line, or the cleanup step);
            the failure's line, or None. Called inside ``_Deferred``."""
            nonlocal tool_files
            if log_done[0]:
                return None
            log_done[0] = True
            # A resumed run that published no frame left its file as it was (the frames past the
            # checkpoint included): its log is left so too, not cut back to the checkpoint's rows.
            if log is not None and log.rows and not log_failed[0] and (args.resume is None or writer.frames_written):
                try:
                    tool_files = write_log()
                except _BesideWriteError as e:
                    # Said whatever ended the run (its own line stands); a finished run is not a
                    # success without its log (it was exit 2, 'bad input', naming no file).
                    return beside_failure(e)
                except Exception as e:  # noqa: BLE001 (an error of no kind expected: said as run says one, exit 1)
                    # A bug in the log's writer: a ValueError was exit 2, 'bad input', the rest a
                    # traceback, neither naming the log nor what the run's file keeps. The log
                    # is renamed over its name only once whole: it is left as it was.
                    log_failed[0] = log_unexpected[0] = True
                    return (f"cannot write the force log {log_files}: {type(e).__name__}: {e} (raised at {_raised_at(e)}; "
                            f"it is left as it was; {writer.path} keeps {_kept(writer, start_frame)})")
            return None

        def on_frame(frame, current):
            if log is not None:
                log.record(frame, current)
            checkpoint(frame, current)
            _safe_point(args)  # after the frame's rows and checkpoint: they go with the frame kept

        close_said = [False]

        def close_writer():
            """``writer.close()``; the line of its failure (its working copies not removed), once,
            or None. A close that raised left with its OSError, a stop's signal dropped (exit 2,
            the errno alone); a later close tries the clean-up again."""
            try:
                writer.close()
            except OSError as e:
                if close_said[0]:
                    return None
                close_said[0] = True
                return (f"cannot finish {writer.path}: {e.strerror or str(e)} (its working copies may be left beside it; "
                        f"it keeps {_kept(writer, start_frame)})")
            return None
    except BaseException:
        writer.close()
        raise
    seen = _signals_seen(args)
    final_log_error = [None]
    try:
        print(f"{PROG}: {scene.name}: {model.particle_count} particles, {len(model.bodies)} "
              f"{'body' if len(model.bodies) == 1 else 'bodies'}, "
              f"{checks.plural(frames, 'frame')} at {fps:g} fps, "
              + ("adaptive dt (CFL), at most " if adaptive else "")
              + f"dt = {dt_shown:.4g} s ({substeps} steps/frame), {args.device} {args.dtype} "
              f"-> {writer.path}" + (f" (resumed at frame {start_frame}, the run {frames_total} frames)" if start_frame else ""), flush=True)
        simulate(model, frames, fps=fps, dt=dt, writer=writer, progress=not args.no_progress, solver=solver,
                 state=state, start_frame=start_frame, callback=on_frame,
                 monitor_exempt=getattr(scene, "diverges", ()),
                 monitor_origin=model.state(requires_grad=False) if start_frame else None, _checked=checked,
                 _finer="a larger --scale, or a smaller spacing in a scene file")
    except KeyboardInterrupt:
        # Its working copies removed and its force log written before the line is built: a second
        # Ctrl-C here waits for them, and one after them ends the process at once (the log was
        # written only in the cleanup below, which that second one never reached).
        with _Deferred(args):
            close_error = close_writer()
            log_error = write_final_log()
        if close_error is None or not _held_signal_wins(args, seen, close_error):
            print(f"{PROG}: {_stopped(args)}: {writer.path} keeps {_kept(writer, start_frame)}", file=sys.stderr)
            if close_error is not None:
                _err(close_error)
        if log_error is not None:
            _err(log_error)
        _export_run(args, writer, start_frame, whole=False)
        return EXIT_INTERRUPTED
    except SimulationError as e:
        close_error = close_writer()
        # Its advice is Python's ('a smaller dt=', 'use dtype=float64'): the command has --dt and
        # --dtype, and neither with --resume.
        said = e.reason if e.advice and args.resume is not None else str(e)
        if e.advice and args.resume is None:
            f32 = args.dtype == "float32"
            # The fresh solver's counts are the run's; above the stable step simulate gave the plain advice.
            ours = {f"; {divergence_advice(model, solver.hourglass)}": divergence_advice(model, solver.hourglass, "--dt"),
                    f"; {divergence_advice(model, solver.hourglass, solver=solver)}":
                    divergence_advice(model, solver.hourglass, "--dt", solver),
                    f"; {far_mesh_advice(f32)}": far_mesh_advice(f32, "--dtype float64"),
                    TOO_FAST_ADVICE: _run_advice()[TOO_FAST_ADVICE][2:]}  # a tools.Scripted motion's (Python scenes)
            said = f"{e.reason}; {ours[e.advice]}" if e.advice in ours else str(e)
        _err(f"{said} ({writer.path} keeps {_kept(writer, start_frame)})")
        if close_error is not None:
            _err(close_error)
        status = _export_run(args, writer, start_frame, whole=False)
        return EXIT_DIVERGED if status in (0, EXIT_WRITE_FAILED) else status
    except OSError as e:
        # A full disk or a vanished folder mid-run: the file keeps the last published frame.
        close_writer()  # (failing, most likely as e did: e's line says what the file keeps)
        if isinstance(e, BrokenPipeError):  # stdout's reader left, not the output file (main)
            raise
        # The USD was written where the checkpoint or the force log failed: naming it sent the
        # reader to the wrong file. A signal held under that write (a checkpoint's) was dropped
        # with it, and the run exited 4 though it had been asked to stop.
        said = (beside_failure(e) if isinstance(e, _BesideWriteError) else
                f"cannot write {writer.path}: {e.strerror or str(e)} (it keeps {_kept(writer, start_frame)})")
        if _held_signal_wins(args, seen, said):
            return EXIT_INTERRUPTED
        _err(said)
        if isinstance(e, _BesideWriteError):  # the USD is whole to its last frame: its frame files too
            status = _export_run(args, writer, start_frame, whole=False)
            return EXIT_WRITE_FAILED if status in (0, EXIT_WRITE_FAILED) else status
        return EXIT_WRITE_FAILED
    except Exception as e:  # noqa: BLE001 (said as one line; a refusal before the first frame is raised as before)
        if not writer.frames_written:
            raise  # the start's checks: bad input, said by the caller
        # An error of no kind the run expects, once frames are written (a bug in a writer or the
        # solver): a traceback that said nothing of the file, or a ValueError called bad input.
        close_error = close_writer()
        _err(f"the run stopped in frame {writer.last_frame + 1}: {type(e).__name__}: {e} (raised at {_raised_at(e)}; "
             f"{writer.path} keeps {_kept(writer, start_frame)})")
        if close_error is not None:
            _err(close_error)
        status = _export_run(args, writer, start_frame, whole=False)
        return EXIT_UNEXPECTED if status in (0, EXIT_WRITE_FAILED) else status
    else:
        final_log_error[0] = False  # said below, after what the run's signals decide
    finally:
        # The force log holds every frame's rows only once this last write is done: a Ctrl-C
        # inside it (a second one, or one as the run ended) lost the whole log of a finished run.
        with _Deferred(args):
            for finish in (close_writer, write_final_log):
                error = finish()
                if error is None:
                    continue
                if final_log_error[0] is False:
                    final_log_error[0] = error
                else:
                    _err(error)
    if final_log_error[0]:
        # A signal held under the log's last write was dropped for exit 4.
        if _held_signal_wins(args, seen, final_log_error[0]):
            return EXIT_INTERRUPTED
        _err(final_log_error[0])
        return EXIT_UNEXPECTED if log_unexpected[0] else EXIT_WRITE_FAILED
    if log_failed[0]:
        return EXIT_WRITE_FAILED
    if getattr(getattr(args, "signals", None), "received", None):
        # Asked to stop while its last files were written, or where the signal could not be
        # raised (a finalizer): the run and its files are whole, but it is no success.
        print(f"{PROG}: {_stopped(args)}: {writer.path} keeps {_kept(writer, start_frame)}", file=sys.stderr)
        return EXIT_INTERRUPTED
    counts = solver.guard_counts()
    guards = ", ".join(f"{k}={v}" for k, v in counts.items())
    # The share the run's warning (simulate.SKIPPED_FIT_SHARE) is judged by, said also where it is small.
    particle_steps = model.particle_count * solver.step_count
    skipped = f"; deformation fit skipped in {100.0 * skipped_fits(counts) / max(particle_steps, 1):.3g} % of {particle_steps} particle-steps"
    coarse = coarse_bodies(model, solver.skipped_fits(), solver.step_count)
    if coarse:  # which bodies: the share is of them all
        skipped += f" (by body, of its own: {shown_bodies(coarse)})"
    per_frame = 1e3 * writer.save_seconds / max(writer.frames_written, 1)
    written = (f"{writer.frames_written} frames (0..{writer.last_frame})" if not start_frame else
               f"frames 0..{writer.last_frame} ({start_frame}..{writer.last_frame} by this run)")
    print(f"wrote {writer.path}: {written}, {model.particle_count} particles; USD save {per_frame:.2f} ms/frame")
    print(f"guard counts (particle-steps each guard held): {guards}{skipped}")
    if log is not None:
        print(f"reaction forces ({', '.join(_log_kinds(model))}): {tool_files[0]}, {tool_files[1]}")
    if args.surface:
        print(f"surfaces: {1e3 * writer.surface_seconds / max(writer.frames_written, 1):.0f} ms/frame (/World/Surfaces)")
    status = _export_run(args, writer, start_frame, whole=True)
    if status:
        return status
    if args.preview:
        from .render import render_usd  # noqa: PLC0415

        try:
            result = render_usd(writer.path, writer.path + ".png", frames="last")
        except KeyboardInterrupt:
            print(f"{PROG}: {_stopped(args)}: --preview: {writer.path}.png is not written; {writer.path} holds the whole "
                  "run", file=sys.stderr)
            return EXIT_INTERRUPTED
        except OSError as e:
            if isinstance(e, BrokenPipeError):
                raise
            # A full disk under the picture of a finished run: exit 2, 'bad input', before.
            _err(f"--preview: cannot write {e.filename or writer.path + '.png'}: {e.strerror or e}; {writer.path} holds "
                 "the whole run")
            return EXIT_WRITE_FAILED
        shown = "surfaces" if result.surface_bodies else "particles"
        print(f"preview: {result.output} ({shown}, {result.seconds:.1f} s)")
    return 0


def _raised_at(e: BaseException) -> str:
    """Where ``e`` was raised, ``file.py:LINE`` (its innermost frame): the line to report a bug with."""
    where = e.__traceback__
    while where.tb_next is not None:
        where = where.tb_next
    return f"{os.path.basename(where.tb_frame.f_code.co_filename)}:{where.tb_lineno}"


def _stopped_writing(what: str, e: BaseException) -> str | None:
    """The one line of an error of no kind ``what`` (``export``, ``render``) expects, raised once
    it began writing (``checks.stopped_writing`` records what its files keep), or None: a write
    that failed (an ``OSError``), an interrupt and a damaged input file (a reader's error, or the
    refusal of a frame by the file's reader, ``usd.py``) are said as before."""
    kept = getattr(e, "kept", None)
    if kept is None or not isinstance(e, Exception) or isinstance(e, OSError) or _is_read_error(e):
        return None
    if isinstance(e, ValueError) and _raised_at(e).startswith("usd.py:"):
        return None  # 'cannot read a.usdc: frame 3 has no particle with a finite position': the input's
    frame = getattr(e, "stopped_frame", None)
    at = f" in frame {frame}" if frame is not None else ""
    return f"the {what} stopped{at}: {type(e).__name__}: {e} (raised at {_raised_at(e)}; {kept})"


def _export_run(args, writer, start_frame: int, whole: bool) -> int:
    """``run --export``: every frame the output holds into ``<output>_<fmt>/``, once the run has
    ended, also where it stopped early (``whole`` False: interrupted, diverged), so that the frame
    files hold the frames the file keeps, no more and none of an earlier run. Returns 0, or the
    status of an export that could not be written (4) or was interrupted (130, 143), its line said."""
    if not args.export or writer.last_frame is None or not os.path.isfile(writer.path):
        return 0
    from . import checks  # noqa: PLC0415
    from .export import ExportWriteError, export_frames  # noqa: PLC0415

    # The whole output name, as the checkpoint's: a.usdc and a.usda in one folder must
    # not share (and overwrite) one folder or picture.
    folder = f"{writer.path}_{args.export}"
    held = "holds the whole run" if whole else f"keeps {_kept(writer, start_frame)}"
    try:
        files = export_frames(writer.path, args.export, folder)
    except ExportWriteError as e:
        _err(f"--export {args.export}: {e}; {writer.path} {held}")
        return EXIT_WRITE_FAILED
    except (ValueError, OSError) as e:
        if whole:
            raise
        # After a run that stopped (the file removed meanwhile): said, and the stop's status kept.
        _err(f"--export {args.export}: {e}; {writer.path} {held}")
        return EXIT_WRITE_FAILED
    except KeyboardInterrupt as e:
        # The run's file is as said: the line said 'interrupted' alone, as if it were not.
        kept = f"{e.kept}; " if getattr(e, "kept", None) else ""
        print(f"{PROG}: {_stopped(args)}: --export {args.export}: {kept}{writer.path} {held}", file=sys.stderr)
        return EXIT_INTERRUPTED  # (main makes it 143 after a SIGTERM)
    # A resumed run's file may end before frames an earlier export of it wrote.
    checks.remove_frame_files(folder, args.export, keep=files)
    print(f"exported {checks.plural(len(files), 'file')} to {folder}")
    return 0


class _BesideWriteError(OSError):
    """A file the run writes beside its USD (``what``: the checkpoint, the force log) that could
    not be written (``cause``: the write's own error)."""

    def __init__(self, what: str, path: str, cause: OSError):
        super().__init__(cause.errno, cause.strerror or str(cause))
        self.what, self.path, self.cause = what, path, cause

    def __reduce__(self):
        # As checks.Rebuilt's, not its base: this module starts without Warp, which checks imports.
        from .checks import _rebuilt  # noqa: PLC0415

        return _rebuilt, (type(self), self.args), self.__dict__


def _log_kinds(model) -> list[str]:
    kinds = [] if model.tools is None else ["tool poses"]
    return kinds + (["static colliders"] if model.planes or model.spheres or model.boxes else [])


def _moved_with(checkpoint, recorded: str, *, output: bool = False) -> str:
    """A file a checkpoint's run record names by its absolute path (the output, a scene
    file), or the file of its name beside the checkpoint: the folder was moved or copied
    whole (it said 'cannot append to /old/folder/a.usdc: no such file').

    The output (``output``) is the one beside the checkpoint whenever it is there, as the
    run wrote its checkpoint beside its output: the resume of a copied folder appended to
    the original's file and rewrote its checkpoint and force log, the copy left as it was.
    A scene file is only read (its fingerprint checked), so its recorded path stands while
    it exists. The run ids and the scene's fingerprint still refuse a file of another run."""
    if not os.path.isabs(recorded):
        return recorded  # (a built-in scene's name is no path)
    if os.path.exists(recorded) and not output:
        return recorded
    beside = os.path.join(os.path.dirname(os.path.abspath(checkpoint)), os.path.basename(recorded))
    return beside if os.path.isfile(beside) else recorded


def _check_run_record(path, run: dict) -> None:
    """The run record of a checkpoint holds what ``_cmd_run`` wrote there (a foreign or
    hand-edited file must fail here, by name, not as a TypeError later)."""
    from . import checks  # noqa: PLC0415

    where = f"--resume = {checks.shown_path(path)} is not allowed: in its run record,"
    try:
        if not isinstance(run["scene"], str) or not isinstance(run["output"], str):
            raise ValueError("scene and output must be text")
        checks.positive("scale", run["scale"])
        checks.positive("fps", run["fps"])
        if run["dt"] != "auto":  # an adaptive (CFL) run records its dt as "auto"
            checks.positive("dt", run["dt"])
        checks.positive_int("frames", run["frames"])
        checks.choice("dtype", run["dtype"], ("float32", "float64"))
        checks.boolean("surface", run.get("surface", False))
        checks.boolean("dt_stable", run.get("dt_stable", False))
        if run.get("checkpoint_every") is not None:
            checks.positive_int("checkpoint_every", run["checkpoint_every"])
        if "fit" in run:
            from .model import FITS  # noqa: PLC0415

            checks.choice("fit", run["fit"], FITS)
        if "contact_ramp" in run:
            from .model import check_contact_ramp  # noqa: PLC0415

            check_contact_ramp("contact_ramp", run["contact_ramp"])
        if run.get("hourglass") is not None:  # None: by the fit (Model.solver_choice)
            checks.hourglass("hourglass", run["hourglass"])
        if "fit_weight" in run:
            from .sim.smoothing import FIT_WEIGHTS  # noqa: PLC0415

            checks.choice("fit_weight", run["fit_weight"], FIT_WEIGHTS)
        if "run_id" in run and (not isinstance(run["run_id"], str) or not run["run_id"]):
            raise ValueError(f"run_id = {run['run_id']!r} must be a non-empty text")
    except ValueError as e:
        raise ValueError(f"{where} {e}") from None


def add_fit_arguments(parser):
    """Declare the ``warp-esph fit`` options on an ``argparse`` (sub)parser."""
    from .losses import ChamferLoss, MeshLoss  # noqa: PLC0415 (Warp is imported only when the parser is built)
    from .rollout import PARAMETERS  # noqa: PLC0415

    parser.add_argument("scene", metavar="SCENE", help="built-in scene name or .toml scene file (the initial guess)")
    parser.add_argument("--target", required=True, action="append", metavar="FILE",
                        help="target: a previous run's .usd (see --target-body), .npz/.npy positions per frame, a point "
                             "cloud (.xyz/.ply/.npy (M, 3) ...), a mesh file, or masks with --cameras; repeatable (their "
                             "losses add up)")
    parser.add_argument("--params", default="yield_stress,flow_rate", metavar="A,B",
                        help=f"comma-separated parameters to fit, of {','.join(PARAMETERS)} (default yield_stress,flow_rate)")
    parser.add_argument("--material", action="append", metavar="BODY",
                        help="fit only this body's material (name or material index); repeatable; default all")
    parser.add_argument("--iterations", type=int, default=50, metavar="N",
                        help="evaluations of each start after its first, line-search trials (gauss-newton: Jacobian "
                             "runs) included; --samples' runs not counted (default 50, at most 100000)")
    parser.add_argument("--lr", type=float, metavar="LR",
                        help="Adam step size, relative (times --param-scales' size for a parameter fitted from 0 or "
                             "below); L-BFGS: its first step (default 0.1, at most 10; "
                             "not with gauss-newton)")
    parser.add_argument("--bounds", action="append", default=[], metavar="NAME=LO:HI", help="bounds of a parameter; repeatable")
    parser.add_argument("--param-scales", action="append", default=[], metavar="NAME=S",
                        help="the size of a parameter fitted as itself (from 0 or below: lam, hardening, "
                             "pressure_stiffness, viscosity), in its units: a step of --lr moves it by LR times S "
                             "(default: its start's magnitude; from 0, its --bounds' width, else its materials'); "
                             "repeatable")
    parser.add_argument("--clip", type=float, metavar="C", help="Adam only: clip the gradient norm (log space) to C")
    parser.add_argument("--target-frames", action="append", metavar="F,G",
                        help="a run's USD: the frames to fit ('2,4,6', '10:60:10', 'last'; default all after the first); "
                             ".npz with 'frames': which of them; .npy (.npz without 'frames'): the frame of each entry "
                             "('1,2,3', '1:3'; default 0 to K-1); a cloud, mesh or mask: the frame it "
                             "shows (default: the last); once per --target or once for all")
    parser.add_argument("--frames", type=int, metavar="N", help="frames to simulate (default: the last target frame or the scene's)")
    parser.add_argument("--fps", type=float, metavar="F", help="frames per second (default: the target's or the scene's; a force log's times must give it)")
    # The command picks the stiffest start's step where it picks one (calibrate.run_fit): the
    # help said 'the stable step', which a reader took for the guess's.
    parser.add_argument("--dt", type=float, metavar="DT",
                        help="time step in s (default: the scene's dt, else the stable step, rounded to fill a frame; "
                             "with --samples or --starts K > 1, that of the stiffest point they start from, the guess "
                             "included, for every start)")
    parser.add_argument("--scale", type=float, default=1.0, metavar="S", help="resolution scale of the scene (default 1)")
    parser.add_argument("--radius", type=float, metavar="R", help="Chamfer search radius for point-cloud targets (default 3 spacings)")
    parser.add_argument("--mesh-mode", choices=MeshLoss.MODES,
                        help="mesh targets: surface (default) or outside")
    parser.add_argument("--cloud-coverage", choices=ChamferLoss.COVERAGES, action="append",
                        help="point-cloud targets: full (default: the cloud shows the whole body, compared both ways) "
                             "or partial (a scan of part of it: each scanned point to its nearest particle only, the "
                             "unseen side free); once per --target (in order; partial only for a cloud) or once for all")
    parser.add_argument("--cloud-offset", type=_cloud_offset, metavar="M|surface",
                        help="point-cloud targets: how far outside the particles' centres the scanned points lie, in "
                             "m (default 0: the cloud is of centres, as a run's own output is); 'surface' for a scan "
                             "of the material's surface: half a spacing")
    parser.add_argument("--checkpoint-every", type=_checkpoint_every, metavar="S|auto",
                        help="checkpoint the rollout every S steps (less memory, one more forward pass); default auto: "
                             "sized from the memory estimate and --memory-limit")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float64", help="precision (default float64)")
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu", help="Warp device (default cpu)")
    parser.add_argument("-o", "--output", metavar="OUT.json", help="the fit's JSON file (default: fit.json in --output-dir)")
    parser.add_argument("--no-usd", action="store_true", help="do not write the fitted run to USD")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    _add_solver_arguments(parser)
    from .calibrate import add_calibration_arguments  # noqa: PLC0415

    add_calibration_arguments(parser)
    return parser


def _cloud_offset(text):
    if str(text).strip().lower() == "surface":
        return "surface"
    from .checks import read_number  # noqa: PLC0415

    try:
        value = read_number(text)  # 1e-400 (0.0) refused by name in _Parser._get_value
    except ValueError:
        value = None
    if value is None or not (value >= 0.0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"{_typed(text)!r} is not allowed: must be a distance in m (>= 0) or 'surface' "
                                         "(half a spacing)")
    return value


def _checkpoint_every(text):
    if str(text).strip().lower() == "auto":
        return "auto"
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{_typed(text)!r} is not allowed: must be a whole number of steps or 'auto'") from None


def _parse_bounds(items) -> dict:
    from .checks import read_number, shorten, unheld_refusal  # noqa: PLC0415

    out = {}
    for item in items or []:
        try:
            name, rng = item.split("=", 1)
            lo, hi = rng.split(":", 1)
            lo, hi, name = read_number(lo), read_number(hi), name.strip()
            if not name:
                raise ValueError
        except ValueError:
            raise ValueError(f"--bounds {_typed(item)!r} is not allowed: use NAME=LO:HI, e.g. flow_rate=1:1000") from None
        for end in (lo, hi):
            # 1e-400 was taken as the bound 0, 1e400 as inf, an open end.
            why = unheld_refusal(end, zero="write 0 where 0 is meant", inf="write inf or -inf for an open end")
            if why:
                raise ValueError(f"--bounds {_typed(item)!r} is not allowed: {shorten(end)}: {why}")
        if name in out:
            # The last one silently won.
            raise ValueError(f"--bounds {_typed(item)!r} is not allowed: {name} already has bounds {out[name][0]:g}:{out[name][1]:g}; "
                             "give one range per parameter")
        out[name] = (lo, hi)
    return out


def _parse_param_scales(items) -> dict:
    out = {}
    for item in items or []:
        try:
            name, size = item.split("=", 1)
            size, name = float(size), name.strip()
            if not name:
                raise ValueError
        except ValueError:
            raise ValueError(f"--param-scales {_typed(item)!r} is not allowed: use NAME=S, e.g. hardening=1e4") from None
        if not (math.isfinite(size) and size > 0.0):
            # A step of lr moves the value by lr times the size: 0, a negative or a NaN moves it nowhere or backwards.
            raise ValueError(f"--param-scales {_typed(item)!r} is not allowed: the size must be > 0 and finite (a step of --lr moves "
                             "the parameter by LR times it)")
        if name in out:
            raise ValueError(f"--param-scales {_typed(item)!r} is not allowed: {name} already has size {out[name]:g}; give one "
                             "size per parameter")
        out[name] = size
    return out


def fit_cli(args, out=None) -> int:
    """Run ``warp-esph fit`` from parsed ``args`` (see ``add_fit_arguments``); returns 0, or
    ``EXIT_NOT_CONVERGED`` for a fit that stopped without converging (its results written).

    The work is ``warp_esph.calibrate.run_fit``: it prints the memory and time estimates,
    fits, says whether the fit converged, stalled or hit the iteration cap, prints the
    diagnostics and writes ``fit.json``, ``history.csv``, ``loss.png``, ``params.png`` and
    ``fitted.usdc`` into ``--output-dir``. Raises ``ValueError``/``OSError`` on bad input
    (the CLI maps them to exit status 2).
    """
    from .calibrate import run_fit  # noqa: PLC0415

    return run_fit(args, out=out)


def _cmd_render(args) -> int:
    from . import checks  # noqa: PLC0415
    from .render import render_usd  # noqa: PLC0415

    checks.positive_int("--width", args.width)
    checks.positive_int("--height", args.height)
    if args.columns is not None:
        checks.positive_int("--columns", args.columns)
    def show(k, n):
        print(f"\r{PROG}: rendered {k}/{n} frames", end="" if k < n else "\n", file=sys.stderr, flush=True)

    progress = show if sys.stderr.isatty() else None
    _arm(args)
    try:
        result = render_usd(
            args.usd, args.output, args.frames, color=args.color, width=args.width, height=args.height,
            supersample=args.supersample, radius_scale=args.radius_scale, azimuth=args.azimuth, elevation=args.elevation,
            zoom=args.zoom, label=not args.no_label, shadows=not args.no_shadows, columns=args.columns, fps=args.fps,
            fit=args.fit, surfaces=not args.particles, progress=progress, flag=option_flag, clear=True,
        )
    except Exception as e:  # noqa: BLE001 (one line for an error of no kind expected mid-way; the rest raised as before)
        said = _stopped_writing("render", e)
        if said is None:
            raise
        _err(said)
        return EXIT_UNEXPECTED
    # (checks.plural: '1 PNG files', '(1 frames)', '(1 bodies as surfaces)' read wrong)
    what = {"dir": f"{checks.plural(len(result.files), 'PNG file')} in {result.output}", "png": result.output,
            "gif": f"{result.output} ({checks.plural(len(result.frames), 'frame')})",
            "mp4": f"{result.output} ({checks.plural(len(result.frames), 'frame')})"}
    bodies = "1 body" if result.surface_bodies == 1 else f"{result.surface_bodies} bodies"
    drawn = f"{result.particles} particles" + (f" ({bodies} as surfaces)" if result.surface_bodies else "")
    size = f"{args.width}x{args.height}"
    if result.kind == "png" and len(result.frames) > 1:  # it said 64x48 of a 256 x 96 sheet
        size = f"a sheet of {len(result.frames)} frames of {size}"
    print(f"wrote {what[result.kind]}: {size}, {drawn}, "
          f"{result.seconds:.1f} s ({result.seconds_per_frame:.2f} s/frame)")
    return 0


def _cmd_export(args) -> int:
    from .export import export_frames  # noqa: PLC0415

    from . import checks  # noqa: PLC0415

    folder = args.output if args.output is not None else f"{os.path.abspath(args.usd)}_{args.format}"
    checks.output_place("--output", folder, folder=True)
    _arm(args)
    try:
        files = export_frames(args.usd, args.format, folder, frames=args.frames, flag=option_flag, clear=True)
    except Exception as e:  # noqa: BLE001 (one line for an error of no kind expected mid-way; the rest raised as before)
        said = _stopped_writing("export", e)
        if said is None:
            raise
        _err(said)
        return EXIT_UNEXPECTED
    frames = len(files) - (1 if args.format == "vtu" else 0)
    extra = " and frames.pvd (open it in ParaView)" if args.format == "vtu" else ""
    print(f"wrote {checks.plural(frames, '.' + args.format + ' file')}{extra} to {folder}")
    return 0


class _Signals:
    """Ctrl-C (SIGINT) and SIGTERM, from the first moment of the process to the last.

    Disarmed (start-up: parsing, importing Warp and pxr, building the scene; and after the
    command): nothing is open that needs closing, so the handler prints one line and ends
    the process at once with 130 (143 for SIGTERM). A ``KeyboardInterrupt`` there would
    print a traceback from whatever module was importing, or be swallowed by native code
    that clears Python errors (it was, once, while pxr imported). Armed (``arm()``: an
    output is being written): the handler raises ``KeyboardInterrupt``, which unwinds
    through the writer, so the file keeps every finished frame; a further signal, outside a
    write that must finish (``holding``), ends the process at once, as when disarmed.
    """

    def __init__(self, exit_at_once: bool = True):
        #: False for ``main`` called inside someone else's Python process: never end it
        #: with ``os._exit``, raise ``KeyboardInterrupt`` throughout.
        self.exit_at_once = exit_at_once
        self.armed = False
        #: Set while files are written that a signal must not cut short (``_Deferred``): the
        #: signal is recorded in ``received`` and acted on by the command once they are whole.
        self.holding = False
        #: Set once a signal has been raised as ``KeyboardInterrupt``: the command is stopping.
        self.raised = False
        #: A signal that landed in a finalizer, where it cannot be raised: ``at_safe_point``
        #: raises it at the next one (a run's frame, a fit's evaluation, a sweep's sample).
        self.pending = False
        self.received: list[int] = []
        self.previous = {}
        #: A copy of the process's standard error taken at install: start-up sends descriptor 2
        #: to a temporary file while Warp and pxr print their native notes
        #: (``startup.init_warp``, ``usd._native_stderr``), and the one line must not land there.
        self.stderr_fd: int | None = None

    def install(self) -> "_Signals":
        try:
            self.stderr_fd = os.dup(2)
        except OSError:  # no descriptor 2 (some embedded interpreters)
            self.stderr_fd = None
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                if signal.getsignal(sig) is signal.SIG_IGN:
                    continue  # started ignoring it (a background job of a script): keep ignoring
                self.previous[sig] = signal.signal(sig, self._handle)
            except ValueError:  # not the main thread: leave the process's handlers alone
                pass
        return self

    def restore(self):
        for sig, handler in self.previous.items():
            signal.signal(sig, handler if handler is not None else signal.SIG_DFL)
        self.previous = {}
        if self.stderr_fd is not None:
            os.close(self.stderr_fd)
            self.stderr_fd = None

    def arm(self):
        self.armed = True

    def disarm(self):
        self.armed = False

    def _handle(self, signum, frame):
        self.received.append(signum)
        if self.holding:
            return
        if self.armed or not self.exit_at_once:
            # Raised once: raising it again while the first unwinds cut the writers' cleanup
            # short. A further one ends the process at once, except inside a write that must
            # finish (``holding``), where it is recorded: ignored, it left a fit writing its
            # pictures or a sweep waiting on its workers to SIGKILL. The files finished
            # are whole (each is written beside and renamed over). In someone else's process
            # (``exit_at_once`` False) it is only recorded. And never inside a finalizer, where
            # Python prints it as 'Exception ignored in ... __del__' with a traceback and drops
            # it: it is kept pending, and raised at the command's next safe point
            # (``at_safe_point``); it was only reported when the whole command ended, a long run
            # going on to its last frame.
            if self.raised:
                if self.exit_at_once:
                    _exit_now(signum, self.stderr_fd)
                return
            if frame is not None and frame.f_code.co_name == "__del__":
                self.pending = True
                return
            self.raised = True
            raise KeyboardInterrupt
        _exit_now(signum, self.stderr_fd)

    def at_safe_point(self):
        """Act on a signal left pending (it landed in a finalizer): raise it as the handler
        would have, here, between two pieces of work."""
        if not self.pending or self.holding:
            return
        self.pending = False
        if self.raised:
            return
        if self.armed or not self.exit_at_once:
            self.raised = True
            raise KeyboardInterrupt
        _exit_now(self.received[-1], self.stderr_fd)


def _safe_point(args) -> None:
    """Where the command may stop between two pieces of work (``_Signals.at_safe_point``)."""
    signals = getattr(args, "signals", None)
    if signals is not None:
        signals.at_safe_point()


class _Deferred:
    """``with _Deferred(args):`` a Ctrl-C or SIGTERM inside is recorded in ``signals.received``,
    not raised. ``then_stop``: one received inside is acted on as the block ends (as the
    handler would have), for files written mid-run, after which the run must not go on."""

    def __init__(self, args, *, then_stop: bool = False):
        self.signals = getattr(args, "signals", None)
        self.then_stop = then_stop

    def __enter__(self) -> "_Deferred":
        if self.signals is not None:
            self._was, self.signals.holding = self.signals.holding, True
            self._seen = len(self.signals.received)
        return self

    def __exit__(self, exc_type, *exc) -> None:
        signals = self.signals
        if signals is None:
            return
        signals.holding = self._was
        if self.then_stop and exc_type is None and not self._was and len(signals.received) > self._seen:
            if signals.armed or not signals.exit_at_once:
                if not signals.raised:
                    signals.raised = True
                    raise KeyboardInterrupt
            else:
                _exit_now(signals.received[-1], signals.stderr_fd)


def _exit_now(signum, stderr_fd: int | None = None) -> None:
    """One line on ``stderr_fd`` (default: descriptor 2), then leave at once (no cleanup
    runs, and none is needed)."""
    try:
        sys.stdout.flush()
    except Exception:  # noqa: BLE001 (a reentrant flush in a signal handler)
        pass
    what = "terminated" if signum == signal.SIGTERM else "interrupted"
    try:
        os.write(2 if stderr_fd is None else stderr_fd, f"{PROG}: {what}\n".encode())
    except OSError:  # stderr's reader has left: the status still tells
        pass
    os._exit(EXIT_TERMINATED if signum == signal.SIGTERM else EXIT_INTERRUPTED)


def console_main() -> NoReturn:
    """The ``warp-esph`` console script and ``python -m warp_esph``: ``main`` with the
    signal handlers kept until the process ends, which it does at once with the command's
    status (``_leave``): no interpreter shutdown follows the work."""
    if sys.stderr is None:
        # Started with descriptor 2 closed (2>&-, some service managers): Python leaves
        # sys.stderr None, and the first progress bar or note raised AttributeError (exit 1,
        # the run not run). Nobody reads it; the exit status still tells.
        sys.stderr = open(os.devnull, "w")  # noqa: SIM115 (for the life of the process)
    from .startup import unread_stream  # noqa: PLC0415 (light: no Warp)

    # Its reader may leave mid-run (2> >(head -c 1)): the notes and lines after that are
    # dropped, and the work goes on to its own status.
    sys.stderr = unread_stream(sys.stderr)
    status = main(restore_signals=False)
    if status == EXIT_PIPE_CLOSED:
        _drop_stdout()  # the flush at exit would fail on the closed pipe again
    _leave(status)


def _leave(status: int) -> NoReturn:
    """End the process with ``status`` once the command's work is done: the exit functions
    run (logging, coverage), the standard streams are flushed, and then ``os._exit``.

    Python's own shutdown resets the signal handlers to the default action before it
    tears the modules down (a quarter of a second after a run, with Warp and pxr loaded):
    a Ctrl-C there killed a finished run's process by the signal (status -2, no line),
    whatever the command had decided. Up to ``os._exit`` the command's handler stands, and
    only records a signal (``main`` left it holding): the command's status is the exit's.
    """
    import atexit  # noqa: PLC0415

    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError, AttributeError):
            # stdout's reader left after the last line was given to it: as a command whose
            # reader left mid-output (main), not a success; Python exited 120 here.
            if stream is sys.stdout and status == 0:
                status = EXIT_PIPE_CLOSED
    try:
        # The C library's buffers too (native notes of Warp or pxr to a redirected stdout, held
        # whole until exit()): os._exit does not flush them, and they were lost.
        import ctypes  # noqa: PLC0415

        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError, TypeError):  # no C library to load by name (some platforms)
        pass
    os._exit(status)


def main(argv=None, *, restore_signals: bool = True) -> int:
    """Entry point; returns the exit status (see the module docstring).

    The signal handlers (``_Signals``) are installed first of all; ``restore_signals``
    (the default, for callers in a Python process) puts the previous ones back on return
    and never ends the caller's process: an interrupt there is a ``KeyboardInterrupt``.
    """
    signals = _Signals(exit_at_once=not restore_signals).install()
    try:
        parser = _build_parser()
        try:
            args = parser.parse_args(argv)
        except _UsageError as e:
            _err(e)
            return EXIT_BAD_INPUT
        if args.command is None:
            _err(f"a command is required: one of {', '.join(parser.commands)} (warp-esph --help for each)")
            return EXIT_BAD_INPUT
        args.signals = signals
        try:
            status = _dispatch(args)
        finally:
            signals.disarm()
        if status in (0, EXIT_NOT_CONVERGED) and signals.received:
            # A signal the handler could not raise (it landed in a finalizer): the work is done,
            # but the command was asked to stop, and that is no success. A fit that stopped
            # short finished too: its 5 had hidden the signal (a SIGTERM exited 5, not 143).
            print(f"{PROG}: {_stopped(args)}", file=sys.stderr)
            status = EXIT_INTERRUPTED
        if status == EXIT_INTERRUPTED and signal.SIGTERM in signals.received:
            return EXIT_TERMINATED
        return status
    finally:
        if restore_signals:
            signals.restore()
        else:
            # The process ends in ``_leave`` with this status: a signal from here on is recorded,
            # not acted on (it made a finished command exit 130 'interrupted' as the exit
            # functions ran).
            signals.holding = True


def _dispatch(args) -> int:
    import numpy as np  # noqa: PLC0415

    # numpy's floating-point notes ('overflow encountered in scalar divide') came before the
    # one error line of an extreme input that the checks then refuse by name; the physics is
    # in Warp's kernels, whose results the checks and the divergence monitor judge.
    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("default")
        warnings.showwarning = _show_warning
        try:
            if args.command == "scenes":
                return _cmd_scenes()
            if args.command == "render":
                return _cmd_render(args)
            if args.command == "export":
                return _cmd_export(args)
            if args.command == "sweep":
                from .sweep import sweep_cli  # noqa: PLC0415

                return sweep_cli(args)
            if args.command == "fit":
                _init_warp(args.device)
                _arm(args)
                return fit_cli(args)
            return _cmd_run(args)
        except KeyboardInterrupt as e:
            kept = getattr(e, "kept", None)  # checks.interrupted: what the files written keep
            print(f"{PROG}: {_stopped(args)}" + (f": {kept}" if kept else ""), file=sys.stderr)
            return EXIT_INTERRUPTED
        except BrokenPipeError as e:
            if not _stdout_closed():
                # Another pipe (ffmpeg's, a worker's): an error like any other write's.
                _err(e)
                return EXIT_BAD_INPUT
            # The reader of the output left (`warp-esph scenes | head -1`): not bad input, and
            # nothing to tell a pipe that is gone. Not 0 either: a run may have stopped here.
            return EXIT_PIPE_CLOSED
        except (ValueError, OSError) as e:
            from .checks import OutputWriteError  # noqa: PLC0415

            if isinstance(e, OutputWriteError):
                # A full disk mid-export or under a fit's results is a failed write, as run's
                # (exit 4), not bad input.
                _err(e)
                return EXIT_WRITE_FAILED
            # UnicodeDecodeError is a ValueError: a reader met bytes that are not text.
            _err(_read_failure(args, e) if _is_read_error(e) else e)
            return EXIT_BAD_INPUT
        except FloatingPointError as e:
            # A fit whose initial guess's rollout blew up or whose loss is not finite there.
            _err(e)
            return EXIT_DIVERGED
        except RuntimeError as e:
            from .simulate import SimulationError  # noqa: PLC0415

            if isinstance(e, SimulationError):
                _err(e)
                return EXIT_DIVERGED
            if _is_allocation_failure(e):
                _err(_out_of_memory(args, e))
                return EXIT_BAD_INPUT
            if not _is_read_error(e):
                raise
            _err(_read_failure(args, e))
            return EXIT_BAD_INPUT
        except MemoryError as e:
            _err(_out_of_memory(args, e))
            return EXIT_BAD_INPUT
        except Exception as e:  # noqa: BLE001 (only a damaged input file is turned into one line)
            if not _is_read_error(e):
                raise
            _err(_read_failure(args, e))
            return EXIT_BAD_INPUT


def _is_allocation_failure(exc: BaseException) -> bool:
    """Whether ``exc`` is Warp's refusal of an allocation its device could not make (a
    ``RuntimeError``: 'Failed to allocate N bytes on device ...')."""
    return isinstance(exc, RuntimeError) and str(exc).startswith("Failed to allocate ")


def _out_of_memory(args, exc: BaseException) -> str:
    """The one line of an allocation that failed before any output was written: a model, a
    rollout or a picture that the estimates let through (they weigh the machine's memory, a
    container's or the process's limit, not what other processes hold, nor this one's own
    libraries) raised a traceback (Warp's RuntimeError, numpy's MemoryError)."""
    from .checks import shorten_text  # noqa: PLC0415

    said = shorten_text(str(exc)) or type(exc).__name__
    less = ("a smaller --width, --height or --supersample, or fewer frames" if args.command == "render" else
            "fewer frames" if args.command == "export" else "a smaller --scale (a larger spacing) or smaller bodies")
    return (f"out of memory: {said}; the command needs more memory than this machine (or the process's limit) gives it "
            f"now: use {less}, or close other programs")


def _is_read_error(exc: BaseException) -> bool:
    from .checks import is_read_error  # noqa: PLC0415

    return is_read_error(exc)


def _read_failure(args, exc: BaseException) -> str:
    """'cannot read <file>: <reason>' for an input file a library could not read (a pxr
    error names no file: it is the USD input of the command)."""
    from .checks import read_reason, shown_path  # noqa: PLC0415

    pxr = type(exc).__module__.split(".")[0] == "pxr"
    if args.command in ("render", "export"):
        files = [args.usd]
    elif args.command == "run":
        files = [args.output] if pxr and args.output else [args.resume or args.scene]
    else:
        # fit's --target is repeatable (a list): one is named, several are listed.
        targets = getattr(args, "target", None) or []
        targets = [targets] if isinstance(targets, str) else list(targets)
        files = [", ".join(map(str, targets)) if targets and not pxr else None, getattr(args, "scene", None)]
    name = next((f for f in files if f), None)
    where = f" {shown_path(str(name))}" if name else ""
    return f"cannot read{where}: {read_reason(exc)} (a damaged or foreign file?)"


if __name__ == "__main__":
    sys.exit(console_main())
