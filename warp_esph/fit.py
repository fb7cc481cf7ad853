"""Fit material parameters to observed motion by gradient descent through a ``Rollout``.

::

    result = fit(model, target, params=["yield_stress", "flow_rate"], steps=300, dt=1e-3,
                 frames=[100, 200, 300], iterations=60)
    result.materials[0]        # the fitted Material
    result.history             # loss and parameter values per iteration

``model`` is a ``Model`` finalized with ``requires_grad=True``, a ``SceneBuilder``, or a
callable returning either (builders are finalized in ``dtype``, float64 by default). The
values the model holds are the initial guess. ``target`` is a ``warp_esph.losses.Loss``,
or target positions (``(frames, n, 3)``, ``{step: (n, 3)}``) fitted with a
``PositionLoss``.

Positive parameters are optimised in log space (a step of Adam changes them by about
``lr`` relative), others (e.g. ``hardening = 0``) in linear space scaled by their initial
magnitude. ``bounds={"flow_rate": (1, 1e3)}`` clips them; ``clip`` caps the norm of the
optimiser-space gradient (long horizons can give exploding gradients, WARP_NOTES).

``tie_pressure``: a ``Material`` whose ``pressure_stiffness`` was left at its default
follows ``mu`` and ``lam`` (``k_p = (lam + 2 mu / 3) / (2 rho0)``); with ``None`` (the
default) each fitted material whose ``k_p`` equals that formula keeps following it while
``mu``/``lam`` change, with the chain rule applied to the gradient.

``fit_cli(args)`` is the ``warp-esph fit`` subcommand (``add_fit_arguments`` declares its
options); see ``docs/fitting.md``.
"""

import dataclasses
import json
import math
import os
import sys
import time
from collections.abc import Callable, Mapping, Sequence

import numpy as np
import warp as wp

from . import checks
from .builder import SceneBuilder
from .losses import ChamferLoss, Loss, MeshLoss, PositionLoss
from .material import Material
from .model import Model
from .rollout import PARAMETERS, Rollout

__all__ = ["fit", "FitResult", "Adam", "load_target", "save_target", "Target", "add_fit_arguments", "fit_cli"]

#: Parameters that must stay > 0 (log space always).
_POSITIVE = ("mu", "yield_stress", "flow_rate")


class Adam:
    """Adam (Kingma & Ba 2015) on a numpy vector, with optional bias correction."""

    def __init__(self, size: int, lr: float = 0.1, betas=(0.9, 0.999), eps: float = 1e-8):
        self.lr = checks.positive("lr", lr)
        self.b1, self.b2 = (checks.in_range("beta", b, 0.0, 0.999999) for b in betas)
        self.eps = eps
        self.m = np.zeros(size)
        self.v = np.zeros(size)
        self.t = 0

    def step(self, z: np.ndarray, g: np.ndarray) -> np.ndarray:
        self.t += 1
        self.m = self.b1 * self.m + (1 - self.b1) * g
        self.v = self.b2 * self.v + (1 - self.b2) * g * g
        mh = self.m / (1 - self.b1**self.t)
        vh = self.v / (1 - self.b2**self.t)
        return z - self.lr * mh / (np.sqrt(vh) + self.eps)


@dataclasses.dataclass
class FitResult:
    """What ``fit`` returns.

    ``params``: the fitted values (lowest loss seen), ``{name: one value per fitted
    material}``; ``materials``: every material of the model with those values;
    ``history``: one dict per evaluation (``iteration, loss, params, grad, seconds``;
    ``grad`` is in optimiser space: ``p dL/dp`` for log-space parameters).
    ``stopped``: why the fit ended (``iterations``, ``converged``, ``tol``, ``callback``).
    """

    params: dict[str, np.ndarray]
    materials: list[Material]
    material_indices: list[int]
    loss: float
    initial_loss: float
    history: list[dict]
    model: Model
    stopped: str = "iterations"

    @property
    def material(self) -> Material:
        """The first fitted material."""
        return self.materials[self.material_indices[0]]

    def to_dict(self) -> dict:
        def mat(m: Material) -> dict:
            d = dataclasses.asdict(m)
            return {k: (None if isinstance(v, float) and math.isinf(v) else v) for k, v in d.items()}

        return _json_safe({
            "params": {k: [float(x) for x in v] for k, v in self.params.items()},
            "material_indices": list(self.material_indices),
            "materials": [mat(m) for m in self.materials],
            "loss": self.loss,
            "initial_loss": self.initial_loss,
            "iterations": len(self.history) - 1,
            "stopped": self.stopped,
            "history": self.history,
        })


