"""``simulate``: run a model for a number of rendered frames, optionally writing USD.

Frame 0 is the initial state; frame ``k`` is the state after ``k * substeps`` steps of
``dt``, ``substeps * dt = 1 / fps``. After every frame the positions and velocities are
checked; the first non-finite value stops the run with a ``SimulationError`` that names
the step, the particle and its body, after the writer has kept every finished frame.
"""

from __future__ import annotations

import math
import sys
import time

import numpy as np

from . import checks
from .model import Model, State
from .sim.solver import Solver

__all__ = ["simulate", "resolve_timestep", "adaptive_timestep", "SimulationError", "AUTO"]

#: ``dt = AUTO`` (``"auto"``) asks ``simulate`` for an adaptive (CFL) time step.
AUTO = "auto"


class SimulationError(RuntimeError):
    """The simulation produced a non-finite position or velocity.

    ``step``: the number of steps taken when it was detected (counted from the start of
    the run; the bad value arose in one of the steps of the last frame). ``particle``:
    the first bad particle's index; ``body``: its body's name; ``frame``: the frame
    whose check found it.
    """

    def __init__(self, message: str, *, step: int, particle: int, body: str | None = None, frame: int | None = None):
        super().__init__(message)
        self.step = step
        self.particle = particle
        self.body = body
        self.frame = frame


def resolve_timestep(model: Model, fps: float = 30.0, substeps: int | None = None, dt: float | None = None) -> tuple[int, float]:
    """``(substeps, dt)`` with ``substeps * dt = 1 / fps``.

    Give at most one of ``substeps`` and ``dt``. With neither, ``dt`` is the model's
    stable step (``model.stable_dt()``) rounded down so that a whole number of steps
    fills a frame. A given ``dt`` must divide ``1 / fps`` into a whole number of steps
    (to 1e-6 relative).
    """
    fps = checks.positive("fps", fps)
    frame_dt = 1.0 / fps
    if substeps is not None and dt is not None:
        raise ValueError(f"substeps = {substeps!r} and dt = {dt!r} are not allowed together: give one of them (or neither)")
    if substeps is not None:
        n = checks.positive_int("substeps", substeps)
        return n, frame_dt / n
    if dt is None:
        stable = model.stable_dt()
        n = max(1, math.ceil(frame_dt / stable * (1.0 - 1e-12)))
        return n, frame_dt / n
    dt = checks.positive("dt", dt)
    ratio = frame_dt / dt
    n = round(ratio)
    if n < 1 or abs(ratio - n) > 1e-6 * ratio:
        lo = max(1, math.floor(ratio))
        hint = f"dt = {frame_dt / lo:.6g}" if n < 1 else f"dt = {frame_dt / math.ceil(ratio):.6g} or {frame_dt / lo:.6g}"
        raise ValueError(
            f"dt = {dt!r} is not allowed: a frame (1/fps = {frame_dt:.6g} s) must be a whole number of steps, "
            f"but 1/fps / dt = {ratio:.6g}; use e.g. {hint}, or give substeps instead"
        )
    return n, frame_dt / n


