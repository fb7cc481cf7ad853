"""Differentiable losses on particle positions at one or several observed steps.

Every loss is a set of Warp kernels that ``wp.atomic_add`` into a one-element array,
zeroed before each evaluation (docs/method.md, Warp pitfall 7). A loss reads the
positions at its ``frames`` (step indices of a ``Rollout``); ``value_and_grad(positions)`` records its
kernels on a tape and returns the value and ``{step: dL/dx}``, which is what
``Rollout.backward`` consumes (``rollout.backward(loss)`` calls it for you).

- ``PositionLoss``: mean squared distance to target positions, particle by particle; a NaN
  target (a missing marker) leaves that particle's term at that frame out.
- ``ChamferLoss``: truncated Chamfer distance to a target point cloud of any size. One
  ``wp.HashGrid`` on the target finds the nearest target point of each particle, a
  second one on the particles (rebuilt at each evaluation) the nearest particle of each
  target point. Only points within ``radius`` count as found; a point with nothing found
  within ``radius`` contributes ``radius**2`` (no gradient), so the loss is
  ``mean_i min(d_i^2, r^2) + mean_j min(d_j^2, r^2)``: continuous as points cross the
  radius. ``unmatched`` reports how many points found nothing at the last evaluation.
  ``coverage="partial"`` keeps only the second term, ``mean_j min(d_j^2, r^2)`` (every
  scanned point must lie on the body; the side the scanner did not see is free): a scan of
  part of the body pulls no particle it never saw. ``surface_offset=s`` is for a scan of
  the material's surface, which lies about half a spacing outside the outer particles'
  centres: each matched distance ``d`` scores ``(d - s)^2`` (``d`` smoothed below ``s/2``
  so that the gradient stays continuous where a point sits on a centre), an unmatched
  point ``(r - s)^2``.
- ``MeshLoss``: mean squared distance of the particles to a triangle mesh
  (``wp.Mesh`` + ``wp.mesh_query_point_no_sign``); ``mode="outside"`` counts only
  particles outside the (closed) mesh. Particles with no surface within ``max_dist``
  contribute ``max_dist**2`` (no gradient).

The nearest-point choices are discrete and made in untaped kernels; the distance to the
chosen point is taped. Their gradient is then exact (for a closest point on a surface,
by the envelope theorem) except where the choice itself switches. Losses combine:
``loss_a + 0.5 * loss_b``. Each takes ``particles`` (distinct indices, or a one-dimensional
boolean mask of one entry per particle) to use a subset (e.g. surface particles) and
``weight``.

Normalisation: each loss is the mean over its frames of its per-frame value, times
``weight`` (a ``PositionLoss`` with missing targets: the mean over its observed pairs).
"""

import contextlib
import copy
import functools
import itertools
import math
import os
import types
from collections.abc import Mapping

import numpy as np
import warp as wp

from . import checks
from .sim.replay import outside_recording_tape
from ._types import type_set

__all__ = ["Loss", "PositionLoss", "ChamferLoss", "MeshLoss", "SumLoss", "WorldLoss", "surface_particles",
           "ReactionForceLoss", "SlumpLoss", "read_tools_csv", "is_tools_csv", "unique_points", "scan_coverage"]

#: HashGrid resolution cap per axis (the grid is periodic: aliasing beyond costs time only).
_MAX_GRID_DIM = 128


@functools.cache
def _kernels(scalar):
    T = type_set(scalar)
    vec3 = T.vec3

    @wp.kernel(module="unique")
    def gather(x: wp.array(dtype=vec3), idx: wp.array(dtype=wp.int32), out: wp.array(dtype=vec3)):
        k = wp.tid()
        out[k] = x[idx[k]]

    @wp.kernel(module="unique")
    def add_scalar(src: wp.array(dtype=scalar), dst: wp.array(dtype=scalar)):
        wp.atomic_add(dst, 0, src[0])

    @wp.kernel(enable_backward=False, module="unique")
    def to_float32(x: wp.array(dtype=vec3), out: wp.array(dtype=wp.vec3f)):
        i = wp.tid()
        p = x[i]
        out[i] = wp.vec3f(wp.float32(p[0]), wp.float32(p[1]), wp.float32(p[2]))

    @wp.kernel(module="unique")
    def squared_distance(x: wp.array(dtype=vec3), target: wp.array(dtype=vec3), w: scalar, out: wp.array(dtype=scalar)):
        i = wp.tid()
        d = x[i] - target[i]
        wp.atomic_add(out, 0, w * wp.dot(d, d))

    @wp.kernel(module="unique")
    def masked_squared_distance(x: wp.array(dtype=vec3), target: wp.array(dtype=vec3), observed: wp.array(dtype=wp.int32),
                                w: scalar, out: wp.array(dtype=scalar)):
        # A missing marker's target is a placeholder: its term (and gradient) is left out, not zeroed by w.
        i = wp.tid()
        if observed[i] != 0:
            d = x[i] - target[i]
            wp.atomic_add(out, 0, w * wp.dot(d, d))

    @wp.kernel(enable_backward=False, module="unique")
    def nearest(
        grid: wp.uint64,
        query32: wp.array(dtype=wp.vec3f),
        query: wp.array(dtype=vec3),
        points: wp.array(dtype=vec3),
        radius: scalar,
        idx: wp.array(dtype=wp.int32),
        unmatched: wp.array(dtype=wp.int32),
    ):
        # Nearest of ``points`` (indexed by ``grid``) to each query within ``radius``; -1 if none.
        i = wp.tid()
        q = query[i]
        best = radius * radius
        found = int(-1)
        it = wp.hash_grid_query(grid, query32[i], wp.float32(radius))
        j = int(0)
        while wp.hash_grid_query_next(it, j):
            d = points[j] - q
            d2 = wp.dot(d, d)
            if d2 < best:
                best = d2
                found = j
        idx[i] = found
        if found < 0:
            wp.atomic_add(unmatched, 0, 1)

    @wp.kernel(module="unique")
    def nearest_term(
        src: wp.array(dtype=vec3),
        dst: wp.array(dtype=vec3),
        idx: wp.array(dtype=wp.int32),
        r2: scalar,
        w: scalar,
        out: wp.array(dtype=scalar),
    ):
        i = wp.tid()
        j = idx[i]
        if j >= 0:
            d = src[i] - dst[j]
            wp.atomic_add(out, 0, w * wp.dot(d, d))
        else:
            wp.atomic_add(out, 0, w * r2)

    @wp.func
    def surface_gap(d2: scalar, s: scalar, eps: scalar) -> scalar:
        # (d - s)^2, the squared distance to the sphere of radius s about the matched point,
        # where d = |d2|^(1/2). Below eps, d is replaced by the parabola (d^2 + eps^2) / (2 eps),
        # which meets it at eps with slope 1: |x - y| has a cone at 0, whose gradient flips
        # direction there; the parabola's is continuous and 0 at coincidence. The sqrt reads
        # max(d2, eps^2) so that its infinite derivative at 0 is never taken.
        d = wp.sqrt(wp.max(d2, eps * eps))
        if d2 < eps * eps:
            d = (d2 + eps * eps) / (scalar(2.0) * eps)
        return (d - s) * (d - s)

    @wp.kernel(module="unique")
    def offset_term(
        src: wp.array(dtype=vec3),
        dst: wp.array(dtype=vec3),
        idx: wp.array(dtype=wp.int32),
        r: scalar,
        s: scalar,
        eps: scalar,
        w: scalar,
        out: wp.array(dtype=scalar),
    ):
        i = wp.tid()
        j = idx[i]
        if j >= 0:
            d = src[i] - dst[j]
            wp.atomic_add(out, 0, w * surface_gap(wp.dot(d, d), s, eps))
        else:
            # (r - s)^2: what a match at the radius scores, so the loss is continuous there.
            wp.atomic_add(out, 0, w * (r - s) * (r - s))

    @wp.func
    def closest_on_triangle(p: vec3, a: vec3, b: vec3, c: vec3) -> vec3:
        # Ericson, Real-Time Collision Detection, 5.1.5, in the loss's precision.
        zero = scalar(0.0)
        ab = b - a
        ac = c - a
        ap = p - a
        d1 = wp.dot(ab, ap)
        d2 = wp.dot(ac, ap)
        if d1 <= zero and d2 <= zero:
            return a
        bp = p - b
        d3 = wp.dot(ab, bp)
        d4 = wp.dot(ac, bp)
        if d3 >= zero and d4 <= d3:
            return b
        vc = d1 * d4 - d3 * d2
        if vc <= zero and d1 >= zero and d3 <= zero:
            return a + (d1 / (d1 - d3)) * ab
        cp = p - c
        d5 = wp.dot(ab, cp)
        d6 = wp.dot(ac, cp)
        if d6 >= zero and d5 <= d6:
            return c
        vb = d5 * d2 - d1 * d6
        if vb <= zero and d2 >= zero and d6 <= zero:
            return a + (d2 / (d2 - d6)) * ac
        va = d3 * d6 - d5 * d4
        if va <= zero and (d4 - d3) >= zero and (d5 - d6) >= zero:
            return b + ((d4 - d3) / ((d4 - d3) + (d5 - d6))) * (c - b)
        denom = scalar(1.0) / (va + vb + vc)
        return a + ab * (vb * denom) + ac * (vc * denom)

    @wp.kernel(enable_backward=False, module="unique")
    def closest_on_mesh(
        mesh: wp.uint64,
        x: wp.array(dtype=vec3),
        verts: wp.array(dtype=vec3),
        tris: wp.array(dtype=wp.int32),
        max_dist: wp.float32,
        outside_only: int,
        closest: wp.array(dtype=vec3),
        code: wp.array(dtype=wp.int32),
        unmatched: wp.array(dtype=wp.int32),
    ):
        # code: 1 = use |x - closest|^2, 0 = inside (outside mode): nothing, -1 = none found.
        i = wp.tid()
        p = x[i]
        p32 = wp.vec3f(wp.float32(p[0]), wp.float32(p[1]), wp.float32(p[2]))
        face = int(-1)
        inside = int(0)
        if outside_only != 0:
            q = wp.mesh_query_point_sign_winding_number(mesh, p32, max_dist)
            if q.result:
                face = q.face
                if q.sign < 0.0:
                    inside = 1
        else:
            q = wp.mesh_query_point_no_sign(mesh, p32, max_dist)
            if q.result:
                face = q.face
        if face < 0:
            code[i] = -1
            closest[i] = p
            wp.atomic_add(unmatched, 0, 1)
        else:
            c = closest_on_triangle(p, verts[tris[3 * face]], verts[tris[3 * face + 1]], verts[tris[3 * face + 2]])
            closest[i] = c
            code[i] = wp.where(inside != 0, 0, 1)

    @wp.kernel(module="unique")
    def mesh_term(
        x: wp.array(dtype=vec3),
        closest: wp.array(dtype=vec3),
        code: wp.array(dtype=wp.int32),
        d2_max: scalar,
        w: scalar,
        out: wp.array(dtype=scalar),
    ):
        i = wp.tid()
        k = code[i]
        if k == 1:
            d = x[i] - closest[i]
            wp.atomic_add(out, 0, w * wp.dot(d, d))
        elif k < 0:
            wp.atomic_add(out, 0, w * d2_max)

    return types.SimpleNamespace(
        gather=gather, add_scalar=add_scalar, to_float32=to_float32, squared_distance=squared_distance,
        masked_squared_distance=masked_squared_distance, nearest=nearest,
        nearest_term=nearest_term, offset_term=offset_term, closest_on_mesh=closest_on_mesh, mesh_term=mesh_term,
    )


def _scalar_of(x: wp.array):
    if x.dtype == wp.vec3d:
        return wp.float64
    if x.dtype == wp.vec3f:
        return wp.float32
    raise ValueError(f"positions of dtype {x.dtype} are not allowed: must be wp.vec3f or wp.vec3d")


def _frames(frames) -> tuple[int, ...]:
    if isinstance(frames, np.ndarray) and frames.ndim == 0:  # a 0-d array is the value it holds
        frames = frames.item()
    if isinstance(frames, (int, np.integer)) and not isinstance(frames, bool):
        frames = [frames]
    try:
        frames = list(frames)
    except TypeError:  # 2.0, True, a 0-d array: Python's "'float' object is not iterable", naming no parameter
        raise ValueError(f"frames = {checks.shorten(frames)!r} is not allowed: give a step index (an integer >= 0) or a list of them") from None
    out = []
    for f in frames:
        if isinstance(f, bool) or not isinstance(f, (int, np.integer)) or f < 0:
            raise ValueError(f"frame {f!r} is not allowed: frames are step indices (integers >= 0)")
        out.append(int(f))
    if not out:
        raise ValueError("frames = [] is not allowed: give at least one step index")
    if len(set(out)) != len(out):
        raise ValueError(f"frames = {out!r} is not allowed: they must be distinct")
    return tuple(out)


def _per_frame(name: str, data, frames, item_ndim: int) -> dict:
    """``{frame: item}`` from one item for every frame, a sequence of items, or a mapping."""
    if isinstance(data, Mapping):
        keys = _frames(list(data.keys()))
        if frames is not None and set(_frames(frames)) != set(keys):
            raise ValueError(f"{name} is given for steps {sorted(keys)} but frames = {list(_frames(frames))}")
        return {f: data[f] for f in keys}
    if frames is None:
        raise ValueError(f"frames is required: say at which step indices {name} applies")
    frames = _frames(frames)
    data = checks.host_values(name, data)
    if isinstance(data, (list, tuple)) and data and all(np.ndim(d) == item_ndim for d in data):
        items = list(data)
    else:
        try:
            complex_ = np.iscomplexobj(data)
            # Refused before numpy keeps the real part with only a ComplexWarning.
            a = None if complex_ else np.asarray(data, dtype=np.float64)
        except checks.ARRAY_ERRORS:  # ragged rows: numpy's own message named no parameter
            raise ValueError(f"{name} is not allowed: give an array, a sequence of arrays or a {{step: array}} mapping") from None
        if complex_:
            raise ValueError(f"{name} is not allowed: it holds complex numbers; positions are real")
        checks.real_numbers(name, data, "positions are numbers (m)")
        if a.ndim == item_ndim:
            return {f: a for f in frames}
        if a.ndim != item_ndim + 1:
            raise ValueError(f"{name} with shape {a.shape} is not allowed: must have {item_ndim} or {item_ndim + 1} dimensions")
        items = list(a)
    if len(items) != len(frames):
        raise ValueError(f"{name}: {len(items)} given for {len(frames)} frames")
    return dict(zip(frames, items))


