"""Command line: ``warp-esph run [SCENE] ...`` and ``warp-esph scenes``.

Exit status: 0 success; 2 bad input (unknown scene, bad option value, bad scene file,
unreadable or unwritable file); 3 the simulation diverged (``SimulationError``; the
output keeps every frame finished before); 130 interrupted (Ctrl-C; the output keeps
every finished frame). Errors are one line on stderr, ``warp-esph: error: ...``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import warnings

PROG = "warp-esph"
EXIT_BAD_INPUT = 2
EXIT_DIVERGED = 3
EXIT_INTERRUPTED = 130


class _UsageError(Exception):
    pass


class _Parser(argparse.ArgumentParser):
    """argparse that reports a usage error as one line and lets ``main`` exit 2."""

    def error(self, message):
        raise _UsageError(message)


def _one_line(text) -> str:
    return " ".join(str(text).split())


def _err(message) -> None:
    print(f"{PROG}: error: {_one_line(message)}", file=sys.stderr)


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
    run.add_argument("--dt", type=float, metavar="DT", help="time step in s; must divide 1/fps (default: the stable step)")
    run.add_argument("--scale", type=float, default=1.0, metavar="S",
                     help="resolution scale: spacing / S, particle count ~ S^3 (default 1)")
    run.add_argument("--device", choices=("cpu", "cuda"), default="cpu", help="Warp device (default cpu)")
    run.add_argument("--dtype", choices=("float32", "float64"), default="float32", help="precision (default float32)")
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    sub.add_parser("scenes", help="list the built-in scenes", description="List the built-in scenes.")
    return p


def _init_warp(device: str) -> None:
    """Initialise Warp without its banner; keep its native stderr notes off the terminal.

    Warp prints a note on stderr from native code when no CUDA driver is found; for a
    CPU run that note is noise, for a CUDA run the failure is reported as an error.
    """
    import warp as wp  # noqa: PLC0415

    wp.config.log_level = wp.LOG_WARNING
    from warp._src import context  # noqa: PLC0415

    if getattr(context, "runtime", None) is not None:
        return
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except OSError:
        wp.init()
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        tmp.seek(0)
        notes = tmp.read().decode(errors="replace").splitlines()
    for note in notes:
        if note.strip() and (device != "cpu" or "CUDA" not in note):
            print(f"{PROG}: warning: {_one_line(note)}", file=sys.stderr)


def _cmd_scenes() -> int:
    from .scenes import DEFAULT_SCENE, scene_descriptions  # noqa: PLC0415

    descriptions = scene_descriptions()
    width = max(len(n) for n in descriptions)
    for name, text in descriptions.items():
        mark = " (default)" if name == DEFAULT_SCENE else ""
        print(f"{name:<{width}}  {text}{mark}")
    return 0


def _cmd_run(args) -> int:
    from . import checks  # noqa: PLC0415

    # Cheap checks first, so a typo is reported before anything is built.
    if args.frames is not None:
        checks.positive_int("--frames", args.frames)
    if args.fps is not None:
        checks.positive("--fps", args.fps)
    if args.dt is not None:
        checks.positive("--dt", args.dt)
    scale = checks.positive("--scale", args.scale)
    if args.output is not None:
        from .usd import USD_EXTENSIONS  # noqa: PLC0415

        if os.path.splitext(args.output)[1].lower() not in USD_EXTENSIONS:
            raise ValueError(f"--output = {args.output!r} is not allowed: the extension must be one of {', '.join(USD_EXTENSIONS)}")

    _init_warp(args.device)
    if args.device == "cuda":
        import warp as wp  # noqa: PLC0415

        if not wp.is_cuda_available():
            raise ValueError("--device = 'cuda' is not allowed: Warp finds no CUDA device on this machine (use --device cpu)")
    from .scenes import load_scene  # noqa: PLC0415
    from .simulate import SimulationError, resolve_timestep, simulate  # noqa: PLC0415
    from .solver import Solver  # noqa: PLC0415
    from .usd import UsdWriter  # noqa: PLC0415

    scene = load_scene(args.scene, scale=scale)
    frames = args.frames if args.frames is not None else scene.frames
    fps = args.fps if args.fps is not None else scene.fps
    dt = args.dt if args.dt is not None else scene.dt
    output = args.output or f"{scene.name}.usdc"

    model = scene.builder.finalize(device=args.device, dtype=args.dtype)
    substeps, dt = resolve_timestep(model, fps, dt=dt)
    solver = Solver(model)
    solver.check_dt(dt)  # the stability warning, once, before the run
    writer = UsdWriter(output, model, fps)
    try:
        print(f"{PROG}: {scene.name}: {model.particle_count} particles, {len(model.bodies)} bodies, "
              f"{frames} frames at {fps:g} fps, dt = {dt:.4g} s ({substeps} steps/frame), {args.device} {args.dtype} "
              f"-> {writer.path}", flush=True)
        simulate(model, frames, fps=fps, dt=dt, writer=writer, progress=not args.no_progress, solver=solver)
    except KeyboardInterrupt:
        writer.close()
        print(f"{PROG}: interrupted: {writer.path} keeps the {writer.frames_written} frames finished", file=sys.stderr)
        return EXIT_INTERRUPTED
    except SimulationError as e:
        writer.close()
        _err(f"{e} ({writer.path} keeps the {writer.frames_written} frames finished)")
        return EXIT_DIVERGED
    finally:
        writer.close()
    guards = ", ".join(f"{k}={v}" for k, v in solver.guard_counts().items())
    per_frame = 1e3 * writer.save_seconds / max(writer.frames_written, 1)
    print(f"wrote {writer.path}: {writer.frames_written} frames (0..{writer.last_frame}), "
          f"{model.particle_count} particles; USD save {per_frame:.2f} ms/frame")
    print(f"guard counts (particle-steps skipped): {guards}")
    return 0


def main(argv=None) -> int:
    """Entry point; returns the exit status (see the module docstring)."""
    parser = _build_parser()
    try:
        args = parser.parse_args(argv)
    except _UsageError as e:
        _err(e)
        return EXIT_BAD_INPUT
    if args.command is None:
        parser.print_help(sys.stderr)
        return EXIT_BAD_INPUT
    with warnings.catch_warnings():
        warnings.simplefilter("default")
        warnings.showwarning = _show_warning
        try:
            if args.command == "scenes":
                return _cmd_scenes()
            return _cmd_run(args)
        except KeyboardInterrupt:
            print(f"{PROG}: interrupted", file=sys.stderr)
            return EXIT_INTERRUPTED
        except (ValueError, OSError) as e:
            _err(e)
            return EXIT_BAD_INPUT
        except RuntimeError as e:
            from .simulate import SimulationError  # noqa: PLC0415

            if isinstance(e, SimulationError):
                _err(e)
                return EXIT_DIVERGED
            raise


if __name__ == "__main__":
    sys.exit(main())