def _json_safe(obj):
    """Non-finite floats become None (JSON has no NaN/inf)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    return obj


def _as_model(model_or_factory, dtype) -> Model:
    obj = model_or_factory
    if callable(obj) and not isinstance(obj, (Model, SceneBuilder)):
        obj = obj()
    if isinstance(getattr(obj, "builder", None), SceneBuilder):  # a scenes.Scene
        obj = obj.builder
    if isinstance(obj, SceneBuilder):
        return obj.finalize(dtype=dtype, requires_grad=True)
    if isinstance(obj, Model):
        if not obj.requires_grad:
            raise ValueError("model is not allowed: finalize it with requires_grad=True (or pass the SceneBuilder)")
        return obj
    raise ValueError(f"model = {model_or_factory!r} is not allowed: give a Model, a SceneBuilder or a callable returning one")


def _material_indices(model: Model, materials) -> list[int]:
    if materials is None:
        return list(range(len(model.materials)))
    if isinstance(materials, (int, str)):
        materials = [materials]
    out = []
    names = [b.name for b in model.bodies]
    for m in materials:
        if isinstance(m, str):
            if m not in names:
                raise ValueError(f"material {m!r} is not allowed: give a material index or a body name ({', '.join(names)})")
            # Every material the body's particles use (one per particle after split_materials).
            b = model.bodies[names.index(m)]
            for k in np.unique(model.particle_material_np[b.start: b.start + b.count]):
                if int(k) not in out:
                    out.append(int(k))
            continue
        if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or not 0 <= m < len(model.materials):
            raise ValueError(f"material {m!r} is not allowed: indices are 0..{len(model.materials) - 1}")
        if int(m) not in out:
            out.append(int(m))
    return out


def _target_loss(target, frames) -> Loss:
    if isinstance(target, Loss):
        return target
    if isinstance(target, (str, os.PathLike)):
        raise ValueError("target is a file: load it with load_target(path).loss(model, ...) first (or use fit_cli)")
    if isinstance(target, Mapping):
        return PositionLoss(target)
    a = np.asarray(target, dtype=np.float64)
    if frames is None:
        raise ValueError("frames is required with target positions: the step index of each target frame")
    return PositionLoss(a, frames=frames)


def fit(
    model,
    target,
    params: Sequence[str] = ("yield_stress", "flow_rate"),
    *,
    steps: int | None = None,
    dt: float | None = None,
    frames: Sequence[int] | None = None,
    materials=None,
    iterations: int = 50,
    lr: float = 0.1,
    lr_end: float | None = None,
    bounds: Mapping[str, tuple[float, float]] | None = None,
    clip: float | None = None,
    checkpoint_every: int | None = None,
    tie_pressure: bool | None = None,
    initial: Mapping[str, object] | None = None,
    tol: float | None = None,
    callback: Callable | None = None,
    progress: bool = True,
    dtype=wp.float64,
    optimizer: str = "adam",
    max_step: float = 1.0,
    lbfgs_memory: int = 10,
) -> FitResult:
    """Fit ``params`` of the model's materials so the rollout matches ``target``.

    - ``steps``/``dt``: the rollout (default ``steps`` = the last target frame, ``dt`` =
      the model's stable step). ``frames``: step indices of target positions (a ``Loss``
      carries its own).
    - ``materials``: indices (or body names) of the materials to fit; default all. With a
      per-particle model (``rollout.split_materials``) this fits a field.
    - ``iterations``, ``lr``: Adam steps and step size (relative, in log space);
      ``lr_end``: decay the step size geometrically to this value at the last iteration.
    - ``bounds``: ``{name: (lo, hi)}`` in the parameter's units. ``clip``: gradient norm cap.
    - ``checkpoint_every``: segment length for checkpointed rollouts (long runs).
    - ``initial``: ``Rollout.forward`` keywords (``x0, v0, F0, alpha0, initial_state``).
    - ``optimizer``: ``"adam"`` (default; ``lr``, ``lr_end``, ``clip``) or ``"lbfgs"``
      (quasi-Newton with a backtracking line search: far fewer evaluations on a smooth
      loss with few parameters; its first step moves by ``lr`` and no step moves a
      parameter by more than ``max_step`` in optimiser space, i.e. a factor ``e`` for
      log-space parameters). ``iterations`` counts gradient evaluations after the first
      (line-search trials included), so both optimisers cost ``iterations + 1`` rollouts.
    - ``tol``: stop once the loss is below it. ``callback(evaluation, loss, params)``:
      after each evaluation; return ``True`` to stop.
    """
    model = _as_model(model, dtype)
    if isinstance(params, str):
        params = [p.strip() for p in params.split(",") if p.strip()]
    params = list(params)
    if not params:
        raise ValueError("params = [] is not allowed: name at least one parameter")
    for p in params:
        if p not in PARAMETERS:
            raise ValueError(f"params entry {p!r} is not allowed: must be one of {', '.join(PARAMETERS)}")
    if len(set(params)) != len(params):
        raise ValueError(f"params = {params!r} is not allowed: names must be distinct")
    idx = _material_indices(model, materials)
    iterations = int(iterations)
    if iterations < 0:
        raise ValueError(f"iterations = {iterations!r} is not allowed: must be >= 0")
    if clip is not None:
        clip = checks.positive("clip", clip)
    optimizer = checks.choice("optimizer", optimizer, ("adam", "lbfgs"))
    max_step = checks.positive("max_step", max_step)
    lbfgs_memory = checks.positive_int("lbfgs_memory", lbfgs_memory)
    if callback is not None and not callable(callback):
        raise ValueError(f"callback = {callback!r} is not allowed: must be callable")
    loss = _target_loss(target, frames)
    steps = max(loss.frames) if steps is None else checks.positive_int("steps", steps)
    if max(loss.frames) > steps:
        raise ValueError(f"the target has frames up to step {max(loss.frames)}, beyond steps = {steps}")
    dt = model.stable_dt() if dt is None else checks.positive("dt", dt)
    rollout = Rollout(model, steps, dt, frames=loss.frames, checkpoint_every=checkpoint_every)
    initial = dict(initial or {})

    # Optimiser space: z = log(p) (positive) or p / scale (others).
    values = rollout.get_parameters()
    spaces, scales = {}, {}
    for name in params:
        v = values[name][idx]
        if name in _POSITIVE or (v > 0).all():
            if not (v > 0).all():
                raise ValueError(f"{name} must be > 0 to be fitted, the initial values are {v.tolist()}")
            spaces[name] = "log"
        else:
            spaces[name] = "linear"
            scales[name] = max(float(np.abs(v).max()), 1.0)
    lo_hi = {}
    for name, (lo, hi) in (bounds or {}).items():
        if name not in params:
            raise ValueError(f"bounds for {name!r} are not allowed: {name} is not fitted (params = {params})")
        lo, hi = float(lo), float(hi)
        if not lo < hi or (spaces[name] == "log" and lo <= 0.0 and lo != -math.inf):
            raise ValueError(f"bounds[{name!r}] = ({lo}, {hi}) is not allowed: need lo < hi (and lo > 0 for a positive parameter)")
        lo_hi[name] = (lo, hi)

    rho = np.array([m.density for m in model.materials])
    if tie_pressure is None:
        tied = [k for k in idx if math.isclose(model.materials[k].pressure_stiffness,
                                               model.materials[k].bulk_modulus / (2 * model.materials[k].density), rel_tol=1e-9)]
    else:
        tied = list(idx) if tie_pressure else []
    tie = bool(tied) and ("mu" in params or "lam" in params) and "pressure_stiffness" not in params

    def to_z(vals):
        parts = []
        for name in params:
            v = vals[name][idx]
            parts.append(np.log(v) if spaces[name] == "log" else v / scales[name])
        return np.concatenate(parts)

    def from_z(z):
        out, k = {}, 0
        for name in params:
            zz = z[k: k + len(idx)]
            k += len(idx)
            v = np.exp(zz) if spaces[name] == "log" else zz * scales[name]
            if name in lo_hi:
                v = np.clip(v, *lo_hi[name])
            out[name] = v
        return out

    def project(z):
        return to_z({name: _full(values[name], idx, v) for name, v in from_z(z).items()})

    def apply(p):
        full = {name: _full(values[name], idx, v) for name, v in p.items()}
        if tie:
            mu = full.get("mu", values["mu"])
            lam = full.get("lam", values["lam"])
            kp = values["pressure_stiffness"].copy()
            kp[tied] = (lam[tied] + 2.0 * mu[tied] / 3.0) / (2.0 * rho[tied])
            full["pressure_stiffness"] = kp
        rollout.set_parameters(full)

    def grad_z(p, grads):
        parts = []
        for name in params:
            g = grads[name].copy()
            if tie and name in ("mu", "lam"):
                gk = grads["pressure_stiffness"]
                factor = 1.0 / (3.0 * rho) if name == "mu" else 1.0 / (2.0 * rho)
                g[tied] += gk[tied] * factor[tied]
            g = g[idx]
            parts.append(g * p[name] if spaces[name] == "log" else g * scales[name])
        return np.concatenate(parts)

    z0 = project(to_z(values))
    if lr_end is not None:
        lr_end = checks.positive("lr_end", lr_end)
    history: list[dict] = []
    best = [math.inf, None]
    bar = None

    def evaluate(z):
        """Loss and optimiser-space gradient at z; records history, best, callback."""
        p = from_z(z)
        apply(p)
        t0 = time.perf_counter()
        try:
            value, grads = rollout.value_and_grad(loss, **initial)
            gz = grad_z(p, grads)
        except FloatingPointError:
            value, gz = math.inf, np.full(len(z), np.nan)
        value = float(value)
        finite = math.isfinite(value) and bool(np.isfinite(gz).all())
        history.append({
            "iteration": len(history),
            "loss": value,
            "params": {k: [float(x) for x in v] for k, v in p.items()},
            "grad": [float(x) for x in gz],
            "seconds": time.perf_counter() - t0,
        })
        if finite and value < best[0]:
            best[0], best[1] = value, {k: v.copy() for k, v in p.items()}
        if bar is not None:
            shown = ", ".join(f"{k}={v[0]:.4g}" for k, v in p.items())
            bar.set_postfix_str(f"loss={value:.3e}, {shown}", refresh=False)
            bar.update(1)
        if callback is not None and callback(len(history) - 1, value, {k: v.copy() for k, v in p.items()}):
            raise _Stop("callback")
        if tol is not None and finite and value < tol:
            raise _Stop("tol")
        return value, gz, finite

    stopped = "iterations"
    if progress:
        from tqdm import tqdm  # noqa: PLC0415

        bar = tqdm(total=iterations + 1, unit="eval", file=sys.stderr, dynamic_ncols=True, desc=f"fit ({optimizer})")
    try:
        if optimizer == "adam":
            stopped = _run_adam(evaluate, project, z0, iterations, lr, lr_end, clip, history)
        else:
            stopped = _run_lbfgs(evaluate, project, z0, iterations, lr, max_step, memory=lbfgs_memory)
    except _Stop as e:
        stopped = str(e)
    finally:
        if bar is not None:
            bar.close()
    if best[1] is None:
        raise FloatingPointError("no finite loss was found")
    value, p = best
    apply(p)
    fitted_materials = list(model.materials)
    kp_now = rollout.get_parameters()["pressure_stiffness"]
    for j, k in enumerate(idx):
        changes = {name: float(p[name][j]) for name in params}
        if tie and k in tied:
            changes["pressure_stiffness"] = float(kp_now[k])
        fitted_materials[k] = dataclasses.replace(model.materials[k], **changes)
    # Leave the model holding the fitted materials (arrays and Material objects agree).
    for k in idx:
        model.set_material(k, fitted_materials[k])
    return FitResult(
        params={k: v.copy() for k, v in p.items()},
        materials=fitted_materials,
        material_indices=idx,
        loss=value,
        initial_loss=history[0]["loss"],
        history=history,
        model=model,
        stopped=stopped,
    )


class _Stop(Exception):
    """Raised inside an evaluation to end the fit (callback or tol)."""


def _run_adam(evaluate, project, z, iterations, lr, lr_end, clip, history) -> str:
    opt = Adam(len(z), lr=lr)
    decay = 1.0 if lr_end is None or iterations <= 1 else (lr_end / lr) ** (1.0 / (iterations - 1))
    good = None
    for it in range(iterations + 1):
        value, g, finite = evaluate(z)
        if it == iterations:
            break
        if not finite:
            # The rollout blew up or the gradient is not finite: back to the last good
            # point with half the step size.
            if good is None:
                raise FloatingPointError(f"the loss or its gradient is not finite at the initial guess (loss = {value})")
            opt.lr *= 0.5
            history[-1]["note"] = f"non-finite; back to the last finite point, lr = {opt.lr:g}"
            z = good
            continue
        good = z.copy()
        if clip is not None:
            norm = float(np.linalg.norm(g))
            if norm > clip:
                g = g * (clip / norm)
        z = project(opt.step(z, g))
        opt.lr *= decay
    return "iterations"


def _run_lbfgs(evaluate, project, z, iterations, lr, max_step, memory=10, c1=1e-4) -> str:
    """L-BFGS (two-loop recursion) with a backtracking Armijo line search, in optimiser space.

    Box bounds are handled by projecting each trial point; pairs with ``s.y <= 0`` are
    skipped. A non-finite trial (a blown-up rollout) counts as a failed trial.
    """
    f, g, finite = evaluate(z)
    if not finite:
        raise FloatingPointError(f"the loss or its gradient is not finite at the initial guess (loss = {f})")
    evals = 0
    S, Y = [], []
    while evals < iterations:
        # Two-loop recursion: d = -H g.
        q = g.copy()
        alphas = []
        for s, y in reversed(list(zip(S, Y))):
            a = s.dot(q) / y.dot(s)
            alphas.append(a)
            q -= a * y
        if S:
            q *= S[-1].dot(Y[-1]) / Y[-1].dot(Y[-1])
        else:
            q *= lr / max(float(np.abs(g).max()), 1e-300)
        for (s, y), a in zip(zip(S, Y), reversed(alphas)):
            b = y.dot(q) / y.dot(s)
            q += (a - b) * s
        d = -q
        if not g.dot(d) < 0.0:
            S.clear()
            Y.clear()
            d = -g * (lr / max(float(np.abs(g).max()), 1e-300))
        big = float(np.abs(d).max())
        if big > max_step:
            d *= max_step / big
        t = 1.0
        while True:
            z_new = project(z + t * d)
            step = z_new - z
            if float(np.abs(step).max()) < 1e-12:
                return "converged"
            f_new, g_new, finite = evaluate(z_new)
            evals += 1
            if finite and f_new <= f + c1 * g.dot(step):
                break
            if evals >= iterations:
                return "iterations"
            t *= 0.5
        s, y = z_new - z, g_new - g
        if s.dot(y) > 1e-12 * np.linalg.norm(s) * np.linalg.norm(y):
            S.append(s)
            Y.append(y)
            if len(S) > memory:
                S.pop(0)
                Y.pop(0)
        if f_new == f and float(np.abs(s).max()) < 1e-10:
            return "converged"
        z, f, g = z_new, f_new, g_new
    return "iterations"


def _full(base: np.ndarray, idx: list[int], v: np.ndarray) -> np.ndarray:
    out = np.array(base, dtype=np.float64)
    out[idx] = v
    return out


# ----------------------------------------------------------------------- targets
@dataclasses.dataclass
class Target:
    """A target read from a file. ``kind``: ``positions`` (``data``: ``(K, n, 3)``),
    ``points`` (a cloud, ``(M, 3)``) or ``mesh`` (``(points, triangles)``). ``frames``:
    rendered frame index of each position frame (or the frame a cloud/mesh shows; None:
    the last simulated frame). ``fps``: as stored, or None."""

    kind: str
    data: object
    frames: list[int] | None
    fps: float | None
    path: str

    def loss(self, model: Model, frame_steps: Mapping[int, int], radius: float | None = None, mode: str = "surface") -> Loss:
        """The loss for ``model``: ``frame_steps`` maps each rendered frame to its step."""
        steps = [frame_steps[f] for f in sorted(frame_steps)]
        if self.kind == "positions":
            pos = np.asarray(self.data)
            if pos.shape[1] != model.particle_count:
                raise ValueError(f"target {self.path} has {pos.shape[1]} particles per frame, the scene {model.particle_count}: "
                                 f"use the scene and --scale the target was made with")
            keep = [k for k, f in enumerate(self.frames) if f != 0]
            if not keep:
                raise ValueError(f"target {self.path} holds only frame 0 (the initial state), which says nothing about the material")
            return PositionLoss({frame_steps[self.frames[k]]: pos[k] for k in keep})
        if self.kind == "points":
            r = radius if radius is not None else 3.0 * model.spacing
            return ChamferLoss(self.data, radius=r, frames=steps)
        return MeshLoss(self.data, frames=steps, mode=mode)


_CLOUD_TEXT = (".xyz", ".txt", ".csv", ".pts")


def save_target(path, positions, frames: Sequence[int], fps: float | None = None):
    """Write target positions ``(K, n, 3)`` of rendered ``frames`` to ``.npz`` (or ``.npy``)."""
    positions = np.asarray(positions, dtype=np.float64)
    if positions.ndim == 2:
        positions = positions[None]
    frames = [int(f) for f in frames]
    if positions.ndim != 3 or positions.shape[2] != 3 or positions.shape[0] != len(frames):
        raise ValueError(f"positions with shape {positions.shape} is not allowed: must be (len(frames) = {len(frames)}, n, 3)")
    path = os.fspath(path)
    if path.lower().endswith(".npy"):
        if frames != list(range(len(frames))):
            raise ValueError("a .npy target holds frames 0..K-1; use .npz to store other frames")
        np.save(path, positions)
        return
    extra = {} if fps is None else {"fps": float(fps)}
    np.savez_compressed(path, positions=positions, frames=np.asarray(frames, dtype=np.int64), **extra)


def load_target(path) -> Target:
    """Read a target file.

    - ``.npz``: ``positions`` ``(K, n, 3)`` (or ``(n, 3)``), optional ``frames`` (rendered
      frame indices; default 0..K-1) and ``fps``.
    - ``.npy``: positions ``(K, n, 3)`` of frames ``0..K-1``, or ``(n, 3)``: the last frame.
    - ``.xyz/.txt/.csv/.pts``: a point cloud, three numbers per line.
    - anything else ``meshio`` (or ``.usd``) reads: a mesh when it has faces, else a cloud.
    """
    p = os.fspath(path)
    if not os.path.isfile(p):
        raise FileNotFoundError(f"target file {p} does not exist")
    ext = os.path.splitext(p)[1].lower()
    if ext in (".npz", ".npy"):
        try:
            data = np.load(p)
            if ext == ".npz":  # read every array here: a damaged zip fails on access, not on open
                data = {k: data[k] for k in data.files}
        except Exception as e:  # noqa: BLE001
            raise ValueError(f"target {p} cannot be read: {e}") from None
        frames, fps = None, None
        if ext == ".npz":
            if "positions" not in data:
                raise ValueError(f"target {p} is not allowed: a .npz target needs a 'positions' array (has {list(data.keys())})")
            pos = np.asarray(data["positions"], dtype=np.float64)
            if "frames" in data:
                frames = [int(f) for f in np.atleast_1d(data["frames"])]
            if "fps" in data:
                fps = float(data["fps"])
        else:
            pos = np.asarray(data, dtype=np.float64)
        if pos.ndim == 2:
            pos = pos[None]
            if frames is None:
                return Target("positions", pos, None, fps, p)
        if pos.ndim != 3 or pos.shape[2] != 3:
            raise ValueError(f"target {p} with shape {pos.shape} is not allowed: positions must be (K, n, 3) or (n, 3)")
        if not np.isfinite(pos).all():
            raise ValueError(f"target {p} is not allowed: it has non-finite positions")
        if frames is None:
            frames = list(range(pos.shape[0]))
        if len(frames) != pos.shape[0] or min(frames) < 0 or len(set(frames)) != len(frames):
            raise ValueError(f"target {p} is not allowed: 'frames' must be {pos.shape[0]} distinct indices >= 0")
        return Target("positions", pos, frames, fps, p)
    if ext in _CLOUD_TEXT:
        try:
            pts = np.loadtxt(p, delimiter="," if ext == ".csv" else None, ndmin=2)[:, :3]
        except Exception as e:  # noqa: BLE001
            raise ValueError(f"target {p} cannot be read as a point cloud: {e}") from None
        return Target("points", pts, None, None, p)
    if ext in (".usd", ".usda", ".usdc"):
        from .meshes import load_mesh  # noqa: PLC0415

        return Target("mesh", load_mesh(p), None, None, p)
    try:
        import meshio  # noqa: PLC0415

        m = meshio.read(p)
    except Exception as e:  # noqa: BLE001
        raise ValueError(f"target {p} cannot be read: {e}") from None
    has_faces = any(c.type in ("triangle", "quad", "polygon", "tetra") or c.type.startswith("triangle") for c in m.cells)
    if has_faces:
        from .meshes import load_mesh  # noqa: PLC0415

        return Target("mesh", load_mesh(p), None, None, p)
    return Target("points", np.asarray(m.points, dtype=np.float64)[:, :3], None, None, p)


# --------------------------------------------------------------------------- CLI
def add_fit_arguments(parser):
    """Declare the ``warp-esph fit`` options on an ``argparse`` (sub)parser."""
    parser.add_argument("scene", metavar="SCENE", help="built-in scene name or .toml scene file (the initial guess)")
    parser.add_argument("--target", required=True, metavar="FILE",
                        help="target: .npz/.npy positions per frame, a point cloud (.xyz/.ply ...) or a mesh file")
    parser.add_argument("--params", default="yield_stress,flow_rate", metavar="A,B",
                        help=f"comma-separated parameters to fit, of {','.join(PARAMETERS)} (default yield_stress,flow_rate)")
    parser.add_argument("--material", action="append", metavar="BODY",
                        help="fit only this body's material (name or material index); repeatable; default all")
    parser.add_argument("--iterations", type=int, default=50, metavar="N", help="optimiser iterations (default 50)")
    parser.add_argument("--lr", type=float, default=0.1, metavar="LR", help="Adam step size, relative (default 0.1)")
    parser.add_argument("--bounds", action="append", default=[], metavar="NAME=LO:HI", help="bounds of a parameter; repeatable")
    parser.add_argument("--clip", type=float, metavar="C", help="clip the gradient norm (log space) to C")
    parser.add_argument("--target-frames", metavar="F,G", help="rendered frame index of each target frame (default: from the file)")
    parser.add_argument("--frames", type=int, metavar="N", help="frames to simulate (default: the last target frame or the scene's)")
    parser.add_argument("--fps", type=float, metavar="F", help="frames per second (default: the target's or the scene's)")
    parser.add_argument("--dt", type=float, metavar="DT", help="time step in s (default: the stable step)")
    parser.add_argument("--scale", type=float, default=1.0, metavar="S", help="resolution scale of the scene (default 1)")
    parser.add_argument("--radius", type=float, metavar="R", help="Chamfer search radius for point-cloud targets (default 3 spacings)")
    parser.add_argument("--mesh-mode", choices=MeshLoss.MODES, default="surface", help="mesh targets: surface or outside")
    parser.add_argument("--checkpoint-every", type=int, metavar="S", help="checkpoint the rollout every S steps (less memory)")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float64", help="precision (default float64)")
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu", help="Warp device (default cpu)")
    parser.add_argument("-o", "--output", metavar="OUT.json", help="fitted parameters (default: <target>.fit.json beside the target)")
    parser.add_argument("--no-usd", action="store_true", help="do not write the fitted run to USD")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    return parser


def _parse_bounds(items) -> dict:
    out = {}
    for item in items or []:
        try:
            name, rng = item.split("=", 1)
            lo, hi = rng.split(":", 1)
            out[name.strip()] = (float(lo), float(hi))
        except ValueError:
            raise ValueError(f"--bounds {item!r} is not allowed: use NAME=LO:HI, e.g. flow_rate=1:1000") from None
    return out


def fit_cli(args, out=sys.stdout) -> int:
    """Run ``warp-esph fit`` from parsed ``args`` (see ``add_fit_arguments``); returns 0.

    Writes the fitted parameters as JSON (``--output``, default ``<target>.fit.json``) and,
    when ``warp_esph.usd`` is available, the fitted run as ``<target>.fit.usdc`` beside it.
    Raises ``ValueError``/``OSError`` on bad input (the CLI maps them to exit status 2).
    """
    from .scenes import load_scene  # noqa: PLC0415
    from .simulate import resolve_timestep  # noqa: PLC0415

    params = [p.strip() for p in str(args.params).split(",") if p.strip()]
    for p in params:
        if p not in PARAMETERS:
            raise ValueError(f"--params entry {p!r} is not allowed: must be one of {', '.join(PARAMETERS)}")
    scale = checks.positive("--scale", args.scale)
    if args.iterations < 0:
        raise ValueError(f"--iterations = {args.iterations!r} is not allowed: must be >= 0")
    bounds = _parse_bounds(args.bounds)
    target = load_target(args.target)
    scene = load_scene(args.scene, scale=scale)
    fps = args.fps if args.fps is not None else (target.fps if target.fps is not None else scene.fps)
    dtype = {"float32": wp.float32, "float64": wp.float64}[args.dtype]
    model = scene.builder.finalize(device=args.device, dtype=dtype, requires_grad=True)
    substeps, dt = resolve_timestep(model, fps, dt=args.dt if args.dt is not None else scene.dt)

    target_frames = target.frames
    if args.target_frames:
        try:
            target_frames = [int(f) for f in args.target_frames.split(",")]
        except ValueError:
            raise ValueError(f"--target-frames = {args.target_frames!r} is not allowed: use comma-separated integers") from None
        if target.kind == "positions" and len(target_frames) != np.asarray(target.data).shape[0]:
            raise ValueError(f"--target-frames has {len(target_frames)} entries, the target {np.asarray(target.data).shape[0]} frames")
        target.frames = target_frames
    frames = args.frames if args.frames is not None else (max(target_frames) if target_frames else scene.frames)
    frames = checks.positive_int("--frames", frames)
    if target.frames is None:
        target.frames = [frames]
    if max(target.frames) > frames:
        raise ValueError(f"the target has frame {max(target.frames)}, beyond --frames = {frames}")
    frame_steps = {f: f * substeps for f in target.frames if f > 0 or target.kind != "positions"}
    loss = target.loss(model, frame_steps, radius=args.radius, mode=args.mesh_mode)
    materials = None
    if args.material:
        materials = [int(m) if m.isdigit() else m for m in args.material]

    print(f"warp-esph fit: {scene.name}: {model.particle_count} particles, {frames} frames at {fps:g} fps, "
          f"dt = {dt:.4g} s ({frames * substeps} steps), fitting {', '.join(params)} to {target.kind} from {target.path}",
          file=sys.stderr)
    result = fit(model, loss, params, steps=frames * substeps, dt=dt, materials=materials, iterations=args.iterations,
                 lr=args.lr, bounds=bounds, clip=args.clip, checkpoint_every=args.checkpoint_every,
                 progress=not args.no_progress)

    stem = os.path.splitext(os.path.abspath(args.target))[0]
    json_path = args.output or f"{stem}.fit.json"
    doc = {"scene": scene.name, "scale": scale, "target": os.path.abspath(args.target), "fps": fps, "dt": dt,
           "frames": frames, "params_fitted": params, **result.to_dict()}
    tmp = json_path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(doc, f, indent=2)
    os.replace(tmp, json_path)
    print(f"wrote {json_path}: loss {result.initial_loss:.4g} -> {result.loss:.4g}", file=out)
    for name, v in result.params.items():
        print(f"  {name} = {', '.join(f'{x:.6g}' for x in v)}", file=out)
    if not args.no_usd:
        usd_path = write_fitted_usd(result.model, f"{stem}.fit.usdc", frames, fps, dt)
        if usd_path:
            print(f"wrote {usd_path}", file=out)
    return 0


def write_fitted_usd(model: Model, path, frames: int, fps: float, dt: float, progress: bool = False) -> str | None:
    """Simulate ``model`` (with its current parameters) and write it to USD; None without usd support."""
    try:
        from .usd import UsdWriter  # noqa: PLC0415
    except ImportError:
        return None
    from .simulate import simulate  # noqa: PLC0415

    writer = UsdWriter(path, model, fps)
    simulate(model, frames, fps=fps, dt=dt, writer=writer, progress=progress)
    return writer.path