def _points(name: str, p, missing: bool = False, unseen: str = "") -> np.ndarray:
    """``p`` as ``(N, 3)`` finite float64 points, else refused naming ``name``. ``missing``: a
    row holding NaN is a missing observation (an occluded marker) and kept as NaN; inf is
    still refused (no export writes a gap as inf: it is an overflow). ``unseen``: what the
    refusal of a NaN says to do instead."""
    p = checks.host_values(name, p)
    if np.iscomplexobj(p):  # numpy kept the real part with only a ComplexWarning
        raise ValueError(f"{name} is not allowed: it holds complex numbers; positions are real")
    checks.real_numbers(name, p, "positions are numbers (m)")
    try:
        a = np.asarray(p, dtype=np.float64)
    except checks.ARRAY_ERRORS:  # numpy's "could not convert string to float" named no parameter
        raise ValueError(f"{name} = {checks.shorten(p)!r} is not allowed: must be (N, 3) numbers") from None
    if a.ndim != 2 or a.shape[1] != 3 or len(a) == 0:
        raise ValueError(f"{name} with shape {a.shape} is not allowed: must be (N, 3) with N >= 1")
    bad = np.isinf(a) if missing else ~np.isfinite(a)
    if bad.any():
        i = int(np.flatnonzero(bad.any(axis=1))[0])
        allowed = " (NaN marks a missing point; inf is no position)" if missing else unseen if np.isnan(a[i]).any() else ""
        raise ValueError(f"{name} is not allowed: it has non-finite values (first at point {i}: {a[i].tolist()}){allowed}")
    return a


def unique_points(points: np.ndarray) -> tuple[np.ndarray, int]:
    """``points`` without the rows that repeat an earlier one exactly (the first of each kept,
    in order), and how many were left out. A cloud's point listed twice (overlapping scans
    merged, a file concatenated with itself) is one observation: counted twice, it weighed
    twice in the Chamfer mean and in the diagnostics' observations and standard errors."""
    _, first = np.unique(points, axis=0, return_index=True)
    if len(first) == len(points):
        return points, 0
    return points[np.sort(first)], len(points) - len(first)


def _grid_dims(points: np.ndarray, cell: float) -> tuple[int, int, int]:
    ext = points.max(axis=0) - points.min(axis=0) if len(points) else np.zeros(3)
    dims = np.clip(np.ceil(ext / cell).astype(np.int64) + 2, 1, _MAX_GRID_DIM)
    return tuple(int(d) for d in dims)


class Loss:
    """Base class: a differentiable scalar of the positions at ``frames``.

    Subclasses implement ``_launch(frame, x, out, scale)``: taped kernels that add the
    frame's value times ``scale`` into ``out[0]`` (untaped helper launches use
    ``record_tape=False``). ``x`` is the frame's positions (or the ``particles`` subset).
    """
    #: What a launch fills and its adjoint reads, per frame (``copy_for_world`` makes them anew).
    _CACHES = ("_out", "_copies", "_subsets", "_keep", "_counts", "_value_buffers")
    #: The buffers a taped ``launch`` writes and its adjoint reads (or holds alive for it):
    #: ``value`` and ``value_and_grad`` run on a set of their own (``_own_buffers``).
    _TAPED = ("_subsets", "_keep")


    def __init__(self, frames, weight: float = 1.0, particles=None):
        self.frames = _frames(frames)
        # A negative weight makes a fit maximise the misfit and report it as a result; a
        # zero weight makes a term that cannot inform the fit (and residual_scale divides by it).
        self.weight = checks.positive("weight", weight)
        self._mask_size = None
        if particles is not None:
            given = checks.host_values("particles", particles)
            # As given, in a plain form: an array showed as 'array([0., 1.])', a tuple as a list.
            shown = checks.shorten(given.tolist() if isinstance(given, np.ndarray) else given)
            idx = np.asarray(given)
            mask = idx.dtype == bool
            if mask:
                if idx.ndim != 1:
                    # Flattened: True selected particle 0, a 2 x 2 mask on 4 particles 0 and 3.
                    raise ValueError(f"particles = {checks.shorten(shown)!r} is not allowed: a boolean mask is one-dimensional, one "
                                     f"entry per particle; this one has shape {idx.shape}")
                self._mask_size = idx.size  # checked against the positions (a wrong length blamed the targets)
                idx = np.flatnonzero(idx)
            elif isinstance(given, (list, tuple)) and any(isinstance(v, (bool, np.bool_)) for v in given):
                # numpy made [True, 2] the indices [1, 2].
                raise ValueError(f"particles = {checks.shorten(shown)!r} is not allowed: it mixes True/False with indices; give "
                                 "particle indices or a boolean mask")
            if idx.ndim == 1 and len(idx) == 0:
                # An all-False mask and an empty list were told to give what they were.
                what = f"particles (a boolean mask of {self._mask_size} entries, all False)" if mask else f"particles = {shown!r}"
                raise ValueError(f"{what} is not allowed: it selects no particle")
            if idx.ndim != 1 or not np.issubdtype(idx.dtype, np.integer) or idx.min() < 0:
                raise ValueError(f"particles = {checks.shorten(shown)!r} is not allowed: give non-negative particle indices "
                                 "or a boolean mask")
            if int(idx.max()) > checks.MAX_INT:
                # int32 wrapped it: 2**31 crashed the process, 2**32 + 1 read particle 1.
                raise ValueError(f"particles is not allowed: index {int(idx.max())} is beyond any model's particles "
                                 f"(at most {checks.MAX_INT})")
            values, counts = np.unique(idx, return_counts=True)
            if (counts > 1).any():
                # A repeat counted that particle twice in the loss's mean, without a word.
                k = int(np.argmax(counts > 1))
                raise ValueError(f"particles = {checks.shorten(shown)!r} is not allowed: particle {int(values[k])} is listed "
                                 f"{int(counts[k])} times; list each particle once")
            particles = idx.astype(np.int32)
        self.particles = particles
        self._out = {}
        self._copies = {}
        self._subsets = {}
        self._keep = []  # grids and meshes used by the last evaluation
        self._counts: dict[int, int] = {}  # points used per frame at the last evaluation
        # The other set of the _TAPED buffers (_own_buffers), and whether value's are in place.
        self._value_buffers: dict = {}
        self._value_side = False
        #: Observation noise of this loss's residuals for ``warp_esph.diagnostics`` (None:
        #: the noise given there).
        self.noise = None

    # -------------------------------------------------------------- interface
    def _launch(self, frame: int, x: wp.array, out: wp.array, scale: float):
        raise NotImplementedError

    def out_of_reach(self) -> str | None:
        """Why this loss gave no gradient at its last evaluation, where it knows (nothing it
        compares came within its reach in any frame), else None."""
        return None

    def _check(self, frame: int, x: wp.array):
        """Validate a frame's positions (particle count) before launching."""
        self._check_count(x.shape[0])

    def _check_count(self, n: int) -> None:
        """Refuse positions of ``n`` particles (after the ``particles`` subset)."""

    def check_positions(self, n: int) -> None:
        """Refuse positions of ``n`` particles that this loss cannot read (a ``particles``
        subset past them, targets of another count), before a rollout runs: its first
        evaluation refused them only after the rollout had run."""
        if self.particles is not None:
            self._check_particles(n)
            n = len(self.particles)
        self._check_count(n)

    def _check_particles(self, n: int) -> None:
        """The ``particles`` subset against positions of ``n`` particles."""
        if self._mask_size is not None and self._mask_size != n:
            raise ValueError(f"particles is a boolean mask of {self._mask_size} entries, the positions {n} "
                             "particles: a mask has one entry per particle")
        if int(self.particles.max()) >= n:
            raise ValueError(f"particles has index {int(self.particles.max())}, the positions only {n} particles")

    def _prepare_x(self, frame: int, x: wp.array) -> wp.array:
        if self.particles is None:
            return x
        self._check_particles(x.shape[0])
        key = (frame, x.dtype)
        sub = self._subsets.get(key)
        if sub is None or sub[1].device != x.device:
            idx = wp.array(self.particles, dtype=wp.int32, device=x.device)
            sub = (idx, wp.zeros(len(self.particles), dtype=x.dtype, device=x.device, requires_grad=True))
            self._subsets[key] = sub
        idx, xs = sub
        wp.launch(_kernels(_scalar_of(x)).gather, len(idx), [x, idx], [xs], device=x.device)
        return xs

    def launch(self, frame: int, x: wp.array, out: wp.array, scale: float = 1.0):
        """Record this loss's kernels for ``frame`` (adds ``weight * value / len(frames)``)."""
        if frame not in self.frames:
            return
        xs = self._prepare_x(frame, x)
        self._check(frame, xs)
        self._counts[frame] = xs.shape[0]
        self._launch(frame, xs, out, scale * self.weight / len(self.frames))

    def _accumulator(self, x: wp.array) -> wp.array:
        key = (str(x.device), x.dtype)
        out = self._out.get(key)
        if out is None:
            out = wp.zeros(1, dtype=_scalar_of(x), device=x.device, requires_grad=True)
            self._out[key] = out
        return out

    def value_and_grad(self, positions: Mapping[int, wp.array]) -> tuple[float, dict[int, wp.array]]:
        """The loss at ``positions`` (``{step: wp.array of vec3}``) and ``{step: dL/dx}``. It
        records on a tape of its own, also where the caller's ``wp.Tape`` is recording: that
        tape is set aside meanwhile and records nothing of it (the value is a number, no part
        of the caller's graph; ``launch`` records the loss on the caller's tape). It runs on
        buffers of its own, so a caller's ``launch`` recorded before it is differentiated by
        the caller's ``tape.backward()`` after it as recorded (``_own_buffers``)."""
        missing = [f for f in self.frames if f not in positions]
        if missing:
            raise ValueError(f"the loss needs positions at steps {missing}, given only at {sorted(k for k in positions if isinstance(k, int))}")
        # Under a caller's tape Warp refused the inner one, after the copies below had been
        # recorded on the caller's, whose backward pass would have replayed them.
        with outside_recording_tape(), self._own_buffers():
            return self._value_and_grad(positions)

    def _nested(self) -> list["Loss"]:
        """The losses this one launches (a sum's terms, a WorldLoss's worlds' losses)."""
        return []

    @contextlib.contextmanager
    def _own_buffers(self):
        """Inside, this loss and every loss it launches use the ``_TAPED`` buffers of their
        own evaluations, not those of a caller's ``launch``: a ``value`` between a caller's
        taped ``launch`` and its ``tape.backward()`` overwrote what that backward reads (the
        subset's positions, a Chamfer loss's nearest points, a mesh loss's closest points),
        and the caller's gradient was another point's (off by more than itself)."""
        seen, stack = {}, [self]
        while stack:
            loss = stack.pop()
            if id(loss) not in seen:
                seen[id(loss)] = loss
                stack.extend(loss._nested())
        # Not those a nested evaluation (a sum's kernel terms) has switched already.
        switched = [loss for loss in seen.values() if not getattr(loss, "_value_side", False)]
        for loss in switched:
            loss._swap_buffers()
        try:
            yield
        finally:
            for loss in switched:
                loss._swap_buffers()

    def _swap_buffers(self):
        other = self.__dict__.setdefault("_value_buffers", {})
        for name in {n for cls in type(self).__mro__ for n in vars(cls).get("_TAPED", ())}:
            if name in vars(self):
                held = getattr(self, name)
                setattr(self, name, other[name] if name in other else type(held)())
                other[name] = held
        self._value_side = not getattr(self, "_value_side", False)

    def _value_and_grad(self, positions: Mapping[int, wp.array]) -> tuple[float, dict[int, wp.array]]:
        any_x = positions[self.frames[0]]
        out = self._accumulator(any_x)
        out.zero_()
        out.grad.zero_()
        copies = {}
        for f in self.frames:
            x = positions[f]
            c = self._copies.get(f)
            if c is None or c.shape != x.shape or c.dtype != x.dtype or c.device != x.device:
                c = wp.zeros(x.shape, dtype=x.dtype, device=x.device, requires_grad=True)
                self._copies[f] = c
            wp.copy(c, x)
            c.grad.zero_()
            copies[f] = c
        self._keep = []
        tape = wp.Tape()
        with tape:
            for f in self.frames:
                self.launch(f, copies[f], out)
        tape.backward(out)
        value = float(out.numpy()[0])
        grads = {f: wp.clone(copies[f].grad) for f in self.frames}
        tape.zero()
        return value, grads

    def value(self, positions: Mapping[int, wp.array]) -> float:
        return self.value_and_grad(positions)[0]

    # ------------------------------------------------------------ statistics
    def _points_per_frame(self) -> float:
        if not self._counts:
            raise RuntimeError(f"{self!r}: evaluate the loss once before asking for its residual counts")
        return float(np.mean([self._counts[f] for f in self.frames if f in self._counts]))

    def residual_scale(self) -> float:
        """``c`` with ``c * value = the sum of the squared residuals`` (m^2), for
        ``warp_esph.diagnostics``: the loss is ``weight`` times a mean over frames and points."""
        return len(self.frames) * self._points_per_frame() / self.weight

    def observation_count(self) -> int:
        """Scalar observations behind the loss (for the residual RMS)."""
        return int(round(len(self.frames) * self._points_per_frame()))

    def __call__(self, positions):
        """``value`` of ``{step: positions}`` (Warp arrays or numpy ``(n, 3)`` arrays)."""
        return self.value(_as_warp_positions(positions))

    def target_items(self, prefix: str = "target") -> dict:
        """What a run is compared against, by name (``prefix`` and the attribute): the frames,
        weight and ``particles`` subset, and each subclass's targets (positions, clouds, meshes,
        masks, force curves, measured lengths) with its settings of the comparison, as held (no
        copies; a fit's ``_SceneGuard`` copies them once). Numbers, arrays or tuples of them:
        what a caller might write in place, so that a fit can tell an edited target."""
        return {f"{prefix}.frames": self.frames, f"{prefix}.weight": self.weight,
                f"{prefix}.particles": self.particles}

    def copy_for_world(self) -> "Loss":
        """This loss with buffers of its own (``WorldLoss``): the same targets, frames and
        weight, but every cache a launch fills and its adjoint reads (the ``particles``
        subset, a Chamfer or mesh loss's scratch) new. Those are kept per frame, not per
        world: one object evaluated on every world let the last world's values overwrite
        what the earlier worlds' adjoints read, and their gradients were 9-42 % off."""
        new = copy.copy(self)
        for cls in type(self).__mro__:
            for name in vars(cls).get("_CACHES", ()):
                if name in vars(self):
                    setattr(new, name, type(getattr(self, name))())
        return new

    # ------------------------------------------------------------- combining
    def __add__(self, other):
        if not isinstance(other, Loss):
            return NotImplemented
        return SumLoss([(1.0, self), (1.0, other)])

    def __mul__(self, k):
        return SumLoss([(_scale("loss scale", k), self)])

    __rmul__ = __mul__