def adaptive_timestep(model: Model, state: State, fps: float = 30.0, courant: float = 0.3) -> tuple[int, float]:
    """``(substeps, dt)`` for the next frame of ``state``, ``substeps * dt = 1 / fps``.

    The CFL limit of docs/method.md §8 with the signal speed measured now: a disturbance
    travels at the p-wave speed relative to the material, which itself moves, so

        dt <= C dx / (c_P + v_max + |g| / fps)

    where ``v_max`` is the largest particle speed of ``state`` and ``|g| / fps`` bounds
    what gravity adds to it within the frame; and ``dt`` is at most the viscous limit of
    ``Model.stable_dt``. A body at rest gets ``stable_dt`` (to the gravity term); one in
    flight or hit hard gets smaller steps. Rounded down to a whole number of steps per frame.
    """
    fps = checks.positive("fps", fps)
    courant = checks.positive("courant", courant)
    frame_dt = 1.0 / fps
    stable = model.stable_dt(courant)
    p = model.parameter_values()
    rho = np.array([m.density for m in model.materials], dtype=np.float64)
    from .material import p_wave_speed  # noqa: PLC0415

    c = float(np.max(p_wave_speed(p["mu"], p["lam"], rho, p["pressure_stiffness"])))
    v = state.v.numpy().astype(np.float64)
    v_max = float(np.sqrt((v * v).sum(axis=1)).max()) if len(v) else 0.0
    if not math.isfinite(v_max):
        v_max = 0.0  # the divergence check after the frame reports it
    g = float(np.linalg.norm(model.gravity))
    dt = min(stable, courant * model.spacing / (c + v_max + g * frame_dt))
    n = max(1, math.ceil(frame_dt / dt * (1.0 - 1e-12)))
    return n, frame_dt / n


def _frame_count(frames) -> int:
    if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames < 1:
        raise ValueError(f"frames = {frames!r} is not allowed: must be an integer >= 1")
    return int(frames)


class _PlainBar:
    """A minimal stand-in for tqdm (used only where tqdm is not installed)."""

    def __init__(self, total: int, desc: str):
        self.total, self.desc, self.n, self.postfix = total, desc, 0, ""

    def set_postfix_str(self, text: str, refresh: bool = True):
        self.postfix = text

    def update(self, n: int = 1):
        self.n += n
        print(f"\r{self.desc}: {self.n}/{self.total} frames, {self.postfix}", end="", file=sys.stderr, flush=True)

    def close(self):
        print(file=sys.stderr, flush=True)


def _progress_bar(total: int, desc: str):
    try:
        from tqdm import tqdm  # noqa: PLC0415 (only when a bar is wanted)
    except ModuleNotFoundError:
        return _PlainBar(total, desc)
    return tqdm(total=total, unit="frame", file=sys.stderr, dynamic_ncols=True, leave=True, desc=desc)


def _first_bad(model: Model, state: State) -> tuple[int, int] | None:
    """(first particle with a non-finite position or velocity, number of such particles)."""
    x = state.x.numpy()
    v = state.v.numpy()
    bad = ~(np.isfinite(x).all(axis=1) & np.isfinite(v).all(axis=1))
    if not bad.any():
        return None
    return int(np.argmax(bad)), int(bad.sum())


