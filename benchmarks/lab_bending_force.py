"""The lab three-point bending scene's pin force and mid-span deflection over its last frames.

    PYTHONPATH=. python -m benchmarks.lab_bending_force [SCALE] [FRAMES]
    FIT=linear HOURGLASS=0 PYTHONPATH=. python -m benchmarks.lab_bending_force   # one change

Runs ``lab_three_point_bending`` as ``warp-esph run`` does (the scene's step, the default
solver unless ``FIT`` / ``HOURGLASS`` set the builder's options as ``--solver-fit`` /
``--hourglass`` do) and prints, for the last frame, each tool's force on the frame's last
step and its mean over the frame (``ReactionLog``, the CLI's force log), then the pin's
frame-mean force and the deflection of the beam's inner layers at mid-span relative to those
over the supports for the last ten frames and their means (docs/physics.md, "The lab
three-point bending scene's pin force"). Written to run on older trees too (used to find the
commit that moved the force), so it uses only long-standing API (and ``benchmarks/_cli.py``,
its command line's checks: copy both).
"""

import os
import sys
import time

import numpy as np
import warp as wp

from benchmarks import _cli
from warp_esph.scenes import load_scene
from warp_esph.sim.solver import Solver
from warp_esph.simulate import resolve_timestep, simulate
from warp_esph.tools import ReactionLog

try:  # the fits FIT may name; an older tree without the list checks FIT when the model is built
    from warp_esph.model import FITS
except ImportError:
    FITS = None


def _inner_layers_y(x, column_x, rest):
    """Mean height of a particle column's inner layers (without its top and bottom layer):
    the neutral axis, clear of the local indentation under the pin and on the supports."""
    col = np.abs(rest[:, 0] - column_x) < 1e-4
    ys = rest[col, 1]
    inner = (ys > ys.min() + 1e-4) & (ys < ys.max() - 1e-4)
    return x[col][inner, 1].mean()


PROG = "python -m benchmarks.lab_bending_force"


def main(argv=None) -> int:
    fits = ", ".join(FITS) if FITS is not None else "the fits"
    p = _cli.Parser(prog=PROG, description=__doc__.split("\n\n")[0],
                    epilog=f"Environment: FIT (one of {fits}) and HOURGLASS (a number >= 0) set the scene builder's "
                           "fit and hourglass control, as warp-esph run's --solver-fit and --hourglass.")
    p.add_argument("scale", nargs="?", default=0.5, type=_cli.positive_float, metavar="SCALE",
                   help="the scene's resolution scale (default 0.5)")
    p.add_argument("frames", nargs="?", default=60, type=_cli.int_at_least(9), metavar="FRAMES",
                   help="frames to run (default 60; at least 9: the last ten frames, the initial one counted, are reported)")
    args = p.parse_args(argv)
    scale, frames = args.scale, args.frames
    fit, hourglass = os.environ.get("FIT"), os.environ.get("HOURGLASS")
    if fit and FITS is not None and fit not in FITS:
        p.error(f"FIT = {fit!r} is not allowed: must be one of {', '.join(FITS)} (or unset)")
    if hourglass:
        try:
            hourglass = _cli.nonnegative_float(hourglass, "HOURGLASS")
        except _cli.Refused as e:
            p.error(e)
    try:  # Warp's start-up, module-load and missing-driver lines held back; an older tree: quiet
        from warp_esph.startup import init_warp
        init_warp()
    except ImportError:
        wp.config.quiet = True
    t0 = time.perf_counter()
    scene = load_scene("lab_three_point_bending", scale=scale)
    if fit:
        scene.builder.fit = fit
    if os.environ.get("HOURGLASS"):
        scene.builder.hourglass = hourglass
    model = scene.builder.finalize(device="cpu", dtype="float32")
    substeps, dt = resolve_timestep(model, scene.fps, dt=scene.dt)
    solver = Solver(model)
    log = ReactionLog(solver)
    rest = np.asarray(model.particle_x0, dtype=np.float64)
    for c in (0.0, -0.09, 0.09):  # the deflection reads these columns' inner layers
        ys = rest[np.abs(rest[:, 0] - c) < 1e-4, 1]
        if len(ys) == 0 or not ((ys > ys.min() + 1e-4) & (ys < ys.max() - 1e-4)).any():
            p.error(f"SCALE = {scale:g} is not allowed: at this scale the beam's lattice has no particle column with inner "
                    f"layers at x = {c:+.2f} m (mid-span, over the supports), which the deflection reads; scale 0.5 and 1 have them")
    deflection, last = {}, {}

    def on_frame(frame, state):
        log.record(frame, state)
        x = state.x.numpy().astype(np.float64)
        mid, left, right = (_inner_layers_y(x, c, rest) - _inner_layers_y(rest, c, rest) for c in (0.0, -0.09, 0.09))
        deflection[frame] = -(mid - 0.5 * (left + right))
        if frame == frames:
            last.update(model.tools.reaction(state))

    simulate(model, frames, fps=scene.fps, dt=dt, solver=solver, progress=False, callback=on_frame)
    print(f"{model.particle_count} particles, dt {dt:.4g} s ({substeps} steps/frame), fit {getattr(model, 'fit', '?')}, "
          f"hourglass {getattr(model, 'hourglass', '?')}")
    mean = {r["tool"]: np.array(r["force"]) for r in log.rows if r["frame"] == frames}
    for name in ("loading_pin", "support_left", "support_right"):
        print(f"frame {frames}, {name}: last step {np.array2string(last[name][0], precision=4)} N, "
              f"frame mean {np.array2string(mean[name], precision=4)} N")
    pin = {r["frame"]: -r["force"][1] for r in log.rows if r["tool"] == "loading_pin"}
    window = range(frames - 9, frames + 1)
    for k in window:
        print(f"  frame {k}: pin {pin[k]:.4f} N, deflection {deflection[k] * 1e3:.4f} mm")
    print(f"frames {window[0]}-{frames}: mean pin force {np.mean([pin[k] for k in window]):.4f} N, "
          f"mean deflection {np.mean([deflection[k] for k in window]) * 1e3:.4f} mm ({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(_cli.run(main, PROG))