def _leaves(loss):
    """The terms of a sum, recursively; a loss that is no sum, itself."""
    return [leaf for _, term in loss.terms for leaf in _leaves(term)] if isinstance(loss, SumLoss) else [loss]


def _as_warp_positions(positions) -> dict[int, wp.array]:
    out = {}
    for f, x in positions.items():
        if isinstance(f, str):  # not positions: the reaction forces and names of Rollout.observations()
            out[f] = x
            continue
        if isinstance(f, bool) or not isinstance(f, (int, np.integer)):
            # int() read frame 1.5 as 1, so its positions replaced frame 1's
            raise ValueError(f"positions for frame {f!r} are not allowed: frames are step indices (integers)")
        if not isinstance(x, wp.array):
            if np.iscomplexobj(x):
                raise ValueError(f"positions of frame {f} are not allowed: they hold complex numbers")
            a = np.asarray(x, dtype=np.float64)
            if a.ndim != 2 or a.shape[1] != 3:  # Warp's RuntimeError for (n, 2)
                raise ValueError(f"positions of frame {f} with shape {a.shape} are not allowed: must be (N, 3)")
            x = wp.array(a, dtype=wp.vec3d)
        out[int(f)] = x
    return out


def _scale(name: str, k) -> float:
    """A loss's coefficient in a sum: a finite number > 0 (the ``weight`` rule)."""
    v = checks.number(name, k)
    if not v > 0.0:
        raise ValueError(f"{name} = {checks.shorten(k)!r} is not allowed: must be > 0 (a negative scale makes a fit "
                         "maximise the loss, a zero one drops it)")
    return v


class SumLoss(Loss):
    """A weighted sum of losses (``a + b``, ``k * a``); its frames are the union."""

    def __init__(self, terms):
        flat = []
        for i, term in enumerate(terms):
            try:
                k, loss = term
            except (TypeError, ValueError):
                raise ValueError(f"terms[{i}] = {checks.shorten(term)!r} is not allowed: must be a (scale, Loss) pair") from None
            k = _scale(f"terms[{i}] scale", k)
            if not isinstance(loss, Loss):
                raise ValueError(f"terms[{i}] = {checks.shorten(term)!r} is not allowed: its second item must be a "
                                 "warp_esph.losses.Loss")
            if isinstance(loss, SumLoss):
                flat.extend((k * kk, ll) for kk, ll in loss.terms)
            else:
                flat.append((k, loss))
        # One term per loss object, its scales added (``a + a`` is ``2 * a``): a loss keeps its
        # per-frame buffers by frame, so a second launch of the same object in one evaluation
        # overwrote the first's taped ones (a WorldLoss twice gave 3 x the gradient).
        merged: dict[int, list] = {}
        for k, loss in flat:
            if id(loss) in merged:
                merged[id(loss)][0] += k
            else:
                merged[id(loss)] = [k, loss]
        flat = [(k, loss) for k, loss in merged.values()]
        for k, loss in flat:
            # Scales of nested sums multiply: two legal ones can overflow or underflow.
            if not 0.0 < k < math.inf:
                raise ValueError(f"the scale of {loss!r} in a sum = {checks.shorten(k)!r} is not allowed: the nested scales multiply to "
                                 "it; must be finite and > 0")
        self.terms = flat
        frames = sorted({f for _, loss in flat for f in loss.frames})
        super().__init__(frames)

    def check_positions(self, n: int) -> None:
        for _, loss in self.terms:
            loss.check_positions(n)

    def copy_for_world(self) -> "SumLoss":
        new = super().copy_for_world()
        new.terms = [(k, loss.copy_for_world()) for k, loss in self.terms]
        new._kernel_sum = None  # built from the terms when needed: the copy's, not these
        return new

    def target_items(self, prefix: str = "target") -> dict:
        out = {f"{prefix}.terms": tuple(id(loss) for _, loss in self.terms)}
        for i, (k, loss) in enumerate(self.terms):
            out[f"{prefix}.terms[{i}].scale"] = k
            out.update(loss.target_items(f"{prefix}.terms[{i}]"))
        return out

    def launch(self, frame, x, out, scale: float = 1.0):
        for k, loss in self.terms:
            loss.launch(frame, x, out, scale * k)

    def _nested(self) -> list[Loss]:
        return [loss for _, loss in self.terms]

    def value_and_grad(self, positions):
        # Terms evaluated on the host (reaction forces) add their own value and gradient.
        host = [(k, loss) for k, loss in self.terms if getattr(loss, "_host", False)]
        if not host:
            return super().value_and_grad(positions)
        kernel_terms = [(k, loss) for k, loss in self.terms if not getattr(loss, "_host", False)]
        value, grads = 0.0, {}
        if kernel_terms:
            if getattr(self, "_kernel_sum", None) is None:
                self._kernel_sum = SumLoss(kernel_terms)
            value, grads = self._kernel_sum.value_and_grad(positions)
            grads = dict(grads)
        for k, loss in host:
            v, g = loss.value_and_grad(positions)
            value += k * v
            for key, a in g.items():
                a = a.numpy() if isinstance(a, wp.array) else np.asarray(a)
                if key in grads:
                    b = grads[key]
                    grads[key] = (b.numpy() if isinstance(b, wp.array) else b) + k * a
                else:
                    grads[key] = k * a
        return value, grads

    def __repr__(self):
        return " + ".join(f"{k:g} * {loss!r}" for k, loss in self.terms)


class WorldLoss(Loss):
    """The sum over the worlds of a model (``SceneBuilder.finalize(worlds=W)``) of one
    loss per world, each evaluated on its own world's particles only.

    ``losses``: one ``Loss`` used for every world, or a sequence of one per world (e.g.
    ``PositionLoss`` with each world's own targets); a world's loss sees an array of that
    world's particles (indices, ``particles=`` and target sizes are the world's). Since
    worlds never interact, the gradient of the sum with respect to world ``w``'s
    parameters (``model.world_materials(w)``) and initial state
    (``model.world_particles(w)``) is that of world ``w``'s loss alone: one backward
    pass gives every world's gradient. ``world_values`` holds each world's term after an
    evaluation (scaled as it entered the sum): summed over the world's frames as its loss
    alone sums them, it is the separate run's value to the bit on the CPU (a loss whose
    frames are in ascending order).
    """

    def __init__(self, model, losses):
        starts = getattr(model, "world_start", None)
        if starts is None:
            raise ValueError(f"model = {checks.shorten(model)!r} is not allowed: must be a warp_esph.Model")
        W = len(starts) - 1
        if isinstance(losses, Loss):
            losses = [losses] * W
        if isinstance(losses, (str, bytes, Mapping)) or not hasattr(losses, "__iter__"):
            # None was a TypeError ("not iterable"), a string read as one loss per character.
            raise ValueError(f"losses = {checks.shorten(losses)!r} is not allowed: must be one warp_esph.losses.Loss or "
                             f"a list of {W} (one per world)")
        losses = list(losses)
        if len(losses) != W or not all(isinstance(loss, Loss) for loss in losses):
            raise ValueError(f"losses is not allowed: must be one warp_esph.losses.Loss or a list of {W} (one per world), got {len(losses)} items")
        nested = [leaf for loss in losses for leaf in _leaves(loss) if isinstance(leaf, WorldLoss)]
        if nested:
            # A world's loss sees that world's particles only: a WorldLoss inside one failed
            # at the first evaluation, after the rollout had run.
            raise ValueError(f"losses with a {nested[0]!r} are not allowed in a WorldLoss: a world's loss is "
                             "evaluated on that world's particles; give each world's own loss (or one for all)")
        host = [type(leaf).__name__ for loss in losses for leaf in _leaves(loss) if getattr(leaf, "_host", False)]
        if host:
            # They are evaluated on the host from the rollout's observations, not launched on a
            # world's particles: inside a WorldLoss they read 0 with a gradient of 0.
            raise ValueError(f"losses with a {host[0]} are not allowed in a WorldLoss: it is evaluated on the host, not "
                             f"on a world's particles; use it on the whole model, beside the WorldLoss in a sum (e.g. a "
                             f"ReactionForceLoss of tool 'w1/press')")
        self.world_start = np.asarray(starts, dtype=np.int64)
        total = int(self.world_start[-1])
        for w, loss in enumerate(losses):
            count = int(self.world_start[w + 1] - self.world_start[w])
            try:
                loss.check_positions(count)
            except ValueError as e:
                # A loss sized for the whole model was refused only at its first evaluation,
                # after the rollout had run, as 'the positions 8 particles' of no named world.
                raise ValueError(f"losses is not allowed: world {w}'s loss is evaluated on that world's {count} particles "
                                 f"(the whole model has {total}), but {e}; give each world's loss that world's targets "
                                 "and particle indices") from None
        # Each world's own copy (Loss.copy_for_world): one object's buffers served every world.
        self.losses = [loss.copy_for_world() for loss in losses]
        super().__init__(sorted({f for loss in losses for f in loss.frames}))
        self._world_x = {}
        self._world_acc = {}
        self._used: list[dict] = [{} for _ in losses]

    @property
    def world_values(self) -> np.ndarray | None:
        """Each world's term at the last evaluation, scaled as it entered the sum (numpy, one
        value per world; None before one), also where this loss is a term of a sum (it was
        set by this loss's own ``value_and_grad`` only, and read stale inside a sum)."""
        if not any(self._used):
            return None
        return np.array([sum(float(a.numpy()[0]) for a in used.values()) for used in self._used])

    _TAPED = ("_world_x", "_world_acc")

    def _nested(self) -> list[Loss]:
        return list(self.losses)

    def check_positions(self, n: int) -> None:
        if n != self.world_start[-1]:
            # Said as a plain loss's size is (PositionLoss): fit wraps it in a refusal of the
            # target, where 'positions ... are not allowed' said 'is not allowed' twice.
            raise ValueError(f"the worlds of this loss have {int(self.world_start[-1])} particles, the positions {n}")

    def launch(self, frame, x, out, scale: float = 1.0):
        self.check_positions(x.shape[0])
        k = _kernels(_scalar_of(x))
        for w, loss in enumerate(self.losses):
            if frame not in loss.frames:
                continue
            key = (w, frame, x.dtype, str(x.device))
            if key not in self._world_x:
                idx = wp.array(np.arange(self.world_start[w], self.world_start[w + 1], dtype=np.int32), device=x.device)
                n = len(idx)
                self._world_x[key] = (idx, wp.zeros(n, dtype=x.dtype, device=x.device, requires_grad=True))
            idx, xw = self._world_x[key]
            # One running total per world over its frames (launched in ascending order), added
            # to ``out`` after its last: the world's value is then summed as the loss alone sums
            # it, to the bit. Summed frame by frame and the frames added after, it was 1-2 ulp off.
            acc_key = (w, x.dtype, str(x.device))
            acc = self._world_acc.get(acc_key)
            if acc is None:
                acc = self._world_acc[acc_key] = wp.zeros(1, dtype=_scalar_of(x), device=x.device, requires_grad=True)
            if frame == min(loss.frames):
                acc.zero_()
            wp.launch(k.gather, len(idx), [x, idx], [xw], device=x.device)
            loss.launch(frame, xw, acc, scale)
            if frame == max(loss.frames):
                wp.launch(k.add_scalar, 1, [acc], [out], device=x.device)
            self._used[w][acc_key] = acc

    def value_and_grad(self, positions):
        self._used = [{} for _ in self.losses]
        return super().value_and_grad(positions)

    def target_items(self, prefix: str = "target") -> dict:
        out = {f"{prefix}.losses": tuple(id(loss) for loss in self.losses)}
        for w, loss in enumerate(self.losses):
            out.update(loss.target_items(f"{prefix}.losses[{w}]"))
        return out

    def __repr__(self):
        return f"WorldLoss({len(self.losses)} worlds: {self.losses[0]!r}, ...)"