def simulate(
    model: Model,
    frames: int,
    fps: float = 30,
    substeps: int | None = None,
    dt: float | None = None,
    writer=None,
    progress: bool = True,
    solver: Solver | None = None,
    state: State | None = None,
    callback=None,
    *,
    start_frame: int = 0,
) -> State:
    """Simulate ``frames`` frames at ``fps``; returns the final state.

    - ``substeps`` / ``dt``: at most one; see ``resolve_timestep``. ``dt="auto"``: an
      adaptive (CFL) step, chosen anew for each frame by ``adaptive_timestep`` (whole
      steps per frame, never above ``model.stable_dt()``).
    - ``writer``: anything with ``write_frame(frame_index, state)`` (e.g. ``UsdWriter``).
      Frame ``start_frame`` (the initial state) is written first, then one frame per
      rendered frame. The writer is closed when the run ends, also when it fails.
    - ``solver``: a ``Solver`` of ``model`` (default: a new one; pass your own to read
      its ``guard_counts()`` afterwards). ``state``: the initial state (default: the
      model's initial configuration); it is copied, not modified.
    - ``callback(frame_index, state)``: called after each frame is written.
    - ``progress``: a tqdm bar on stderr (frames, particles, steps per second).
    - ``start_frame``: index of the initial frame (resuming a run); frames are numbered
      ``start_frame .. start_frame + frames``.

    Two states are swapped, so nothing is allocated per step. Raises ``SimulationError``
    when a position or velocity becomes non-finite.
    """
    try:
        if not isinstance(model, Model):
            raise ValueError(f"model = {model!r} is not allowed: must be a warp_esph.Model")
        frames = _frame_count(frames)
        if isinstance(start_frame, bool) or not isinstance(start_frame, (int, np.integer)) or start_frame < 0:
            raise ValueError(f"start_frame = {start_frame!r} is not allowed: must be an integer >= 0")
        start_frame = int(start_frame)
        fps = checks.positive("fps", fps)
        adaptive = isinstance(dt, str)
        if adaptive:
            if dt != AUTO:
                raise ValueError(f"dt = {dt!r} is not allowed: must be a number of seconds or {AUTO!r}")
            if substeps is not None:
                raise ValueError(f"substeps = {substeps!r} and dt = {AUTO!r} are not allowed together: the adaptive step chooses the substeps")
            n_sub, dt = 1, model.stable_dt()
        else:
            n_sub, dt = resolve_timestep(model, fps, substeps, dt)
        if writer is not None:
            if not callable(getattr(writer, "write_frame", None)):
                raise ValueError(f"writer = {writer!r} is not allowed: it must have a write_frame(frame_index, state) method")
            wfps = getattr(writer, "fps", None)
            if wfps is not None and not math.isclose(float(wfps), fps, rel_tol=1e-9):
                raise ValueError(f"fps = {fps:g} is not allowed: the writer was opened with fps = {float(wfps):g}")
        if callback is not None and not callable(callback):
            raise ValueError(f"callback = {callback!r} is not allowed: must be callable as callback(frame_index, state)")
        if solver is None:
            solver = Solver(model)
        elif not isinstance(solver, Solver) or solver.model is not model:
            raise ValueError("solver is not allowed: it must be a warp_esph.Solver built for this model")
        solver.check_dt(dt)  # warns once here, before the progress bar, if dt is above the stable limit

        current = model.state(requires_grad=False)
        if state is not None:
            if not isinstance(state, State) or state.particle_count != model.particle_count:
                raise ValueError("state is not allowed: it must be a warp_esph.State of this model")
            current.assign(state)
        spare = model.state(requires_grad=False)

        bar = _progress_bar(frames, f"{model.particle_count} particles") if progress else None
        try:
            if writer is not None:
                writer.write_frame(start_frame, current)
            if callback is not None:
                callback(start_frame, current)
            steps = 0
            t0 = time.perf_counter()
            for k in range(1, frames + 1):
                if adaptive:
                    n_sub, dt = adaptive_timestep(model, current, fps)
                for _ in range(n_sub):
                    solver.step(current, spare, dt)
                    current, spare = spare, current
                steps += n_sub
                frame = start_frame + k
                bad = _first_bad(model, current)
                if bad is not None:
                    p, count = bad
                    body = model.bodies[int(model.particle_body_np[p])].name
                    step = steps if adaptive else start_frame * n_sub + steps
                    raise SimulationError(
                        f"the simulation diverged: non-finite position or velocity after step {step} "
                        f"(frame {frame}, t = {frame / fps:.4g} s, dt = {dt:.4g} s): particle {p} of body {body!r} "
                        f"is the first of {count} bad particles; try a smaller dt (stable limit "
                        f"{model.stable_dt():.3g} s) or stiffer-to-softer material settings",
                        step=step, particle=p, body=body, frame=frame,
                    )
                if writer is not None:
                    writer.write_frame(frame, current)
                if callback is not None:
                    callback(frame, current)
                if bar is not None:
                    elapsed = max(time.perf_counter() - t0, 1e-9)
                    bar.set_postfix_str(f"{steps / elapsed:.0f} steps/s, dt={dt:.3g}s", refresh=False)
                    bar.update(1)
        finally:
            if bar is not None:
                bar.close()
        return current
    finally:
        if writer is not None and callable(getattr(writer, "close", None)):
            writer.close()