class PositionLoss(Loss):
    """``weight * mean over the observed (frame, particle) pairs of |x_i - target_i|^2``:
    with every particle observed, the mean over frames of ``mean_i |x_i - target_i|^2``.

    ``targets``: ``(frames, n, 3)``, one ``(n, 3)`` array per frame, ``{step: (n, 3)}``,
    or one ``(n, 3)`` array for every frame. ``particles``: use only these particles
    (then targets are ``(len(particles), 3)`` per frame). A target row holding NaN is a
    missing observation (an occluded marker): that particle's term at that frame is left
    out of the value, the gradient, ``residuals`` and ``observation_count``. A frame, or a
    target, with no observed particle is refused (it says nothing; leave the frame out).
    """
    _CACHES = ("_wp_targets",)


    def __init__(self, targets, frames=None, weight: float = 1.0, particles=None):
        per = _per_frame("targets", targets, frames, 2)
        super().__init__(list(per), weight, particles)
        self.targets = {f: _points(f"targets at step {f}", t, missing=True) for f, t in per.items()}
        #: ``{step: bool (n,)}``: which particles each frame observes (every one: all True).
        self.observed = {f: np.isfinite(t).all(axis=1) for f, t in self.targets.items()}
        empty = [f for f in self.frames if not self.observed[f].any()]
        if empty:
            every = "every step" if len(empty) == len(self.frames) else f"step{'s' if len(empty) > 1 else ''} {', '.join(map(str, empty))}"
            raise ValueError(f"targets at {every} are not allowed: every point there is NaN (missing), so the frame "
                             "observes nothing; leave such frames out")
        # Each observed (frame, particle) pair weighs the same: the per-frame mean over a
        # frame's own observed count weighed a frame of 2 visible markers as much as one of
        # 200, and then no c had c * value = the sum of squared residuals (diagnostics).
        self._observed_count = int(sum(int(m.sum()) for m in self.observed.values()))
        self._wp_targets = {}

    def _check_count(self, n):
        for frame, t in self.targets.items():
            if t.shape[0] != n:
                raise ValueError(f"targets at step {frame} has {t.shape[0]} points, the positions {n} particles")

    def _launch(self, frame, x, out, scale):
        key = (frame, x.dtype, str(x.device))
        seen = self.observed[frame]
        cached = self._wp_targets.get(key)
        if cached is None:
            # Placeholders of 0 where missing: NaN times a zero weight is NaN in the sum.
            t = wp.array(np.where(seen[:, None], self.targets[frame], 0.0), dtype=x.dtype, device=x.device)
            m = None if seen.all() else wp.array(seen.astype(np.int32), dtype=wp.int32, device=x.device)
            cached = self._wp_targets[key] = (t, m)
        t, m = cached
        S = _scalar_of(x)
        # ``scale`` divides by the frames; this, by the observed pairs per frame: the mean
        # over every observed pair (x.shape[0] itself where nothing is missing).
        per_frame = self._observed_count / len(self.frames)
        self._counts[frame] = int(seen.sum())
        k = _kernels(S)
        if m is None:
            wp.launch(k.squared_distance, x.shape[0], [x, t, S(scale / per_frame)], [out], device=x.device)
        else:
            wp.launch(k.masked_squared_distance, x.shape[0], [x, t, m, S(scale / per_frame)], [out], device=x.device)

    def observation_count(self) -> int:
        return 3 * super().observation_count()

    def residuals(self, positions: Mapping[int, np.ndarray]) -> np.ndarray:
        """The residual vector ``r`` (``sum r^2 = residual_scale() * value``): every
        coordinate of ``x_i - target_i`` of every observed particle at every frame, from
        numpy ``{step: (n, 3)}`` (a missing target's particle has none)."""
        out = []
        for f in self.frames:
            x = np.asarray(positions[f], dtype=np.float64)
            if self.particles is not None:
                x = x[self.particles]
            seen = self.observed[f]
            out.append((x[seen] - self.targets[f][seen]).ravel())
        return np.concatenate(out)

    def target_items(self, prefix: str = "target") -> dict:
        return {**super().target_items(prefix), **{f"{prefix}.targets[{f}]": t for f, t in self.targets.items()}}

    def __repr__(self):
        return f"PositionLoss(frames={list(self.frames)}, weight={self.weight:g})"


class ChamferLoss(Loss):
    """Truncated symmetric Chamfer distance to target point clouds (see the module doc).

    ``targets``: one ``(M, 3)`` cloud for every frame, one per frame, or ``{step: cloud}``;
    clouds may differ in size from the particle count and from each other. ``radius``
    (m): the search radius of both nearest-point searches; choose it above the largest
    expected particle-to-target gap (a few particle spacings), since nothing beyond it
    pulls. After an evaluation ``unmatched[step] = (particles, targets)`` without a
    match within ``radius``.

    ``coverage``: ``"full"`` (default) where the cloud shows the whole body; ``"partial"``
    where it shows part of it (one scanner's view, the top of a sample on a plate): only
    ``mean_j min(d_j^2, r^2)`` over the cloud's points is kept, each to its nearest
    particle, so the particles the scanner never saw are free (``unmatched[step]`` then
    counts 0 particles). The two-way loss pulls those particles onto the scanned side and
    biases the fit (``scan_coverage`` tells such a cloud).

    ``surface_offset`` (m, default 0: the cloud is of particle centres, as a run's own
    output is): how far outside the particles' centres the scanned points lie. A scanner
    sees the material's surface, about dx/2 outside the outer centres (``0.5 *
    model.spacing``, where ``surface.particle_surface`` draws it); compared with the
    centres, such a scan has the body grow to meet it and biases the fit (docs/fitting.md,
    "Losses"). Each matched distance ``d`` then scores ``(d - s)^2``, with ``d`` replaced
    below ``s/2`` by the parabola ``(d^2 + (s/2)^2) / s`` that meets it there with slope 1
    (``|x - y|`` has a cone at 0 whose gradient flips); an unmatched point scores
    ``(radius - s)^2``. Must be below ``radius``.
    """
    #: ``unmatched`` and ``_sizes`` too: what one world's evaluation found is no other's.
    _CACHES = ("_target_data", "_particle_grid", "_scratch", "_pairs", "unmatched", "_sizes", "_free")
    _TAPED = ("_scratch", "_free")  # the nearest points' indices nearest_term's adjoint reads; the free particles' copy


    #: ``full``: the cloud shows the whole body (both directions compared); ``partial``: it
    #: shows part of it (only scan point -> nearest particle).
    COVERAGES = ("full", "partial")

    def __init__(self, targets, radius: float, frames=None, weight: float = 1.0, particles=None, coverage: str = "full",
                 surface_offset: float = 0.0, held=None):
        per = _per_frame("targets", targets, frames, 2)
        super().__init__(list(per), weight, particles)
        # Particles held in place (a particle floor's, a pinned set's; indices into the positions
        # compared): no parameter moves them, and a scan of the sample need not show them, so
        # they are left out of the particle -> nearest point side and stay candidates of the
        # other. Compared there, a floor's 104 particles under a 64-particle pile added constant
        # misfits that the diagnostics took for noise (sigma 0.02 m, a spacing) and called a
        # yield stress fitted to the digit 'not determined' (113 %).
        self.held = None
        if held is not None:
            h = np.unique(np.asarray(checks.host_values("held", held), dtype=np.int64).ravel())
            if h.size and h.min() < 0:
                raise ValueError(f"held = {checks.shorten(h.tolist())!r} is not allowed: give non-negative indices into the "
                                 "positions compared")
            self.held = h if h.size else None
        self.radius = checks.positive("radius", radius)
        self.coverage = checks.choice("coverage", coverage, self.COVERAGES)
        self.surface_offset = checks.non_negative("surface_offset", surface_offset)
        if self.surface_offset >= self.radius:
            raise ValueError(f"surface_offset = {checks.shorten(surface_offset)!r} is not allowed: must be below radius = {self.radius:g} "
                             "(a match is searched within the radius, and the scan lies surface_offset from the particles)")
        self.targets = {}
        for f, t in per.items():
            # Unordered, a cloud has no place to hold a gap: a point not seen is left out.
            pts, repeats = unique_points(_points(f"targets at step {f}", t, unseen=(
                "; a cloud is unordered: leave a point not seen out of it (load_target leaves out a file's NaN rows)")))
            if repeats:
                import warnings  # noqa: PLC0415

                warnings.warn(f"targets at step {f}: {repeats} of its {len(pts) + repeats} points repeat an earlier point "
                              f"exactly; each point is counted once ({len(pts)} points)", stacklevel=2)
            self.targets[f] = pts
        self._target_data = {}
        self._particle_grid = {}
        self._scratch = {}
        self._free = {}
        self.unmatched: dict[int, tuple[int, int]] = {}
        self._sizes: dict[int, tuple[int, int]] = {}  # (particles, target points) per frame, last evaluation

    def _target(self, frame, x):
        key = (frame, x.dtype, str(x.device))
        d = self._target_data.get(key)
        if d is None:
            pts = self.targets[frame]
            y = wp.array(pts, dtype=x.dtype, device=x.device)
            y32 = wp.array(pts.astype(np.float32), dtype=wp.vec3f, device=x.device)
            grid = wp.HashGrid(*_grid_dims(pts, self.radius), device=x.device)
            grid.build(y32, self.radius)
            d = (y, y32, grid)
            self._target_data[key] = d
        return d

    def _buffers(self, frame, x, m):
        key = (frame, x.dtype, str(x.device), x.shape[0], m)
        s = self._scratch.get(key)
        if s is None:
            n = x.shape[0]
            s = types.SimpleNamespace(
                x32=wp.zeros(n, dtype=wp.vec3f, device=x.device),
                idx_x=wp.zeros(n, dtype=wp.int32, device=x.device),
                idx_y=wp.zeros(m, dtype=wp.int32, device=x.device),
                unmatched=wp.zeros(2, dtype=wp.int32, device=x.device),
            )
            self._scratch[key] = s
        return s

    def _launch(self, frame, x, out, scale):
        S = _scalar_of(x)
        k = _kernels(S)
        dev = x.device
        y, y32, ygrid = self._target(frame, x)
        n, m = x.shape[0], y.shape[0]
        s = self._buffers(frame, x, m)
        r = S(self.radius)
        s.unmatched.zero_()
        wp.launch(k.to_float32, n, [x], [s.x32], device=dev, record_tape=False)
        full = self.coverage == "full"
        if full and self.held is None:
            # Particles -> nearest target point (grid on the target, built once); the free ones' below.
            wp.launch(k.nearest, n, [ygrid.id, s.x32, x, y, r], [s.idx_x, s.unmatched[0:1]], device=dev, record_tape=False)
        # Target points -> nearest particle (grid on the particles, rebuilt now).
        xs = s.x32.numpy()
        dims = _grid_dims(xs, self.radius)
        gkey = (frame, str(dev))
        grid = self._particle_grid.get(gkey)
        if grid is None or grid[0] != dims:
            grid = (dims, wp.HashGrid(*dims, device=dev))
            self._particle_grid[gkey] = grid
        grid[1].build(s.x32, self.radius)
        wp.launch(k.nearest, m, [grid[1].id, y32, y, x, r], [s.idx_y, s.unmatched[1:2]], device=dev, record_tape=False)
        self._keep.extend([ygrid, grid[1]])
        r2 = S(self.radius * self.radius)
        xp, sp, nf = x, s, n  # the particle -> nearest point side: the free particles
        if full and self.held is not None:
            xp, sp = self._free_side(frame, x, m, k)
            nf = xp.shape[0]
            sp.unmatched.zero_()
            wp.launch(k.to_float32, nf, [xp], [sp.x32], device=dev, record_tape=False)
            wp.launch(k.nearest, nf, [ygrid.id, sp.x32, xp, y, r], [sp.idx_x, sp.unmatched[0:1]], device=dev,
                      record_tape=False)
        if self.surface_offset > 0.0:
            so, eps = S(self.surface_offset), S(self._smoothing())
            if full:
                wp.launch(k.offset_term, nf, [xp, y, sp.idx_x, r, so, eps, S(scale / nf)], [out], device=dev)
            wp.launch(k.offset_term, m, [y, x, s.idx_y, r, so, eps, S(scale / m)], [out], device=dev)
        else:
            if full:
                wp.launch(k.nearest_term, nf, [xp, y, sp.idx_x, r2, S(scale / nf)], [out], device=dev)
            wp.launch(k.nearest_term, m, [y, x, s.idx_y, r2, S(scale / m)], [out], device=dev)
        um = s.unmatched.numpy()
        self.unmatched[frame] = (int(sp.unmatched.numpy()[0]) if sp is not s else int(um[0]), int(um[1]))
        self._sizes[frame] = (nf, m)
        watch = getattr(self, "_coverage_watch", None)
        if full and watch is not None and frame not in watch[2]:
            watch[2].add(frame)
            xs = x.numpy()
            self._warn_partial_scan(frame, xs[watch[0]], watch[1], watch[3], xs[watch[4]])

    def _free_indices(self, n: int) -> np.ndarray:
        """The compared particles not ``held`` (indices into positions of ``n`` particles)."""
        if int(self.held.max()) >= n:
            raise ValueError(f"held has index {int(self.held.max())}, the positions compared only {n} particles")
        free = np.setdiff1d(np.arange(n), self.held)
        if not free.size:
            raise ValueError(f"held = every one of the {n} particles compared is not allowed: the particle side compares none")
        return free

    def _free_side(self, frame, x, m, k):
        """The free particles' positions, gathered on the tape (their adjoint scattered back),
        and their own search buffers."""
        key = (frame, x.dtype, str(x.device), x.shape[0])
        f = self._free.get(key)
        if f is None:
            idx = wp.array(self._free_indices(x.shape[0]).astype(np.int32), dtype=wp.int32, device=x.device)
            f = (idx, wp.zeros(idx.shape[0], dtype=x.dtype, device=x.device, requires_grad=True))
            self._free[key] = f
        idx, xf = f
        wp.launch(k.gather, idx.shape[0], [x, idx], [xf], device=x.device)
        return xf, self._buffers(("free", frame), xf, m)

    def watch_coverage(self, surface, spacing: float, what: str = "target", held=()) -> None:
        """Check, at the first evaluation of each frame, whether a ``coverage="full"`` cloud
        shows only part of the body (``scan_coverage`` of the particles ``surface``, indices
        into the positions this loss compares), and warn naming ``what`` where it does. A fit
        asks it of each such loss with the model's surface particles. ``held``: surface
        particles held in place (a pinned set, a particle floor), indices as ``surface``'s:
        a scan need not show them (``scan_coverage``'s ``held``)."""
        self._coverage_watch = (np.asarray(surface, dtype=np.int64), float(spacing), set(), what,
                                np.asarray(held, dtype=np.int64))

    def copy_for_world(self) -> "ChamferLoss":
        """As ``Loss.copy_for_world``, with a coverage watch of its own (``watch_coverage``):
        the same surface, but the frames checked counted per world. Shared, the first world
        to reach a frame marked it checked, and a world whose body the cloud shows only part
        of was never checked (one loss given for worlds of different bodies)."""
        new = super().copy_for_world()
        watch = vars(self).get("_coverage_watch")
        if watch is not None:
            new._coverage_watch = (watch[0], watch[1], set(), *watch[3:])
        return new

    def _warn_partial_scan(self, frame: int, surface: np.ndarray, spacing: float, what: str,
                           held: np.ndarray | None = None) -> None:
        if len(surface) == 0:
            return
        unseen, stray, distance = scan_coverage(surface, self.targets[frame], spacing, held=held)
        if unseen >= UNSEEN_SHARE and stray <= COVERED_NEAR:
            import warnings  # noqa: PLC0415

            warnings.warn(f"{what}: the point cloud at step {frame} looks like a scan of part of the body: {unseen:.0%} "
                          f"of the body's surface particles lie more than {distance:.3g} m from every point of it, "
                          f"while {stray:.0%} of its points lie that far from the body. A full-coverage (two-way) "
                          "loss pulls the particles the scanner never saw onto the scanned side and biases the fit: "
                          "give a scan of part of the body as coverage='partial' (warp-esph fit --cloud-coverage "
                          "partial)", UserWarning, stacklevel=2)

    def out_of_reach(self) -> str | None:
        """Where no particle and no target point met within ``radius`` in any frame of the last
        evaluation: the loss is the constant ``2 radius^2`` and its gradient 0 (a cloud in mm,
        or far from the body)."""
        if self.coverage == "partial":
            # Only the cloud's points are searched: out of reach where none found a particle.
            if not self.unmatched or any(self.unmatched[f][1] != self._sizes.get(f, (0, -1))[1] for f in self.unmatched):
                return None
        elif not self.unmatched or any(self.unmatched[f] != self._sizes.get(f) for f in self.unmatched):
            return None
        return (f"no target point of the point clouds lies within radius = {self.radius:g} m of a particle in any "
                f"frame (targets in other units than metres, or placed elsewhere?)")

    def _smoothing(self) -> float:
        # Half the offset: the distance is exact from there out, and a scan point lies about
        # the offset from its particle, so the parabola only shapes points that sit nearly on
        # a particle centre, where the exact term's gradient would flip.
        return 0.5 * self.surface_offset

    def _gap(self, d2: np.ndarray) -> np.ndarray:
        """``surface_gap``'s ``d - s`` on the host (the residuals' and the tests' reference)."""
        eps, s = self._smoothing(), self.surface_offset
        d = np.where(d2 < eps * eps, (d2 + eps * eps) / (2.0 * eps), np.sqrt(np.maximum(d2, eps * eps)))
        return d - s

    def reset_residuals(self):
        """Forget the correspondences ``residuals`` fixed (the next call chooses them anew)."""
        self._pairs = {}

    def correspondences(self):
        """The nearest points ``residuals`` keeps now (``{step: (ix, iy)}``, None before any
        call), for ``set_correspondences``: a Gauss-Newton Jacobian's columns read those of
        the point they difference from, not a later trial's."""
        return getattr(self, "_pairs", None)

    def set_correspondences(self, kept) -> None:
        """Keep ``kept`` (a ``correspondences()`` answer) for the next ``residuals``."""
        self._pairs = kept

    def residuals(self, positions) -> np.ndarray:
        """A residual vector for Gauss-Newton diagnostics (numpy, from ``{step: (n, 3)}``):
        ``x_i - y_nn(i)`` and ``y_j - x_nn(j)`` with the nearest points chosen at the first
        call after ``reset_residuals`` and then kept (so the vector is smooth in the
        parameters, as the loss's own gradient is for fixed choices), each scaled so that
        ``sum r^2 = residual_scale() * value`` where every point has a match within
        ``radius``; a point without one adds the constant ``radius``. Kept pairs count motion
        along the surface as observed, which a cloud does not see: standard errors from it
        are lower bounds."""
        pairs = getattr(self, "_pairs", None)
        if pairs is None:
            pairs = self._pairs = {}
        out = []
        for f in self.frames:
            x = np.asarray(positions[f], dtype=np.float64)
            if self.particles is not None:
                x = x[self.particles]
            y = self.targets[f]
            xf = x if self.held is None else x[self._free_indices(len(x))]  # the particle side's
            n, m = len(xf), len(y)
            if f not in pairs:
                ix = _nearest_within(xf, y, self.radius) if self.coverage == "full" else None
                pairs[f] = (ix, _nearest_within(y, x, self.radius))
            ix, iy = pairs[f]
            half = 0.5 * (n + m)
            sides = ((xf, y, ix, n), (y, x, iy, m))
            if self.coverage == "partial":
                half, sides = m, sides[1:]  # mean_j d_j^2 alone: m points per frame
            for src, dst, idx, count in sides:
                r = np.where(idx[:, None] >= 0, src - dst[np.maximum(idx, 0)], 0.0)
                if self.surface_offset > 0.0:
                    # One residual a point: its distance to the offset surface (the normal
                    # gap), which is all the offset term scores.
                    r = self._gap((r * r).sum(axis=1))[idx >= 0]
                    r = np.concatenate([r, np.full(int((idx < 0).sum()), self.radius - self.surface_offset)])
                    out.append(math.sqrt(half / count) * r)
                    continue
                r = np.concatenate([r.ravel(), np.full(int((idx < 0).sum()), self.radius)])
                out.append(math.sqrt(half / count) * r)
        return np.concatenate(out)

    def residual_scale(self) -> float:
        # mean_i d_i^2 + mean_j d_j^2: with n particles and m target points, (n + m) / 2
        # points per frame give the same sum when every residual is alike.
        m = float(np.mean([len(self.targets[f]) for f in self.frames]))
        if self.coverage == "partial":
            return len(self.frames) * m / self.weight
        return len(self.frames) * 0.5 * (self._particle_side() + m) / self.weight

    def _particle_side(self) -> float:
        """Particles per frame on the particle -> nearest point side (the held ones left out)."""
        n = self._points_per_frame()
        return n if self.held is None else float(len(self._free_indices(int(round(n)))))

    def observation_count(self) -> int:
        m = float(np.mean([len(self.targets[f]) for f in self.frames]))
        if self.coverage == "partial":
            return int(round(len(self.frames) * m))
        return int(round(len(self.frames) * (self._particle_side() + m)))

    def target_items(self, prefix: str = "target") -> dict:
        return {**super().target_items(prefix), f"{prefix}.radius": self.radius, f"{prefix}.coverage": self.coverage,
                f"{prefix}.surface_offset": self.surface_offset,
                **{f"{prefix}.targets[{f}]": t for f, t in self.targets.items()}}

    def __repr__(self):
        shown = "" if self.coverage == "full" else f", coverage={self.coverage!r}"
        shown += f", surface_offset={self.surface_offset:g}" if self.surface_offset > 0.0 else ""
        return f"ChamferLoss(frames={list(self.frames)}, radius={self.radius:g}, weight={self.weight:g}{shown})"


class MeshLoss(Loss):
    """``weight * mean over frames of mean_i min(d(x_i, mesh)^2, max_dist^2)``.

    ``mesh``: a mesh file (anything ``warp_esph.meshes.load_mesh`` reads) or
    ``(points, triangles)`` (``load_mesh(path, prim_path=...)`` reads one Mesh prim of a USD
    file that shows several), for every frame, or ``{step: mesh}``. ``mode``:
    ``"surface"`` (unsigned distance: every particle is pulled onto the surface; use
    with ``particles=surface_particles(model)``) or ``"outside"`` (particles inside the
    closed mesh contribute 0: the body is pulled inside the shape). ``max_dist`` (m):
    search distance; particles with no surface within it contribute ``max_dist**2``
    without gradient. ``unmatched[step]`` counts them after an evaluation.
    """
    _CACHES = ("_wp", "_scratch", "_planes", "unmatched", "_sizes")  # unmatched: per world, as ChamferLoss's
    _TAPED = ("_scratch",)  # the closest points and codes mesh_term's adjoint reads


    MODES = ("surface", "outside")

    def __init__(self, mesh, frames=None, mode: str = "surface", max_dist: float = 1.0, weight: float = 1.0, particles=None):
        if isinstance(mesh, Mapping):
            per = _per_frame("mesh", mesh, frames, 2)
        else:
            if frames is None:
                raise ValueError("frames is required: say at which step indices the mesh applies")
            per = {f: mesh for f in _frames(frames)}
        super().__init__(list(per), weight, particles)
        self.mode = checks.choice("mode", mode, self.MODES)
        # Its square is the far particles' value, passed to Warp in float32: 1e200 overflowed.
        self.max_dist = checks.in_range("max_dist", max_dist, 1e-12, 1e15)
        self.meshes = {f: self._load(m) for f, m in per.items()}
        self._wp = {}
        self._scratch = {}
        self.unmatched: dict[int, int] = {}
        self._sizes: dict[int, int] = {}  # particles per frame at the last evaluation

    @staticmethod
    def _load(mesh):
        if isinstance(mesh, (str, bytes, os.PathLike)):
            from . import meshes  # noqa: PLC0415

            points, tris = meshes.load_mesh(mesh, name="mesh")
        else:
            try:
                points, tris = mesh
            except (TypeError, ValueError):
                raise ValueError("mesh is not allowed: give a mesh file or a (points, triangles) pair") from None
        points = _points("mesh points", points)
        tris = np.asarray(tris)
        if tris.ndim != 2 or tris.shape[1] != 3 or len(tris) == 0 or not np.issubdtype(tris.dtype, np.integer):
            raise ValueError(f"mesh triangles with shape {tris.shape} is not allowed: must be (T, 3) integers")
        if tris.min() < 0 or tris.max() >= len(points):
            raise ValueError("mesh triangles are not allowed: they index points that do not exist")
        return points, tris.astype(np.int32)

    def _mesh(self, frame, x):
        key = (frame, x.dtype, str(x.device))
        d = self._wp.get(key)
        if d is None:
            points, tris = self.meshes[frame]
            flat = wp.array(tris.reshape(-1), dtype=wp.int32, device=x.device)
            mesh = wp.Mesh(
                points=wp.array(points.astype(np.float32), dtype=wp.vec3f, device=x.device),
                indices=flat,
                support_winding_number=self.mode == "outside",
            )
            verts = wp.array(points, dtype=x.dtype, device=x.device)
            d = (mesh, verts, flat)
            self._wp[key] = d
        return d

    def _launch_query(self, frame, x):
        """Untaped: the closest point and code of every particle (into the frame's scratch)."""
        S = _scalar_of(x)
        k = _kernels(S)
        dev = x.device
        mesh, verts, flat = self._mesh(frame, x)
        n = x.shape[0]
        key = (frame, x.dtype, str(dev), n)
        s = self._scratch.get(key)
        if s is None:
            s = types.SimpleNamespace(
                closest=wp.zeros(n, dtype=x.dtype, device=dev),
                code=wp.zeros(n, dtype=wp.int32, device=dev),
                unmatched=wp.zeros(1, dtype=wp.int32, device=dev),
            )
            self._scratch[key] = s
        s.unmatched.zero_()
        wp.launch(
            k.closest_on_mesh, n,
            [mesh.id, x, verts, flat, wp.float32(self.max_dist), int(self.mode == "outside")],
            [s.closest, s.code, s.unmatched], device=dev, record_tape=False,
        )
        self._keep.append(mesh)
        return s

    def _launch(self, frame, x, out, scale):
        S = _scalar_of(x)
        s = self._launch_query(frame, x)
        n = x.shape[0]
        wp.launch(_kernels(S).mesh_term, n, [x, s.closest, s.code, S(self.max_dist**2), S(scale / n)], [out], device=x.device)
        self.unmatched[frame] = int(s.unmatched.numpy()[0])
        self._sizes[frame] = n

    def out_of_reach(self) -> str | None:
        """Where no particle came within ``max_dist`` of the mesh in any frame of the last
        evaluation: every particle adds the constant ``max_dist^2`` and the gradient is 0."""
        if not self.unmatched or any(self.unmatched[f] != self._sizes.get(f) for f in self.unmatched):
            return None
        return (f"no particle lies within max_dist = {self.max_dist:g} m of the target mesh in any frame (a mesh in "
                f"other units than metres, or placed elsewhere?)")

    def reset_residuals(self):
        """Forget the closest points and normals ``residuals`` fixed."""
        self._planes = {}

    def correspondences(self):
        """The tangent planes ``residuals`` keeps now (``{step: (c0, n0, code)}``, None before
        any call), for ``set_correspondences`` (``ChamferLoss.correspondences``)."""
        return getattr(self, "_planes", None)

    def set_correspondences(self, kept) -> None:
        """Keep ``kept`` (a ``correspondences()`` answer) for the next ``residuals``."""
        self._planes = kept

    def residuals(self, positions) -> np.ndarray:
        """A residual vector for Gauss-Newton diagnostics (numpy, from ``{step: (n, 3)}``):
        ``n0 . (x_i - c0_i)``, the distance to the tangent plane at the closest point ``c0``
        chosen at the first call after ``reset_residuals`` (``n0`` the unit direction from
        ``c0`` to the particle then), so motion along the surface is not counted as
        observed; particles with nothing within ``max_dist`` add the constant ``max_dist``,
        those inside in ``outside`` mode and those exactly on the surface add 0. At the
        first call ``sum r^2 = residual_scale() * value``."""
        planes = getattr(self, "_planes", None)
        if planes is None:
            planes = self._planes = {}
        out = []
        for f in self.frames:
            x = np.asarray(positions[f], dtype=np.float64)
            if self.particles is not None:
                x = x[self.particles]
            if f not in planes:
                xw = wp.array(x, dtype=wp.vec3d)
                with self._own_buffers():  # not a caller's launch's, which its backward reads
                    s = self._launch_query(f, xw)
                    c, code = s.closest.numpy().astype(np.float64), s.code.numpy()
                d = x - c
                norm = np.linalg.norm(d, axis=1)
                normal = np.where(norm[:, None] > 1e-12, d / np.maximum(norm, 1e-300)[:, None], 0.0)
                normal[code != 1] = 0.0
                planes[f] = (c, normal, code)
            c, normal, code = planes[f]
            r = np.einsum("ij,ij->i", normal, x - c)
            out.append(np.concatenate([r, np.full(int((code < 0).sum()), self.max_dist)]))
        return np.concatenate(out)

    def target_items(self, prefix: str = "target") -> dict:
        out = {**super().target_items(prefix), f"{prefix}.mode": self.mode, f"{prefix}.max_dist": self.max_dist}
        for f, (points, tris) in self.meshes.items():
            out[f"{prefix}.meshes[{f}].points"], out[f"{prefix}.meshes[{f}].triangles"] = points, tris
        return out

    def __repr__(self):
        return f"MeshLoss(frames={list(self.frames)}, mode={self.mode!r}, weight={self.weight:g})"


def _nearest_within(a: np.ndarray, b: np.ndarray, radius: float, chunk: int = 1024) -> np.ndarray:
    """Index of the nearest point of ``b`` to each point of ``a`` within ``radius`` (-1: none)."""
    out = np.full(len(a), -1, dtype=np.int64)
    for s in range(0, len(a), chunk):
        d2 = ((a[s: s + chunk, None, :] - b[None, :, :]) ** 2).sum(axis=2)
        k = d2.argmin(axis=1)
        ok = d2[np.arange(len(k)), k] < radius * radius
        out[s: s + chunk] = np.where(ok, k, -1)
    return out


#: ``scan_coverage``'s sign of a cloud that shows part of the body: at least this share of
#: the surface particles far from every point of it, while at most ``COVERED_NEAR`` of its
#: points lie far from the body (a top-half scan of a cylinder: 45 % and 0 %; a full scan,
#: a guess that spread more or less than the scan: both shares alike).
UNSEEN_SHARE = 0.25
COVERED_NEAR = 0.05


def _far_share(a: np.ndarray, b: np.ndarray, distance: float, sample: int = 2000, chunk: int = 256) -> float:
    """The share of ``a``'s points farther than ``distance`` from every point of ``b``, from
    at most ``sample`` of them, evenly strided (a scan of 10^5 points is not squared)."""
    if len(a) > sample:
        a = a[np.linspace(0, len(a) - 1, sample).astype(np.int64)]
    far = 0
    for s in range(0, len(a), chunk):
        d2 = ((a[s: s + chunk, None, :] - b[None, :, :]) ** 2).sum(axis=2)
        far += int((d2.min(axis=1) > distance * distance).sum())
    return far / len(a)


def scan_coverage(surface: np.ndarray, cloud: np.ndarray, spacing: float, held=None) -> tuple[float, float, float]:
    """How much of a body a cloud shows: ``(unseen, stray, distance)``, the share of the
    ``surface`` particles' positions ``(n, 3)`` farther than ``distance`` from every point of
    ``cloud`` ``(m, 3)``, and the share of the cloud's points that far from every surface
    particle. ``distance`` is 1.5 times the larger of the particle ``spacing`` and the
    cloud's own (median nearest-neighbour distance): a sparse but full scan leaves gaps of
    its own spacing, not more. A cloud of part of the body leaves many surface particles
    unseen while its points all lie on the body (``UNSEEN_SHARE``, ``COVERED_NEAR``).

    ``held``: positions ``(k, 3)`` of surface particles held in place (a pinned set, a
    particle floor, ``SceneBuilder.add_particle_floor``), not in ``surface``. A scan of the
    sample alone need not show them, so they are not in the unseen share (a full scan of a
    block on a floor left 59 % of the surface unseen, the floor's); a cloud point near one
    is still on the body (not stray)."""
    surface = np.asarray(surface, dtype=np.float64)
    cloud = np.asarray(cloud, dtype=np.float64)
    body = surface
    if held is not None and len(held):
        body = np.concatenate([surface, np.asarray(held, dtype=np.float64).reshape(-1, 3)])
    own = 0.0
    if len(cloud) > 1:
        probe = cloud if len(cloud) <= 512 else cloud[np.linspace(0, len(cloud) - 1, 512).astype(np.int64)]
        gaps = []
        for s in range(0, len(probe), 64):
            d2 = ((probe[s: s + 64, None, :] - cloud[None, :, :]) ** 2).sum(axis=2)
            d2[d2 == 0.0] = np.inf  # the point itself
            gaps.append(np.sqrt(d2.min(axis=1)))
        gaps = np.concatenate(gaps)
        gaps = gaps[np.isfinite(gaps)]
        own = float(np.median(gaps)) if len(gaps) else 0.0
    distance = 1.5 * max(float(spacing), own)
    return _far_share(surface, cloud, distance), _far_share(cloud, body, distance), distance


def surface_particles(model) -> np.ndarray:
    """Indices of the particles on a body's surface in the model's initial configuration.

    Particles are on each body's lattice; one is on the surface when any of its six face
    neighbours on the lattice is not a particle of the same body.
    """
    x = np.asarray(model.particle_x0, dtype=np.float64)
    body = np.asarray(model.particle_body_np, dtype=np.int64)
    q = np.zeros((len(x), 3), dtype=np.int64)
    for b in np.unique(body):
        sel = body == b
        q[sel] = np.round((x[sel] - x[sel].min(axis=0)) / model.spacing).astype(np.int64) + 1
    dims = q.max(axis=0) + 2

    def encode(c):
        return ((body * dims[0] + c[:, 0]) * dims[1] + c[:, 1]) * dims[2] + c[:, 2]

    keys = np.sort(encode(q))
    free = np.zeros(len(x), dtype=bool)
    for axis in range(3):
        for sign in (-1, 1):
            c = q.copy()
            c[:, axis] += sign
            k = encode(c)
            pos = np.clip(np.searchsorted(keys, k), 0, len(keys) - 1)
            free |= keys[pos] != k
    return np.flatnonzero(free).astype(np.int32)


# ------------------------------------------------------------ reaction forces
_AXES = {"x": 0, "y": 1, "z": 2}


class ReactionForceLoss(Loss):
    """A tool's or a static collider's reaction force over time (a force-displacement curve):
    ``weight * mean over observed windows of |P (F_j - target_j)|^2``.

    ``F_j`` is the mean over the ``window`` steps ending at step ``steps[j]`` of the force the
    ``tool`` exerted on the material (``warp_esph.tools``: ``state.reaction_force``), i.e.
    what ``warp-esph run`` writes per frame to ``<output>_tools.csv`` with ``window`` =
    steps per frame. ``tool`` may also name a static collider as ``Solver.collider_reactions``
    does (``"plane0"``, the first plane or ground; ``"sphere0"``, ``"box0"``; ``"w<w>/..."``
    with worlds): its ``state.collider_force`` row. ``P`` keeps ``components`` (``"xyz"`` default, or e.g. ``"y"``, the
    loading axis of a compression test). ``targets``: ``(K, len(components))`` newtons (or
    ``(K,)`` with one component), one row per entry of ``steps``.

    The loss observes the rollout's step forces (``Rollout.observations()`` under
    ``rollout.FORCES``), not positions: its ``frames`` are the window ends, so that a fit
    runs long enough. Its arithmetic (a few numbers per step) is done on the host with its
    exact gradient, which ``Rollout.backward`` seeds into each step's reaction-force adjoint
    (a static collider's: its ``collider_force`` adjoint); the gradient through the
    simulation is the tape's.

    ``noise``: the force measurement's standard deviation (N) for ``warp_esph.diagnostics``.
    Default None: the diagnostics estimate it from the curve's residuals at the optimum
    (``sqrt(SSR / (N - P))``, ``diagnostics.estimated_noise``), at least 1 % of the target's RMS force (``noise`` then holds that floor, ``noise_stated`` is
    False), as positions' noise is estimated; a fixed 1 % had been taken for the noise whatever
    the curve's scatter, so a curve measured with 3 % noise got standard errors 0.41 x the
    fitted values' spread over noise draws, and a curve the model cannot follow was reported
    determined to 0.7 %.
    """

    _host = True

    def __init__(self, targets, tool: str | int, steps, window: int = 1, components: str = "xyz",
                 weight: float = 1.0, noise: float | None = None):
        # Whole step indices as frames are (int() took 2.7 as 2, "3" as 3 and True as 1).
        steps = list(_frames(np.ravel(steps).tolist() if isinstance(steps, np.ndarray) else steps))
        super().__init__(steps, weight)
        if list(self.frames) != steps:
            raise ValueError(f"steps = {checks.shorten(steps)!r} is not allowed: window end steps must be distinct and increasing")
        self.window = checks.positive_int("window", window)
        if steps[0] < self.window:
            raise ValueError(f"steps[0] = {steps[0]} is not allowed: the first window of {self.window} steps must end "
                             f"at step >= {self.window}")
        comps = str(components).lower()
        if not comps or any(c not in _AXES for c in comps) or len(set(comps)) != len(comps):
            raise ValueError(f"components = {checks.shorten(components)!r} is not allowed: give distinct axes among x, y, z (e.g. 'y')")
        self.components = comps
        self._axes = [_AXES[c] for c in comps]
        targets = checks.host_values("targets", targets)
        checks.real_numbers("targets", targets, "must be numbers (N)")
        try:
            t = np.asarray(targets, dtype=np.float64)
        except checks.ARRAY_ERRORS:
            raise ValueError(f"targets = {checks.shorten(targets)!r} is not allowed: must be numbers (N)") from None
        if t.ndim == 1 and len(comps) == 1:
            t = t[:, None]
        if t.shape != (len(steps), len(comps)):
            raise ValueError(f"targets with shape {t.shape} is not allowed: must be ({len(steps)}, {len(comps)}) finite "
                             f"newtons, one row per window, one column per component ({comps})")
        bad = np.argwhere(~np.isfinite(t))
        if len(bad):
            j, c = (int(i) for i in bad[0])
            raise ValueError(f"targets[{j}][{c}] = {checks.shorten(float(t[j, c]))!r} is not allowed: must be a finite force (N) (window ending "
                             f"at step {steps[j]}, component {comps[c]})")
        # Before the default noise squares them (its RMS overflowed past 1.3e154 N and the force
        # was refused as 'noise = inf', a value the caller never gave).
        checks.squarable_coordinates("targets", t, "float64", lambda w: f"window ending at step {steps[w[0]]}, "
                                     f"component {comps[w[1]]}", quantity="force", unit="N", hint="give forces in newtons")
        self.targets = t
        if isinstance(tool, bool) or not isinstance(tool, (str, int, np.integer)):
            raise ValueError(f"tool = {checks.shorten(tool)!r} is not allowed: give the tool's or static collider's name, or the tool's index")
        self.tool = tool
        #: Whether ``noise`` was given (else it is the floor of the diagnostics' estimate).
        self.noise_stated = noise is not None
        if noise is None:
            rms = float(np.sqrt(np.mean(t**2)))
            noise = 0.01 * rms if rms > 0 else 1.0
        self.noise = checks.noise("noise", noise)

    #: The unit of ``noise`` and of the residuals (the diagnostics' messages).
    noise_unit = "N"

    @property
    def term_name(self) -> str:
        return f"force curve of {self.tool!r}"

    # The positions of a frame are not observed.
    def launch(self, frame, x, out, scale: float = 1.0):
        return

    def _source(self, obs) -> tuple[str, int]:
        """The observation key (``rollout.FORCES`` or ``COLLIDER_FORCES``) and row of ``tool``."""
        from .rollout import COLLIDER_FORCES, COLLIDER_NAMES, FORCES, TOOL_NAMES  # noqa: PLC0415 (rollout imports the model, not losses)

        tools = list(obs.get(TOOL_NAMES, [])) if FORCES in obs else []
        static = list(obs.get(COLLIDER_NAMES, [])) if COLLIDER_FORCES in obs else []
        if not tools and not static:
            raise ValueError("a ReactionForceLoss is not allowed here: the observations hold no reaction forces "
                             "(the scene has no tools or static colliders, or the caller passed positions only)")
        if isinstance(self.tool, str):
            if self.tool in tools:
                return FORCES, tools.index(self.tool)
            if self.tool in static:
                return COLLIDER_FORCES, static.index(self.tool)
            raise ValueError(f"tool = {checks.shorten(self.tool)!r} is not allowed: the scene's tools are {', '.join(tools) or 'none'}, "
                             f"its static colliders {', '.join(static) or 'none'}")
        if not 0 <= int(self.tool) < len(tools):
            raise ValueError(f"tool = {checks.shorten(self.tool)!r} is not allowed: tool indices are 0..{len(tools) - 1}"
                             if tools else f"tool = {checks.shorten(self.tool)!r} is not allowed: the scene has no tools (give a static "
                             f"collider's name: {', '.join(static)})")
        return FORCES, int(self.tool)

    def _forces(self, obs) -> tuple[np.ndarray, int, str]:
        from .rollout import COLLIDER_NAMES, FORCES, TOOL_NAMES  # noqa: PLC0415

        key, row = self._source(obs)
        names = list(obs[TOOL_NAMES if key == FORCES else COLLIDER_NAMES])
        f = obs[key]
        f = f.numpy() if isinstance(f, wp.array) else np.asarray(f)
        f = np.asarray(f, dtype=np.float64).reshape(-1, len(names), 3)
        if self.frames[-1] > f.shape[0]:
            raise ValueError(f"the loss observes up to step {self.frames[-1]}, the rollout ran {f.shape[0]} steps")
        return f, row, key

    def curve(self, obs) -> np.ndarray:
        """The simulated window means ``F_j`` (``(K, len(components))``, N)."""
        f, c, _ = self._forces(obs)
        w = self.window
        return np.stack([f[e - w:e, c].mean(axis=0)[self._axes] for e in self.frames])

    def residuals(self, obs) -> np.ndarray:
        return (self.curve(obs) - self.targets).ravel()

    #: ``opposite_sign`` speaks where the target negated, at the model's size, leaves at most
    #: this share of the misfit of the target at that size (a cosine of -1/3 or less).
    OPPOSITE_SHARE = 0.5

    def opposite_sign(self, obs) -> str | None:
        """A sentence where the simulated curve points against the target (a negative cosine
        over the observed windows, the two curves' RMS within ``SIZE_MISMATCH`` of each other,
        where ``size_mismatch`` is silent): it then fits worse than no force at all. A log of
        the force on the tool, or of compression counted positive, measures the negative of the
        force the tool exerts on the material, which no material value reaches: a fit drove mu
        from 8000 to 7 Pa and said only that it had not converged. Said only where the target
        negated, scaled to the model's RMS, would leave at most ``OPPOSITE_SHARE`` of the misfit
        of the target so scaled: a curve at a cosine near 0 (columns swapped: -0.00) is not
        mended by negating it, nor is a log of zeros whose round-off points against the model's
        (the size's note says what it is), and both were told to be. The scale keeps the test
        to the direction: compared at their own sizes, a negated log of a guess 6 to 10 times
        as stiff as the sample (or 0.1 to 0.17 times) was said nothing of."""
        sim = self.curve(obs)
        s, t = float(np.linalg.norm(sim)), float(np.linalg.norm(self.targets))
        if not s * t > 0.0 or not t / self.SIZE_MISMATCH < s < t * self.SIZE_MISMATCH:
            return None
        cosine = float(np.sum(sim * self.targets)) / (s * t)
        scaled = self.targets * (s / t)
        negated = float(np.sum((sim + scaled) ** 2))
        if cosine >= 0.0 or negated > self.OPPOSITE_SHARE * float(np.sum((sim - scaled) ** 2)):
            return None
        return (f"the {self.term_name} points against the model's (cosine {cosine:.2f} over the observed windows; no "
                "force at all would fit it better): the target is the force the tool exerts on the material, and a log "
                "of the force on the tool, or of compression counted positive, is its negative (negate its columns)")

    def other_axes(self, obs) -> str | None:
        """A sentence where the target's force lies mostly along another axis than the simulated
        curve's (each along its largest component by more than half its sum of squares, their
        sizes within ``SIZE_MISMATCH``): a lab's log whose vertical force is fz (z up, where a
        y-up scene's is fy) or whose columns are in another order fits as a force the model never
        exerts, and the fit drives the material soft, said only as undetermined. The loss does
        not know the scene's up axis (a scene may stand along z), so the sentence names none."""
        if len(self._axes) < 2:
            return None
        sim = self.curve(obs)
        s2, t2 = np.sum(sim**2, axis=0), np.sum(self.targets**2, axis=0)
        a, b = int(np.argmax(t2)), int(np.argmax(s2))
        if (a == b or not t2[a] > 0.5 * t2.sum() or not s2[b] > 0.5 * s2.sum()
                or not s2.sum() * self.SIZE_MISMATCH**2 > t2.sum() > s2.sum() / self.SIZE_MISMATCH**2):
            return None
        cosine = float(np.sum(sim * self.targets)) / float(np.sqrt(s2.sum() * t2.sum()))
        k = len(self.frames)
        return (f"the {self.term_name} lies along {self.components[a]} (RMS {np.sqrt(t2[a] / k):.3g} N), the model's along "
                f"{self.components[b]} (RMS {np.sqrt(s2[b] / k):.3g} N; cosine {cosine:.2f} over the observed windows): "
                "its columns fx, fy, fz are in another order, or in the lab's axes, not the scene's (a z-up lab's fz is a "
                "y-up scene's fy)")

    #: A target this many times larger or smaller (RMS) than the fitted curve is named (``size_mismatch``).
    SIZE_MISMATCH = 10.0

    def size_mismatch(self, obs) -> str | None:
        """A sentence where the target's RMS force is ``SIZE_MISMATCH`` times the simulated
        curve's or more (or that much smaller). At a fit's end this is a curve the fit could
        not reach: a log in mN read as newtons is 1000 times the force, and a fit with mu
        bounded where the material could be ran mu to its bound, which the diagnostics named
        as held there, not that the curve was still hundreds of times short. Nothing in the
        numbers tells a unit slip from a scene that does not press as the experiment did, so
        both are said."""
        sim = float(np.sqrt(np.mean(self.curve(obs) ** 2)))
        target = float(np.sqrt(np.mean(self.targets**2)))
        f = self.SIZE_MISMATCH
        if not target > 0.0 or target / f < sim < target * f:
            return None
        if sim > 0.0:
            ratio = max(target, sim) / min(target, sim)
            size = f"{ratio:.3g} times {'larger' if target > sim else 'smaller'} than the fitted curve"
        else:
            size = "larger than the fitted curve, which is 0"
        return (f"the {self.term_name} is {size} (RMS {target:.3g} N against {sim:.3g} N at the fitted values): the fit "
                "could not reach its size (a value held at a bound, a scene that does not load the material as the "
                "experiment did, or a log in another unit than newtons: a log in mN read as newtons is 1000 times too "
                "large, one in kN 1000 times too small)")

    def value_and_grad(self, obs):
        f, c, key = self._forces(obs)
        r = self.curve(obs) - self.targets
        K, w = len(self.frames), self.window
        value = self.weight / K * float(np.sum(r * r))
        g = np.zeros_like(f)
        for j, e in enumerate(self.frames):
            g[e - w:e, c, self._axes] += (2.0 * self.weight / (K * w)) * r[j]
        return value, {key: g}

    def residual_scale(self) -> float:
        return len(self.frames) / self.weight

    def observation_count(self) -> int:
        return len(self.frames) * len(self._axes)

    def target_items(self, prefix: str = "target") -> dict:
        return {**super().target_items(prefix), f"{prefix}.targets": self.targets, f"{prefix}.tool": self.tool,
                f"{prefix}.window": self.window, f"{prefix}.components": self.components}

    def __repr__(self):
        return (f"ReactionForceLoss(tool={self.tool!r}, {len(self.frames)} windows of {self.window} steps, "
                f"components={self.components!r}, weight={self.weight:g})")

    @classmethod
    def from_csv(cls, path, tool: str, frame_steps, components: str = "xyz", frames=None, weight: float = 1.0,
                 noise: float | None = None) -> "ReactionForceLoss":
        """The loss for the ``tool`` rows of a ``<output>_tools.csv`` (``warp-esph run``):
        ``frame_steps`` maps a rendered frame to its step (``f * substeps``); each frame's
        row is the mean over that frame's steps. ``frames``: the frames to observe (default
        every frame after the first, whose row has no preceding frame)."""
        rows = read_tools_csv(path)
        mine = [r for r in rows if r["tool"] == tool]
        if not mine:
            raise ValueError(f"tool = {checks.shorten(tool)!r} is not allowed: {checks.shown_path(path, False)} holds the forces of "
                             f"{', '.join(dict.fromkeys(r['tool'] for r in rows))}")
        by_frame = {r["frame"]: r for r in mine}  # one row per frame: read_tools_csv refuses a repeat
        chosen = sorted(f for f in by_frame if f > 0) if frames is None else list(_frames(frames))
        if any(f < 1 for f in chosen):
            raise ValueError(f"frames = {checks.shorten(chosen)!r} is not allowed: frames are >= 1 (frame 0's row has no frame before "
                             "it to average over)")
        missing = [f for f in chosen if f not in by_frame]
        if missing:
            raise ValueError(f"frames {missing} are not allowed: {checks.shown_path(path, False)} has no row of tool {tool!r} for them")
        if not isinstance(frame_steps, Mapping):
            raise ValueError(f"frame_steps = {checks.shorten(frame_steps)!r} is not allowed: must map each rendered "
                             "frame to its step ({frame: step})")
        missing = [f for f in chosen if f not in frame_steps]
        if missing:
            raise ValueError(f"frame_steps = {checks.shorten(dict(frame_steps))!r} is not allowed: it has no step for "
                             f"frame{'s' if len(missing) > 1 else ''} {', '.join(map(str, missing))} of tool {tool!r} "
                             f"in {checks.shown_path(path, False)}")
        steps = [checks.positive_int(f"frame_steps[{f}]", frame_steps[f]) for f in chosen]
        windows = {round(s / f) for s, f in zip(steps, chosen) if f > 0}
        if len(windows) != 1 or any(s != f * next(iter(windows)) for s, f in zip(steps, chosen)):
            raise ValueError(f"frame_steps = {dict(frame_steps)} is not allowed: every frame must span the same number of steps")
        axes = [_AXES[c] for c in str(components).lower() if c in _AXES]
        targets = np.array([[by_frame[f]["force"][a] for a in axes] for f in chosen])
        return cls(targets, tool, steps, window=next(iter(windows)), components=components, weight=weight, noise=noise)


TOOLS_CSV_COLUMNS = ("frame", "time", "tool", "fx", "fy", "fz")


#: The unit a force log's column may name in its header (``fy [N]``, ``time (s)``).
TOOLS_CSV_UNITS = {"time": "s", "fx": "N", "fy": "N", "fz": "N"}


def _column(name: str) -> tuple[str, str | None]:
    """A header cell as ``(name, unit)``: ``' Fy [N]'`` and ``'Fy / N'`` (ISO 80000's quantity /
    unit, which had read as a column 'fy / n' and the log as lacking fy) are ``('fy', 'N')``."""
    import re  # noqa: PLC0415

    m = re.fullmatch(r"\s*(.*?)\s*(?:[\[(]\s*([^\])]*?)\s*[\])]|/\s*([^/]*?))?\s*", name or "")
    return m.group(1).lower(), m.group(2) if m.group(2) is not None else m.group(3)


#: Lines before a force log's header that are read past: a testing machine's preamble
#: ('# Instron 5969', '# sample: ...'), as a point cloud's '#' lines are.
_PREAMBLE_LINES = 1000


def _is_preamble(line: str) -> bool:
    """Whether a line before a force log's header is a comment or blank (read past)."""
    return not line.strip() or line.lstrip().startswith("#")


def tools_log_head(fh) -> tuple[str, int]:
    """A force log's header line and how many lines before it are read past (``#`` comments
    and blank lines): ``("", n)`` where none follows within ``_PREAMBLE_LINES``."""
    for skipped in range(_PREAMBLE_LINES):
        line = fh.readline()
        if not line:
            break
        if not _is_preamble(line):
            return line, skipped
    return "", 0


def tools_log_delimiter(header: str) -> str:
    """The field separator of a force log: tabs where its header has tabs and no commas (an
    instrument's tab-separated export, which had been refused as if its separator meant decimal
    commas), else commas."""
    return "\t" if "\t" in header and "," not in header else ","


def tools_csv_header(path) -> list[str] | None:
    """The column names of a CSV file's header line as a force log reads them (a spreadsheet's
    byte-order mark, quotes, spaces and capitals left out; ``#`` lines before it read past), or
    None where it cannot be read."""
    import csv  # noqa: PLC0415

    try:
        # utf-8-sig: a spreadsheet's 'CSV UTF-8' starts with a byte-order mark, which made its
        # 'frame' column '\ufeffframe' and the log 'lacks frame', as printed beside it.
        with open(path, newline="", encoding=checks.text_encoding(path), errors="replace") as fh:
            head, _ = tools_log_head(fh)
    except OSError:
        return None
    # Parsed as the rows are (read_tools_csv's reader, spaces after the separators skipped): a
    # header of quoted cells ('"frame","time",...') had been read as the names '"frame"', ...,
    # and with a space after each comma ('"frame", "time"') as '"time"', ... still.
    try:
        cells = next(csv.reader([head.rstrip("\r\n")], delimiter=tools_log_delimiter(head), skipinitialspace=True), [])
    except csv.Error:
        return None
    return [_column(c)[0] for c in cells]


def is_tools_csv(path) -> bool:
    """Whether ``path`` is a reaction-force log (``<output>_tools.csv``): its header names
    ``frame``, ``time``, ``tool`` and ``fx, fy, fz`` (in any case, with or without spaces
    after the commas)."""
    cols = tools_csv_header(path)
    return cols is not None and all(c in cols for c in TOOLS_CSV_COLUMNS)


def _not_utf8(shown: str, line: int, text: str) -> str:
    """The refusal of a force log's row that is not UTF-8 text (read with its bytes replaced)."""
    return (f"force log {shown} cannot be read: row {line} ({checks.shorten(text.strip())!r}) is not UTF-8 text (\ufffd "
            "marks a byte that is not): save the file as UTF-8 (a spreadsheet's 'CSV UTF-8'; one saved in Windows' "
            "cp1252?), or it is no force log (a damaged or foreign file?)")


def read_tools_csv(path) -> list[dict]:
    """Rows of a reaction-force log: ``{frame, time, tool, force (3,)}``; one row per tool
    and frame, frames >= 0, finite numbers (a ``ValueError`` naming the file and row
    otherwise)."""
    import csv  # noqa: PLC0415

    p = os.fspath(path)
    shown = checks.shown_path(p, False)
    # The convention of the other target readers (fit.load_target, silhouette.load_masks).
    if not os.path.exists(p):
        raise FileNotFoundError(f"force log {shown} does not exist")
    if os.path.isdir(p):
        raise ValueError(f"force log {shown} is not allowed: it is a folder, not a '<output>_tools.csv' file")
    out = []
    seen: dict[tuple[str, int], int] = {}
    try:
        # errors="replace": an instrument's preamble saved in Windows' code page ('# 23 °C' in
        # cp1252) was refused as 'utf-8' codec can't decode byte 0xb0 in position 33', where '#'
        # lines are read past (as a point cloud's are); a cell the log reads is held to UTF-8 below.
        with open(p, newline="", encoding=checks.text_encoding(p), errors="replace") as fh:
            head, skipped = tools_log_head(fh)
            if "\ufffd" in head:
                raise ValueError(_not_utf8(shown, skipped + 1, head))
            # 'frame, time, tool, ...' (spaces after the commas) read as the columns ' time',
            # ' tool', ... and the log was refused as lacking them, printed beside it.
            reader = csv.DictReader(itertools.chain([head], fh), skipinitialspace=True,
                                    delimiter=tools_log_delimiter(head))
            if reader.fieldnames:
                columns = [_column(c) for c in reader.fieldnames]
                for (name, unit), cell in zip(columns, reader.fieldnames):
                    if unit is not None and name in TOOLS_CSV_UNITS and unit != TOOLS_CSV_UNITS[name]:
                        # A log in mN or ms is 1000 times off: refused, not read as newtons and seconds.
                        raise ValueError(f"{shown} is not allowed as a force target: its column {cell.strip()!r} is in "
                                         f"{unit}; give {name} in {TOOLS_CSV_UNITS[name]} (header '{name}' or "
                                         f"'{name} [{TOOLS_CSV_UNITS[name]}]')")
                names = [name for name, _ in columns]
                twice = [n for n in dict.fromkeys(names) if n and names.count(n) > 1]
                if twice:
                    # The reader's rows keep one cell per name (the last): a log naming fy twice had
                    # its rows refused as one field short, which they were not.
                    cells = [cell.strip() for (name, _), cell in zip(columns, reader.fieldnames) if name == twice[0]]
                    raise ValueError(f"{shown} is not allowed as a force target: its header names the column "
                                     f"{twice[0]!r} {checks.plural(len(cells), 'time')} ({', '.join(map(repr, cells))}); "
                                     "which one to read is not ours to choose: name each column once")
                # A spreadsheet's export of a sheet wider than its data ends every line, the header's
                # too, in empty cells (',,'): unnamed columns, each its own, so rows count them all.
                reader.fieldnames = [name or f"\0{i}" for i, name in enumerate(names)]
            missing = [c for c in TOOLS_CSV_COLUMNS if c not in (reader.fieldnames or [])]
            if missing:
                raise ValueError(f"{shown} is not allowed as a force target: it lacks the columns {', '.join(missing)} "
                                 f"(a '<output>_tools.csv' of 'warp-esph run' has them)")
            width = len(reader.fieldnames)
            for row in reader:
                # The row's line in the file: counting rows had named the wrong line below a
                # preamble or an empty line (which the reader skips).
                line = reader.line_num + skipped
                if not row.get(None) and not any((v or "").strip() for key, v in row.items() if key is not None):
                    continue  # a spreadsheet's empty row (',,,,,') holds nothing
                cells = [v for key, v in row.items() if key is not None and v is not None] + (row.get(None) or [])
                if any("\ufffd" in v for v in cells):
                    raise ValueError(_not_utf8(shown, line, ",".join(cells)))
                fields = len(cells)
                if fields != width:
                    # A row cut inside its fz read the digits left as the force (the torque columns
                    # after it unread), and a longer row was read as if it were this table's.
                    raise ValueError(f"{shown}, row {line} is not allowed: it has {fields} fields, the header {width} (a file "
                                     "cut short, or a row of another table?)")
                tool = (row["tool"] or "").strip()
                if not tool:
                    # Read as a tool named '' and refused as 'holds the forces of ', naming no row.
                    raise ValueError(f"{shown}, row {line}: tool = '' is not allowed: it is empty; name the scene's tool (or "
                                     "static collider, 'plane0' for the ground) that measured the force, as --target-tool "
                                     "does")
                values = {}
                for c in ("frame", "time", "fx", "fy", "fz"):
                    cell = (row[c] or "").strip()
                    try:
                        values[c] = int(cell) if c == "frame" else float(cell)
                    except ValueError:
                        # It said 'frame, time, fx, fy, fz must be numbers', not which cell or why.
                        why = ("it is empty" if not cell else
                               "a decimal comma? write numbers with a decimal point" if c != "frame" and "," in cell else
                               "frames are whole rendered frame indices" if c == "frame" else "must be a number")
                        unit = f" ({TOOLS_CSV_UNITS[c]})" if c in TOOLS_CSV_UNITS else ""
                        if c in ("fx", "fy", "fz") and (not cell or cell.lower() in ("na", "n/a", "-", "null", "none")):
                            unit += "; a frame not measured is left out of the log (no row)"
                        raise ValueError(f"{shown}, row {line}: {c} = {checks.shorten(cell)!r} is not allowed: {why}{unit}") from None
                frame = values.pop("frame")
                if frame < 0:
                    raise ValueError(f"{shown}, row {line}: frame = {frame} is not allowed: frames are rendered frame "
                                     "indices >= 0")
                for c, v in values.items():
                    # float() reads 'nan' and '1e400' (inf) without complaint.
                    if not math.isfinite(v):
                        # NaN is a missing marker in positions: said how a log leaves a frame out.
                        gap = ("; a frame not measured is left out of the log (no row), as NaN marks a missing marker "
                               "in positions") if math.isnan(v) else ""
                        raise ValueError(f"{shown}, row {line} (frame {frame}, tool {tool!r}): {c} = {row[c]!r} is not "
                                         f"allowed: must be a finite number{' (s)' if c == 'time' else ' (N)'}{gap}")
                force = np.array([values["fx"], values["fy"], values["fz"]])
                # Refused as the loss's 'targets' (a name the command line never gave) by window and
                # step, not by the file's row and column.
                checks.squarable_coordinates(f"{shown}, row {line} (frame {frame}, tool {tool!r})", force, "float64",
                                             lambda w: ("fx", "fy", "fz")[w[0]], quantity="force", unit="N",
                                             hint="give forces in newtons")
                if (tool, frame) in seen:
                    # Silently the last row won: which of two measurements is the force is not ours to choose.
                    raise ValueError(f"{shown}, row {line}: frame {frame} of tool {tool!r} is not allowed: row "
                                     f"{seen[tool, frame]} already gives it (one row per tool and frame)")
                seen[tool, frame] = line
                out.append({"frame": frame, "time": values["time"], "tool": tool, "row": line, "force": force})
    except OSError as e:
        raise ValueError(f"force log {shown} cannot be read: {e.strerror or e}") from None
    except (UnicodeDecodeError, csv.Error) as e:
        raise ValueError(f"force log {shown} cannot be read: {checks.read_reason(e)} (a damaged or foreign file?)") from None
    if not out:
        raise ValueError(f"{shown} is not allowed as a force target: it has no rows")
    return out


# ------------------------------------------------------------------- slump test
def _soft_top(q: np.ndarray, tau: float) -> tuple[float, np.ndarray]:
    """``M = sum_i w_i q_i`` with ``w = softmax(q / tau)`` (the top of ``q``, smoothly: the
    mean of the topmost values within about ``tau``) and ``dM/dq``."""
    z = (q - q.max()) / tau
    w = np.exp(z)
    w /= w.sum()
    m = float(np.dot(w, q))
    return m, w * (1.0 + (q - m) / tau)


class SlumpLoss(Loss):
    """The final height and spread of a slump test: ``weight * ((h - h*)^2 + (R - R*)^2)``.

    ``h``: the top of the material above ``floor`` (y), ``R``: the largest horizontal
    distance of the material from the vertical axis through ``center`` (x, z), each
    measured as a lab would, to the edge of the outermost particles: the smooth maximum
    (softmax-weighted mean, temperature ``tau``, default 0.05 ``spacing``: within a small
    fraction of a spacing of the hard maximum a ruler reads) of the
    particles' heights (distances) plus half a ``spacing`` (each particle stands for a
    cell). ``height``/``spread``: the measured values (m); either may be None (not
    measured). ``frame``: the step at which they were measured. ``noise``: their standard
    deviation (m) for ``warp_esph.diagnostics`` (None: the fit's ``noise``).

    Evaluated on the host (two numbers per evaluation) with the exact gradient.
    """

    _host = True
    noise_unit = "m"
    term_name = "slump lengths"

    def __init__(self, height: float | None, spread: float | None, frame: int, spacing: float, floor: float = 0.0,
                 center=(0.0, 0.0), tau: float | None = None, weight: float = 1.0, particles=None,
                 noise: float | None = None):
        super().__init__([frame], weight, particles)
        if height is None and spread is None:
            raise ValueError("height = None and spread = None is not allowed: give at least one measurement")
        self.height = None if height is None else checks.positive("height", height)
        self.spread = None if spread is None else checks.positive("spread", spread)
        self.spacing = checks.positive("spacing", spacing)
        self.floor = checks.number("floor", floor)
        center = checks.host_values("center", center)
        try:
            c = np.asarray(center, dtype=np.float64).ravel()
        except checks.ARRAY_ERRORS:  # numpy's "could not convert string to float" named no parameter
            c = np.full(1, np.nan)
        if c.shape != (2,) or not np.isfinite(c).all():
            raise ValueError(f"center = {checks.shorten(center)!r} is not allowed: give the axis position (x, z)")
        self.center = c
        self.tau = 0.05 * self.spacing if tau is None else checks.positive("tau", tau)
        if self.tau < 1e-6 * self.spacing:  # the smooth maximum's exponentials overflow: NaN gradients at 5e-324
            raise ValueError(f"tau = {checks.shorten(tau)!r} is not allowed: must be at least 1e-6 spacing = {1e-6 * self.spacing:g}")
        self.noise = None if noise is None else checks.noise("noise", noise)

    def launch(self, frame, x, out, scale: float = 1.0):
        return

    def _x(self, positions) -> np.ndarray:
        x = positions[self.frames[0]]
        x = x.numpy() if isinstance(x, wp.array) else np.asarray(checks.host_values(f"positions at step {self.frames[0]}", x))
        x = np.asarray(x, dtype=np.float64)
        if self.particles is None:
            return x
        self._check_particles(x.shape[0])  # a wrong-length mask was used, an index past the end an IndexError
        return x[self.particles]

    def measure(self, positions) -> tuple[float, float, np.ndarray, np.ndarray]:
        """Simulated ``(height, spread)`` and their gradients with respect to the (observed) positions."""
        x = self._x(positions)
        half = 0.5 * self.spacing
        h, dh = _soft_top(x[:, 1], self.tau)
        g_h = np.zeros_like(x)
        g_h[:, 1] = dh
        d = np.stack([x[:, 0] - self.center[0], x[:, 2] - self.center[1]], axis=1)
        r = np.sqrt((d * d).sum(axis=1))
        R, dR = _soft_top(r, self.tau)
        g_R = np.zeros_like(x)
        safe = np.where(r > 0.0, r, 1.0)
        g_R[:, 0] = dR * d[:, 0] / safe
        g_R[:, 2] = dR * d[:, 1] / safe
        return h + half - self.floor, R + half, g_h, g_R

    def residuals(self, positions) -> np.ndarray:
        h, R, _, _ = self.measure(positions)
        out = []
        if self.height is not None:
            out.append(h - self.height)
        if self.spread is not None:
            out.append(R - self.spread)
        return np.array(out)

    def value_and_grad(self, positions):
        h, R, g_h, g_R = self.measure(positions)
        value, g = 0.0, np.zeros_like(g_h)
        if self.height is not None:
            value += (h - self.height) ** 2
            g += 2.0 * (h - self.height) * g_h
        if self.spread is not None:
            value += (R - self.spread) ** 2
            g += 2.0 * (R - self.spread) * g_R
        f = self.frames[0]
        if self.particles is not None:
            x = positions[f]
            full = np.zeros((x.shape[0], 3))
            np.add.at(full, self.particles, g)  # a particle listed twice gets both shares
            g = full
        self._counts[f] = 1
        return self.weight * value, {f: self.weight * g}

    def residual_scale(self) -> float:
        return 1.0 / self.weight

    def observation_count(self) -> int:
        return int(self.height is not None) + int(self.spread is not None)

    def target_items(self, prefix: str = "target") -> dict:
        return {**super().target_items(prefix), **{f"{prefix}.{name}": getattr(self, name) for name in
                                                   ("height", "spread", "spacing", "floor", "center", "tau")}}

    def __repr__(self):
        return f"SlumpLoss(height={self.height}, spread={self.spread}, frame={self.frames[0]}, weight={self.weight:g})"
