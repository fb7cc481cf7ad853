"""Tools and boundary conditions: moving rigid colliders, pinned (kinematic) particle sets,
and the reaction force and torque each of them exerts on the material.

Every tool (a collider or a pinned set) follows a rigid motion: a pose ``(p(t), q(t))``
(position, unit quaternion in Warp's ``(x, y, z, w)`` order) given by keyframes, by a
constant linear and angular velocity, or by a Python callable. Each step evaluates the
pose at the step's start ``t0`` and end ``t1 = t0 + dt`` (``poses`` kernel, differentiable
in the keyframes and velocities), then ``integrate`` does the symplectic Euler update of
``integrate.py`` followed by

- the static colliders of ``colliders.py`` (unchanged),
- each moving collider: the candidate position is expressed in the collider's frame at
  ``t1``. A particle of a box, sphere, capsule, cylinder or mesh collider whose relative
  path in the collider frame (start in the ``t0`` frame, end in the ``t1`` frame) enters it
  is stopped at the entry point (no tunnelling through a thin or fast tool); otherwise a
  particle found inside, or within ``CONTACT_MARGIN`` spacings of its surface, is moved to
  the nearest surface point (a plane, a half-space that no path can cross, always so). Both
  put the particle ``CONTACT_MARGIN`` spacings outside the surface (a plane: on it), on the
  surface of the shape grown by the margin, where it is found touching again the next step
  (a resting particle stays there). The surface point's velocity
  over the step ``(T1(c) - T0(c)) / dt`` is the velocity the contact is measured against: the
  inward relative normal velocity is removed, and Coulomb friction acts on the relative
  tangential velocity (static coefficient: sticks while ``|v_t| <= mu_s |dv_n|``; else
  kinetic: ``|v_t|`` shrinks by ``mu_k |dv_n|``). The tangential part of the step's
  displacement follows the responded velocity, so a sticking particle stays put;
- pinned particles: ``x = p(t1) + R(t1) (X - c)`` (evaluated as ``X + (p - c) + (R - I)(X - c)``,
  exactly ``X`` while the set is at rest) with ``X`` the rest position and ``c`` the
  set's rest centroid (the set's pose at rest is ``(c, identity)``), ``v = (x(t1) - x(t0)) / dt``
  (both velocities with the step's displacement and rotation from the motion's rates, not from
  two rounded places: ``step_displacement``, ``step_rotation``, ``rotation_delta``;
  docs/tools.md, "Reaction forces").
  Pinned particles stay in every neighbour fit and force sum as ordinary particles: only
  their x and v are prescribed, so F is consistent across the clamp.

Reaction force (written into ``state_out.reaction_force`` / ``reaction_torque``, one row per
tool, differentiable): the force the tool exerts on the material during the step,

- collider: ``sum_i m_i (v_i^after - v_i^before) / dt`` over its contacts (the impulse of the
  contact response over dt; ``v^before`` is the velocity after forces and gravity);
- pinned set: ``sum_i [m_i (v_i(t1) - v_i(t0)) / dt - f_i - m_i g]``, the force the support
  must add to the internal forces ``f_i`` and gravity on the pinned particles to give them
  their prescribed acceleration (for a static clamp: ``-(sum f_i + m g)``).

The torque is taken about the tool's position ``p(t1)``. The force the material exerts on
the tool is minus these.
"""

import bisect
import dataclasses
import functools
import math
import os
import types
import warnings
from collections.abc import Callable, Mapping

import numpy as np
import warp as wp

from . import checks
from .meshes import coordinate_round_off
from .sim import colliders
from .sim.integrate import funcs as integrate_funcs, static_collider_struct, struct as static_struct
from .sim.replay import kept_through_backward
from ._types import type_set

#: Collider shapes, in the order their loops run in ``integrate`` (each kind's loop is
#: unrolled, docs/method.md, Warp pitfall 1: a dynamic loop carrying x and v through non-linear
#: projections gets a wrong adjoint).
KINDS = ("plane", "box", "sphere", "capsule", "cylinder", "mesh")
#: How far outside a tool (in spacings) the contact puts a particle that met it; a particle
#: this close to a tool (but a plane) counts as touching it.
CONTACT_MARGIN = 1.0e-3
MAX_TOOLS = 16
#: The advice of ``ToolSet.check_speed``'s refusal (a Python caller's names; ``warp-esph run``
#: gives its options').
TOO_FAST_ADVICE = "; give a slower motion or a smaller dt="
IDENTITY = (0.0, 0.0, 0.0, 1.0)


# --------------------------------------------------------------------------- motions
def _quat(name: str, value) -> tuple[float, float, float, float]:
    return checks.unit_vector(name, value, 4, "quaternion (x, y, z, w)")


#: The names ``check_keyframes`` gives its three arguments in messages.
KEYFRAME_NAMES = ("times", "positions", "orientations")


def _refuse(name: str, value, allowed: str, detail=None):
    """``name = value is not allowed: allowed (detail)``; ``detail`` may be the ValueError of
    the one item at fault, which names that item."""
    if isinstance(detail, ValueError):
        detail = str(detail).replace(" is not allowed: ", ": ", 1)
    more = f" ({detail})" if detail else ""
    raise ValueError(f"{name} = {checks.shorten(value)!r} is not allowed: {allowed}{more}") from None


def _items(name: str, value, allowed: str) -> list:
    """The items of ``value``, an ordered sequence whose length is known: an iterator would
    be used up by the check, and a set or mapping has no order to pair times with poses."""
    if isinstance(value, np.ndarray) and value.ndim == 0:
        _refuse(name, value, allowed, "its shape is ()")
    if isinstance(value, (str, bytes, set, frozenset, Mapping)) or not hasattr(value, "__len__") \
            or not hasattr(value, "__getitem__"):
        _refuse(name, value, allowed, f"it is of type {type(value).__name__}, not a list, tuple or array")
    try:
        return list(value)
    except Exception as e:  # noqa: BLE001 (a sequence that cannot be read is refused, whatever it raises)
        _refuse(name, value, allowed, f"reading it raised {type(e).__name__}: {e}")


def check_keyframes(times, positions, orientations=None, names=KEYFRAME_NAMES):
    """``(times, positions, orientations)`` checked and as tuples of floats: times one or
    more finite, increasing numbers, one position (3 numbers) and one quaternion (4, not all
    zero; scaled to unit length, each in the hemisphere of the one before, for the shortest
    arc) per time; ``orientations=None``: the identity throughout. ``names``: what messages
    call the three (a scene file's keys)."""
    tn, pn, qn = names
    allowed = "must be one or more finite, increasing numbers"
    if isinstance(times, np.ndarray) and times.ndim != 1:  # [[0, 1]] was read as [0, 1]
        _refuse(tn, times, allowed, f"its shape is {times.shape}")
    t_items = _items(tn, times, allowed)
    if not t_items:
        _refuse(tn, times, allowed)
    t = []
    for k, v in enumerate(t_items):
        try:
            t.append(checks.number(f"{tn}[{k}]", v))
        except ValueError as e:
            _refuse(tn, times, allowed, e)
        if k and not t[k] > t[k - 1]:
            _refuse(tn, times, allowed, f"{tn}[{k}] = {checks.shorten(v)!r} is not after {tn}[{k - 1}] = {checks.shorten(t_items[k - 1])!r}")
    n = len(t)

    def rows(name, value, width, what, check):
        allowed = f"must be ({n}, {width}) {what}, one row per time"
        items = _items(name, value, allowed)
        if len(items) != n:
            _refuse(name, value, allowed, f"it has {len(items)} row{'' if len(items) == 1 else 's'}")
        out = []
        for k, row in enumerate(items):
            try:
                out.append(check(f"{name}[{k}]", row))
            except ValueError as e:
                _refuse(name, value, allowed, e)
        return out

    p = rows(pn, positions, 3, "finite numbers", checks.vector)
    if orientations is None:
        q = [IDENTITY] * n
    else:
        q = [list(r) for r in rows(qn, orientations, 4, "quaternions (x, y, z, w), none zero", _quat)]
        # Shortest arcs: consecutive keyframes in the same hemisphere.
        for k in range(1, n):
            if np.dot(q[k], q[k - 1]) < 0.0:
                q[k] = [-c for c in q[k]]
    return tuple(t), tuple(tuple(r) for r in p), tuple(tuple(float(c) for c in r) for r in q)


@dataclasses.dataclass(frozen=True)
class Keyframes:
    """Piecewise motion through keyframes: position linear, orientation slerp in between;
    held at the first pose before ``times[0]`` and at the last after ``times[-1]``.

    ``orientations``: unit quaternions (x, y, z, w); default: identity throughout.
    ``position=None`` is not allowed here: keyframes are absolute poses."""

    times: tuple
    positions: tuple
    orientations: tuple | None = None

    def __post_init__(self):
        t, p, q = check_keyframes(self.times, self.positions, self.orientations)
        object.__setattr__(self, "times", t)
        object.__setattr__(self, "positions", p)
        object.__setattr__(self, "orientations", q)

    def sample(self, t: float) -> tuple[int, int, float]:
        return sample_times(self.times, t)


def sample_times(ts, t: float) -> tuple[int, int, float]:
    """The keyframes ``(a, b)`` around time ``t`` and the weight ``w`` of ``b``. At a
    keyframe's time the segment that starts there, the first keyframe's included: a step
    starting at ``times[0]`` (a motion keyed from t = 0) reads that segment's rate, as a step
    starting at any other keyframe does, and the tape's derivative in each keyframe time on a
    step boundary is the one for that keyframe moved earlier. The first keyframe's sample took
    the hold before it, so its time derivative at t = 0 was the other side's (moved later:
    -1.536 where the side every other keyframe takes reads 0.512, docs/tools.md)."""
    if t < ts[0]:
        return 0, 0, 0.0
    if t >= ts[-1]:
        return len(ts) - 1, len(ts) - 1, 0.0
    # A list (the step's own samples): bisect finds the index searchsorted would, without
    # converting the list to an array.
    k = (bisect.bisect_right(ts, t) if isinstance(ts, list) else int(np.searchsorted(ts, t, side="right"))) - 1
    return k, k + 1, (t - ts[k]) / (ts[k + 1] - ts[k])


@dataclasses.dataclass(frozen=True)
class Velocity:
    """Constant linear ``velocity`` (m/s) and ``angular_velocity`` (rad/s, about the tool's
    position) from the pose ``(position, orientation)`` at t = 0; ``None``: the tool's own
    rest pose (a collider's ``position``/``orientation``, a pinned set's centroid)."""

    velocity: tuple = (0.0, 0.0, 0.0)
    angular_velocity: tuple = (0.0, 0.0, 0.0)
    position: tuple | None = None
    orientation: tuple | None = None

    def __post_init__(self):
        object.__setattr__(self, "velocity", checks.vector("velocity", self.velocity))
        object.__setattr__(self, "angular_velocity", checks.vector("angular_velocity", self.angular_velocity))
        if self.position is not None:
            object.__setattr__(self, "position", checks.vector("position", self.position))
        if self.orientation is not None:
            object.__setattr__(self, "orientation", _quat("orientation", self.orientation))


@dataclasses.dataclass(frozen=True)
class Scripted:
    """A Python callable ``fn(t) -> (position, quaternion (x, y, z, w))``, evaluated on the
    host at each step's start and end, at t = 0 by ``finalize``'s checks, and again at a
    frame's time by ``ToolSet.pose_at``'s readers (``ReactionLog.record``, the USD writer),
    and again at a forward's times by a re-run of it (a checkpointed ``Rollout.backward``, the
    torch bridge's backward), which refuses another pose: it must give the same pose when
    asked again at the same t. Not differentiable: its poses enter the tape as constants, so nothing
    flows back to the motion (``ToolSet.motion_gradient`` refuses it, and a taped step warns
    once per tool set); ``Keyframes`` and ``Velocity`` are the differentiable motions."""

    fn: Callable

    def __post_init__(self):
        if not callable(self.fn):
            raise ValueError(f"fn = {checks.shorten(self.fn)!r} is not allowed: must be callable as fn(t) -> (position, quaternion)")

    def pose(self, t: float, owner: str = "tools.Scripted"):
        """``fn(t)`` checked; ``owner`` (``"tool 'press'"``) is what messages name: an
        exception or a bad pose from deep in a step must say whose motion and when."""
        t = float(t)
        at = f"{owner}: its scripted motion at t = {t:g} is not allowed"
        try:
            r = self.fn(t)
        except Exception as e:  # noqa: BLE001 (the user's code may raise anything; Ctrl-C still passes)
            raise ValueError(f"{at}: it raised {type(e).__name__}: {e}") from e
        must = "must return (position, quaternion (x, y, z, w))"
        try:
            p, q = r
        except Exception:  # noqa: BLE001 (whatever unpacking r raises, r is the fault)
            raise ValueError(f"{at}: it returned {checks.shorten(r)!r}; {must}") from None
        try:
            return checks.vector("position", p), _quat("quaternion", q)
        except ValueError as e:
            raise ValueError(f"{at}: it returned {str(e).replace(' is not allowed: ', ', which ', 1)}") from None
        except Exception:  # noqa: BLE001 (a returned object whose reading raises is the fault)
            raise ValueError(f"{at}: it returned {checks.shorten(r)!r}; {must}") from None


MOTIONS = (Keyframes, Velocity, Scripted)


# ---------------------------------------------------------------------------- shapes
@dataclasses.dataclass(frozen=True)
class Collider:
    """A moving rigid collider (see ``SceneBuilder.add_tool``)."""

    name: str
    kind: str
    param: tuple  # plane: local normal; box: half extents; sphere: (r, 0, 0); capsule/cylinder: (r, half height, 0)
    motion: object
    friction: float
    static_friction: float
    mesh_points: np.ndarray | None = None
    mesh_triangles: np.ndarray | None = None


@dataclasses.dataclass(frozen=True)
class PinSet:
    name: str
    indices: np.ndarray
    motion: object
    #: A particle floor's (``SceneBuilder.add_particle_floor``): no part of the sample, which a
    #: camera's mask of the sample leaves empty (``fit.floor_particles``).
    floor: bool = False


def shape_param(kind: str, *, normal=None, half_extents=None, radius=None, half_height=None) -> tuple:
    """The local-frame shape parameter of a collider kind, checked."""
    kind = checks.choice("shape", kind, KINDS)
    if kind == "plane":
        return checks.unit_vector("normal", (0.0, 1.0, 0.0) if normal is None else normal)
    if kind == "box":
        if half_extents is None:
            raise ValueError("half_extents = None is not allowed: a box collider needs 3 positive half extents")
        return checks.positive_vector("half_extents", half_extents)
    if kind == "sphere":
        return (checks.positive("radius", radius), 0.0, 0.0)
    if kind in ("capsule", "cylinder"):
        return (checks.positive("radius", radius), checks.positive("half_height", half_height), 0.0)
    return (0.0, 0.0, 0.0)


# --------------------------------------------------------------------------- kernels
@functools.cache
def pose_kernels(scalar) -> types.SimpleNamespace:
    """The kernels that do not depend on the tool configuration: one compiled module each
    per scalar type, whatever tools a model has (``kernels`` is specialised)."""
    T = type_set(scalar)
    vec3, quat = T.vec3, (wp.quatf if scalar is wp.float32 else wp.quatd)
    ONE, HALF, ZERO = scalar(1.0), scalar(0.5), scalar(0.0)

    @wp.func
    def quat_exp(r: vec3):
        """Unit quaternion of the rotation vector ``r`` (series below 1e-6 rad, so the
        gradient at r = 0 is finite)."""
        th = wp.length(r)
        s = HALF
        c = ONE
        if th > scalar(1.0e-6):
            s = wp.sin(HALF * th) / th
            c = wp.cos(HALF * th)
        else:
            c = ONE - th * th / scalar(8.0)
        return quat(s * r[0], s * r[1], s * r[2], c)

    @wp.func
    def interp_quat(a: quat, b: quat, w: scalar):
        """Slerp (normalised lerp below 0.5 degrees, where slerp's 1/sin divides by ~0)."""
        d = wp.dot(a, b)
        if d > scalar(0.99999):
            return wp.normalize(a * (ONE - w) + b * w)
        th = wp.acos(wp.min(d, ONE))
        s = wp.sin(th)
        return a * (wp.sin((ONE - w) * th) / s) + b * (wp.sin(w * th) / s)

    @wp.func
    def segment_weight(kf_t: wp.array(dtype=scalar), i0: int, i1: int, w_host: scalar, t: scalar):
        """The weight of keyframe ``i1`` at ``t`` from the keyframe times on the tape
        (differentiable in them); the host only chose the segment (``w_host`` is its value,
        for the hold before / after)."""
        w = w_host
        if i1 != i0:
            w = (t - kf_t[i0]) / (kf_t[i1] - kf_t[i0])
        return w

    @wp.func
    def sampled_position(kf_t: wp.array(dtype=scalar), kf_p: wp.array(dtype=vec3), lin_v: wp.array(dtype=vec3), c: int,
                         i0: int, i1: int, w_host: scalar, t: scalar):
        """The position of tool ``c`` at ``t`` on the keyframe segment ``(i0, i1)``."""
        w = segment_weight(kf_t, i0, i1, w_host, t)
        return kf_p[i0] * (ONE - w) + kf_p[i1] * w + lin_v[c] * t

    @wp.func
    def step_displacement(kf_t: wp.array(dtype=scalar), kf_p: wp.array(dtype=vec3), lin_v: wp.array(dtype=vec3), c: int,
                          i0: int, i1: int, dt: scalar):
        """``p(t1) - p(t0)`` over a step of ``dt`` within one keyframe segment, from the
        motion's rates: the difference of the two positions lost float32's resolution of
        the position itself, eps |p| / dt in the velocity (1e-4 m/s at 0.3 m and the stable
        step at 2 cm), and the per-step reaction of a tool or pinned set moving steadily
        read that over dt again (0.2 N on a 0.24 kg pinned set translating at 0.05 m/s, 8 %
        of its weight, where it is 0)."""
        d = lin_v[c] * dt
        if i1 != i0:
            d = d + (kf_p[i1] - kf_p[i0]) * (dt / (kf_t[i1] - kf_t[i0]))
        return d

    @wp.func
    def quat_log(q: quat):
        """Rotation vector of the rotation ``q`` (normalised here; series below 1e-6 rad, so
        the gradient at the identity is finite)."""
        u = wp.normalize(q)
        v = vec3(u[0], u[1], u[2])
        sv = wp.length(v)
        f = scalar(2.0) / u[3]
        if sv > scalar(1.0e-6):
            f = scalar(2.0) * wp.atan2(sv, u[3]) / sv
        return v * f

    @wp.func
    def segment_rotation(kf_q: wp.array(dtype=quat), i0: int, i1: int):
        """The rotation vector that turns keyframe ``i0``'s orientation into ``i1``'s, in
        ``i0``'s frame: slerp's ``q(w) = q0 E(w r)``."""
        return quat_log(wp.quat_inverse(wp.normalize(kf_q[i0])) * wp.normalize(kf_q[i1]))

    @wp.func
    def sampled_orientation(kf_q: wp.array(dtype=quat), ang_v: wp.array(dtype=vec3), c: int, i0: int, i1: int, w: scalar,
                            t: scalar):
        # Normalised: a keyframe quaternion a descent moved off the unit sphere would
        # otherwise scale the tool (quat_rotate by |q|^2) and its local frame by the
        # inverse, so a particle placed on its surface would not be on it a step later.
        return wp.normalize(quat_exp(ang_v[c] * t) * interp_quat(kf_q[i0], kf_q[i1], w))

    @wp.func
    def step_rotation(kf_t: wp.array(dtype=scalar), kf_q: wp.array(dtype=quat), ang_v: wp.array(dtype=vec3), c: int,
                      i0: int, i1: int, q0: quat, dt: scalar):
        """The rotation vector ``r`` of a step of ``dt`` within one keyframe segment, in the
        tool's frame at the step's start (``R(t1) = R(t0) E(r)``), from the motion's rates
        (as ``step_displacement``): the angular velocity's ``R(t0)^T w dt``, the segment's
        slerp rotation times ``dt`` over its length, or both composed as the pose
        ``E(w t) Q(t)`` (``sampled_orientation``) gives them, ``E(R(t0)^T w dt) E(r_seg dt / T)``:
        their sum is off by their commutator, second order in dt."""
        r = wp.quat_rotate_inv(q0, ang_v[c] * dt)
        if i1 != i0:
            rs = segment_rotation(kf_q, i0, i1) * (dt / (kf_t[i1] - kf_t[i0]))
            r = quat_log(quat_exp(r) * quat_exp(rs))
        return r

    @wp.func
    def crossing_fractions(kf_t: wp.array(dtype=scalar), j0: int, j1: int, i0: int, i1: int, t0: scalar, dt: scalar):
        """The fractions of the segments ``(j0, j1)`` (the step's start) and ``(i0, i1)`` (its
        end) that a step from ``t0`` crossing keyframes covers: to keyframe ``j1``, and from
        keyframe ``i0`` for the rest of ``dt``, so that the two times sum to ``dt`` exactly and
        a motion at one speed through the keyframe moves by its speed times ``dt`` (a hold
        before the first or after the last keyframe covers nothing)."""
        f0 = ZERO
        f1 = ZERO
        if j1 != j0:
            f0 = (kf_t[j1] - t0) / (kf_t[j1] - kf_t[j0])
        if i1 != i0:
            f1 = (dt - (kf_t[i0] - t0)) / (kf_t[i1] - kf_t[i0])
        return f0, f1

    @wp.func
    def crossing_displacement(kf_t: wp.array(dtype=scalar), kf_p: wp.array(dtype=vec3), lin_v: wp.array(dtype=vec3), c: int,
                              j0: int, j1: int, i0: int, i1: int, t0: scalar, dt: scalar):
        """``p(t1) - p(t0)`` over a step that crosses keyframes, the sum of the pieces the
        motion's rates give on either side (``crossing_fractions``) and the whole segments
        between (``kf_p[i0] - kf_p[j1]``, 0 for one keyframe crossed): differencing the two
        poses, as before, kept float32's resolution of the place in every crossing step's
        velocity (a pinned set carried at one speed through 41 keyframes read 0.0079 N of
        reaction per step, docs/tools.md)."""
        f0, f1 = crossing_fractions(kf_t, j0, j1, i0, i1, t0, dt)
        d = lin_v[c] * dt + (kf_p[i0] - kf_p[j1])
        if j1 != j0:
            d = d + (kf_p[j1] - kf_p[j0]) * f0
        if i1 != i0:
            d = d + (kf_p[i1] - kf_p[i0]) * f1
        return d

    @wp.func
    def crossing_rotation(kf_t: wp.array(dtype=scalar), kf_q: wp.array(dtype=quat), ang_v: wp.array(dtype=vec3), c: int,
                          j0: int, j1: int, i0: int, i1: int, q0: quat, t0: scalar, dt: scalar):
        """The rotation vector of a step that crosses keyframes, in the tool's frame at its
        start (as ``step_rotation``): the rest of the start's segment, the whole segments
        between, then the part of the end's segment, composed (``crossing_displacement``), after
        the angular velocity's turn (``step_rotation``)."""
        f0, f1 = crossing_fractions(kf_t, j0, j1, i0, i1, t0, dt)
        qa = quat(ZERO, ZERO, ZERO, ONE)
        qm = quat(ZERO, ZERO, ZERO, ONE)
        qb = quat(ZERO, ZERO, ZERO, ONE)
        if j1 != j0:
            qa = quat_exp(segment_rotation(kf_q, j0, j1) * f0)
        if i0 != j1:
            qm = wp.quat_inverse(wp.normalize(kf_q[j1])) * wp.normalize(kf_q[i0])
        if i1 != i0:
            qb = quat_exp(segment_rotation(kf_q, i0, i1) * f1)
        return quat_log(quat_exp(wp.quat_rotate_inv(q0, ang_v[c] * dt)) * qa * qm * qb)

    @wp.kernel(module="unique")
    def poses(
        kf_t: wp.array(dtype=scalar),
        kf_p: wp.array(dtype=vec3),
        kf_q: wp.array(dtype=quat),
        lin_v: wp.array(dtype=vec3),
        ang_v: wp.array(dtype=vec3),
        s_i0: wp.array(dtype=wp.int32),
        s_i1: wp.array(dtype=wp.int32),
        s_w: wp.array(dtype=scalar),
        s_t: wp.array(dtype=scalar),
        s_direct: wp.array(dtype=wp.int32),
        s_p: wp.array(dtype=vec3),
        s_q: wp.array(dtype=quat),
        s_dp: wp.array(dtype=vec3),
        s_dr: wp.array(dtype=vec3),
        dt: scalar,
        pose_p: wp.array(dtype=vec3),
        pose_q: wp.array(dtype=quat),
        pose_dp: wp.array(dtype=vec3),
        pose_dr: wp.array(dtype=vec3),
    ):
        """Pose of tool ``s // 2`` at its sample ``s`` (even: step start, odd: step end), and
        at an odd sample the step's displacement ``p(t1) - p(t0)`` and rotation
        (``step_displacement``, ``step_rotation``; ``crossing_displacement``,
        ``crossing_rotation`` for a step across keyframes)."""
        s = wp.tid()
        c = s // 2
        if s_direct[s] != 0:
            pose_p[s] = s_p[s]
            pose_q[s] = s_q[s]
            pose_dp[s] = s_dp[s]
            pose_dr[s] = s_dr[s]
        else:
            i0 = s_i0[s]
            i1 = s_i1[s]
            t = s_t[s]
            p = sampled_position(kf_t, kf_p, lin_v, c, i0, i1, s_w[s], t)
            q = sampled_orientation(kf_q, ang_v, c, i0, i1, segment_weight(kf_t, i0, i1, s_w[s], t), t)
            pose_p[s] = p
            pose_q[s] = q
            dp = vec3(ZERO, ZERO, ZERO)
            dr = vec3(ZERO, ZERO, ZERO)
            if s % 2 == 1:
                j0 = s_i0[s - 1]
                j1 = s_i1[s - 1]
                t0 = s_t[s - 1]
                q0 = sampled_orientation(kf_q, ang_v, c, j0, j1, segment_weight(kf_t, j0, j1, s_w[s - 1], t0), t0)
                if j0 == i0 and j1 == i1:
                    dp = step_displacement(kf_t, kf_p, lin_v, c, i0, i1, dt)
                    dr = step_rotation(kf_t, kf_q, ang_v, c, i0, i1, q0, dt)
                else:
                    dp = crossing_displacement(kf_t, kf_p, lin_v, c, j0, j1, i0, i1, t0, dt)
                    dr = crossing_rotation(kf_t, kf_q, ang_v, c, j0, j1, i0, i1, q0, t0, dt)
            pose_dp[s] = dp
            pose_dr[s] = dr

    @wp.kernel(module="unique")
    def accumulate(src: wp.array(dtype=vec3), scale: scalar, dst: wp.array(dtype=vec3)):
        k = wp.tid()
        dst[k] = dst[k] + scale * src[k]

    @wp.kernel(module="unique")
    def work(rforce: wp.array(dtype=vec3), rtorque: wp.array(dtype=vec3), pose_q: wp.array(dtype=quat),
             pose_dp: wp.array(dtype=vec3), pose_dr: wp.array(dtype=vec3), n_tools: int, dst: wp.array(dtype=wp.float64)):
        """Add to ``dst[r]`` the work (J) reaction row ``r`` did on the material over the step:
        its force along the tool's displacement plus its torque along the tool's rotation (the
        rotation vector ``pose_dr`` is in the tool's frame at the step start). Each contact's
        impulse times its surface point's velocity summed, as the ``apply`` and pin responses
        measure that velocity, to first order in the step's rotation. Float64: a run's sum of
        many small steps' terms."""
        r = wp.tid()
        k = r % n_tools
        w = wp.dot(rforce[r], pose_dp[2 * k + 1]) + wp.dot(rtorque[r], wp.quat_rotate(pose_q[2 * k], pose_dr[2 * k + 1]))
        dst[r] = dst[r] + wp.float64(w)

    return types.SimpleNamespace(poses=poses, accumulate=accumulate, work=work, quat=quat)


@functools.cache
def kernels(scalar, n_planes: int, n_spheres: int, n_boxes: int, counts: tuple, n_pins: int) -> types.SimpleNamespace:
    """Specialised to the static collider counts and the number of tools of each kind in
    ``KINDS`` (tools are stored grouped by kind in that order, pinned sets after them)."""
    T = type_set(scalar)
    vec3, quat = T.vec3, (wp.quatf if scalar is wp.float32 else wp.quatd)
    kin = integrate_funcs(scalar, n_planes, n_spheres, n_boxes)
    StaticColliders = static_struct(scalar)
    col = colliders.funcs(scalar)
    offsets = [int(sum(counts[:k])) for k in range(len(counts))]
    ONE, ZERO = scalar(1.0), scalar(0.0)

    @wp.func
    def world(p: vec3, q: quat, xl: vec3):
        return p + wp.quat_rotate(q, xl)

    @wp.func
    def local(p: vec3, q: quat, x: vec3):
        return wp.quat_rotate_inv(q, x - p)

    @wp.func
    def rotation_delta(r: vec3, y: vec3):
        """``(E(r) - I) y`` for the rotation ``E`` of rotation vector ``r`` (Rodrigues), without
        subtracting ``y`` from ``E(r) y``, which carried float32's resolution of ``y`` into a
        step's velocity (``pose_dp``). Series below 1e-3 rad."""
        th2 = wp.dot(r, r)
        s1 = ONE - th2 / scalar(6.0)
        s2 = scalar(0.5) - th2 / scalar(24.0)
        if th2 > scalar(1.0e-6):
            th = wp.sqrt(th2)
            h = wp.sin(scalar(0.5) * th)
            s1 = wp.sin(th) / th
            s2 = scalar(2.0) * h * h / th2
        ry = wp.cross(r, y)
        return s1 * ry + s2 * wp.cross(r, ry)

    @wp.func
    def tangential_follow(x_start: vec3, x_s: vec3, v_new: vec3, vs: vec3, n: vec3, p0: vec3, q0: quat, p1: vec3, q1: quat, dt: scalar):
        """Tangential offset from the contact point ``x_s`` (normal ``n``) to where the
        particle's step ends: its start carried with the tool plus ``dt`` times its responded
        velocity relative to the surface, projected on the tangent plane. The step's
        tangential displacement relative to the tool is then ``dt`` times the responded
        relative velocity, whether ``x_s`` is the nearest surface point of the end of the path
        or the point where the path entered the tool: a sticking particle stays where it was
        on the tool, a sliding one moves with its velocity. (Offsetting ``x_s`` by the
        velocity change alone, as before, was right only for the nearest point: from an entry
        point a particle resting on a tool lost the part of the drift after the entry each
        step: one sticking on a sphere crept against the tangential force, a frictionless one
        kept a tangential velocity its position never followed, and the apex particles under
        a held frictional sphere indenter wandered by more than a spacing, docs/tools.md.)"""
        d = world(p1, q1, local(p0, q0, x_start)) + dt * (v_new - vs) - x_s
        return d - wp.dot(d, n) * n

    @wp.func
    def apply(
        x: vec3, v: vec3, x_start: vec3, hit: int, xc: vec3, nl: vec3, c: int, row: int, m: scalar, dt: scalar, ramp: scalar,
        pose_p: wp.array(dtype=vec3), pose_q: wp.array(dtype=quat), pose_dp: wp.array(dtype=vec3),
        pose_dr: wp.array(dtype=vec3), mu_s: wp.array(dtype=scalar), mu_k: wp.array(dtype=scalar), rforce: wp.array(dtype=vec3), rtorque: wp.array(dtype=vec3),
    ):
        """Move a particle in contact to the surface point ``xc`` (collider frame) and
        respond relative to that point's velocity; adds the impulse / dt to the reaction row
        ``row`` (tool ``c`` in the particle's world)."""
        if hit == 0:
            return x, v
        p0 = pose_p[2 * c]
        q0 = pose_q[2 * c]
        p1 = pose_p[2 * c + 1]
        q1 = pose_q[2 * c + 1]
        x_s = world(p1, q1, xc)
        # From the step's displacement, not the difference of the two world points (which
        # carries float32's resolution of the tool's place: pose_dp).
        vs = (pose_dp[2 * c + 1] + wp.quat_rotate(q0, rotation_delta(pose_dr[2 * c + 1], xc))) / dt
        n = wp.quat_rotate(q1, nl)
        # The whole depth is undone (a particle left inside a moving tool could be passed by
        # it: a thin blade's nearest face may be its back); the touchdown share acts on the
        # velocity alone.
        # The depth's round-off: of the world points and of the collider-frame ones (the
        # surface point and the tool's place) that the contact was found from.
        tol = col.depth_round_off(col.max_abs(x) + col.max_abs(p1) + col.max_abs(xc))
        v_new = col.coulomb_response(v, vs, n, wp.dot(x_s - x, n), dt, ramp, mu_s[c], mu_k[c], tol)
        x_new = x_s + tangential_follow(x_start, x_s, v_new, vs, n, p0, q0, p1, q1, dt)
        f = m * (v_new - v) / dt
        wp.atomic_add(rforce, row, f)
        wp.atomic_add(rtorque, row, wp.cross(x_s - p1, f))
        return x_new, v_new

    @wp.func
    def shape_plane(xl: vec3, nrm: vec3):
        d = wp.dot(nrm, xl)
        if d < ZERO:
            return 1, xl - d * nrm, nrm
        return 0, xl, nrm

    # The inside tests of the swept shapes take the shape grown by ``margin`` and put a
    # particle found in it on its surface, where the entry tests put one too (the entry
    # point plus the margin along the normal). One put exactly on the surface, as before,
    # started the next step there, where round-off alone chose between entering (put the
    # margin outside) and inside (put back on the surface): a float64 loss jumped by up to
    # 4e-5 under relative changes of lam below 1e-6 (docs/method.md §1). Put the margin
    # outside a test that took the ungrown shape, a resting particle fell back through the
    # margin every few steps and was lifted again: a block on a held box chattered, its
    # kinetic energy 200 times that of one at rest on it (docs/tools.md). Placed on the grown
    # surface it is found in it again the next step and stays there; where round-off
    # decides, both answers leave it in the same place.
    @wp.func
    def shape_sphere_at(xl: vec3, a: vec3, r: scalar, margin: scalar):
        d = xl - a
        r2 = wp.dot(d, d)
        if r2 < (r + margin) * (r + margin) and r2 > ZERO:
            nl = d / wp.sqrt(r2)
            return 1, a + (r + margin) * nl, nl
        return 0, xl, vec3()

    @wp.func
    def shape_sphere(xl: vec3, param: vec3, margin: scalar):
        return shape_sphere_at(xl, vec3(), param[0], margin)

    @wp.func
    def shape_capsule(xl: vec3, param: vec3, margin: scalar):
        y = wp.clamp(xl[1], -param[1], param[1])
        return shape_sphere_at(xl, vec3(ZERO, y, ZERO), param[0], margin)

    @wp.func
    def shape_box(xl: vec3, half: vec3, margin: scalar):
        gap = vec3(wp.abs(xl[0]) - half[0], wp.abs(xl[1]) - half[1], wp.abs(xl[2]) - half[2])
        if gap[0] < margin and gap[1] < margin and gap[2] < margin:
            axis = int(0)
            if gap[1] > gap[axis]:
                axis = 1
            if gap[2] > gap[axis]:
                axis = 2
            # No component assignment (xc[axis] = ...): its adjoint in Warp 1.19 let the
            # overwritten component's gradient through (measured: 12x off against central
            # differences).
            e = vec3(wp.where(axis == 0, ONE, ZERO), wp.where(axis == 1, ONE, ZERO), wp.where(axis == 2, ONE, ZERO))
            sgn = wp.where(xl[axis] < ZERO, scalar(-1.0), ONE)
            return 1, xl + (sgn * (half[axis] + margin) - xl[axis]) * e, sgn * e
        return 0, xl, vec3()

    @wp.func
    def slab(s: scalar, d: scalar, h: scalar):
        """Entry and exit parameters of the path ``s + t d`` through ``|.| <= h``, and the
        sign of the face it enters by."""
        big = scalar(1.0e30)
        if d == ZERO:
            if wp.abs(s) <= h:
                return -big, big, ZERO
            return big, -big, ZERO
        ta = (-h - s) / d
        tb = (h - s) / d
        if ta < tb:
            return ta, tb, scalar(-1.0)
        return tb, ta, ONE

    @wp.func
    def swept_box(xs: vec3, xl: vec3, half: vec3, margin: scalar):
        """A box the relative path ``xs -> xl`` passes through (a thin plate moving more than
        its thickness in a step): stop at the entry point."""
        d = xl - xs
        t0x, t1x, sx = slab(xs[0], d[0], half[0])
        t0y, t1y, sy = slab(xs[1], d[1], half[1])
        t0z, t1z, sz = slab(xs[2], d[2], half[2])
        t_in = t0x
        nl = vec3(sx, ZERO, ZERO)
        if t0y > t_in:
            t_in = t0y
            nl = vec3(ZERO, sy, ZERO)
        if t0z > t_in:
            t_in = t0z
            nl = vec3(ZERO, ZERO, sz)
        t_out = wp.min(t1x, wp.min(t1y, t1z))
        if t_in > ZERO and t_in <= ONE and t_in <= t_out:
            return 1, xs + t_in * d + margin * nl, nl
        return 0, xl, vec3()

    @wp.func
    def ray_sphere(xs: vec3, d: vec3, a: vec3, r: scalar):
        """Entry parameter ``t`` of the path ``xs + t d`` into the sphere ``(a, r)``; 2 (no
        entry in the step) when the path misses it or starts inside it."""
        o = xs - a
        dd = wp.dot(d, d)
        cc = wp.dot(o, o) - r * r
        t = scalar(2.0)
        if cc > ZERO and dd > ZERO:
            b = wp.dot(o, d)
            disc = b * b - dd * cc
            if disc > ZERO and b < ZERO:
                t = (-b - wp.sqrt(disc)) / dd
        return t

    @wp.func
    def ray_disc(ox: scalar, oz: scalar, dx: scalar, dz: scalar, r: scalar):
        """Entry and exit parameters of the path ``o + t d`` (projected on x-z) through the
        infinite cylinder ``x^2 + z^2 <= r^2`` along y."""
        big = scalar(1.0e30)
        dd = dx * dx + dz * dz
        cc = ox * ox + oz * oz - r * r
        if dd == ZERO:
            if cc < ZERO:
                return -big, big
            return big, -big
        b = ox * dx + oz * dz
        disc = b * b - dd * cc
        if disc <= ZERO:
            return big, -big
        sq = wp.sqrt(disc)
        return (-b - sq) / dd, (-b + sq) / dd

    @wp.func
    def swept_sphere(xs: vec3, xl: vec3, param: vec3, margin: scalar):
        """A sphere the relative path ``xs -> xl`` enters during the step (however fast the
        tool moves past the particle): stop at the entry point."""
        d = xl - xs
        t = ray_sphere(xs, d, vec3(), param[0])
        if t > ZERO and t <= ONE:
            nl = wp.normalize(xs + t * d)
            return 1, xs + t * d + margin * nl, nl
        return 0, xl, vec3()

    @wp.func
    def swept_capsule(xs: vec3, xl: vec3, param: vec3, margin: scalar):
        """The capsule is the union of its side and its two end spheres: the path enters it
        where it first enters one of them."""
        r = param[0]
        h = param[1]
        d = xl - xs
        # Starting inside: the nearest-point projection handles it.
        ys = wp.clamp(xs[1], -h, h)
        o = xs - vec3(ZERO, ys, ZERO)
        if wp.dot(o, o) <= r * r:
            return 0, xl, vec3()
        t = scalar(2.0)
        a = vec3()
        tc, tc_out = ray_disc(xs[0], xs[2], d[0], d[2], r)
        yc = xs[1] + tc * d[1]
        if tc > ZERO and tc < tc_out and yc >= -h and yc <= h:
            t = tc
            a = vec3(ZERO, yc, ZERO)
        top = vec3(ZERO, h, ZERO)
        t_top = ray_sphere(xs, d, top, r)
        if t_top < t:
            t = t_top
            a = top
        t_bot = ray_sphere(xs, d, -top, r)
        if t_bot < t:
            t = t_bot
            a = -top
        if t > ZERO and t <= ONE:
            nl = wp.normalize(xs + t * d - a)
            return 1, xs + t * d + margin * nl, nl
        return 0, xl, vec3()

    @wp.func
    def swept_cylinder(xs: vec3, xl: vec3, param: vec3, margin: scalar):
        """The capped cylinder is the infinite cylinder cut by the slab ``|y| <= h``: the path
        enters it at the later of its two entries, if that precedes both exits."""
        r = param[0]
        d = xl - xs
        tc0, tc1 = ray_disc(xs[0], xs[2], d[0], d[2], r)
        ty0, ty1, sy = slab(xs[1], d[1], param[1])
        t_in = wp.max(tc0, ty0)
        if t_in > ZERO and t_in <= ONE and t_in <= wp.min(tc1, ty1):
            p = xs + t_in * d
            nl = vec3(ZERO, sy, ZERO)
            if tc0 > ty0:
                nl = wp.normalize(vec3(p[0], ZERO, p[2]))
            return 1, p + margin * nl, nl
        return 0, xl, vec3()

    @wp.func
    def shape_cylinder(xl: vec3, param: vec3, margin: scalar):
        r = param[0]
        hh = param[1]
        rho2 = xl[0] * xl[0] + xl[2] * xl[2]
        if rho2 < (r + margin) * (r + margin) and wp.abs(xl[1]) < hh + margin:
            rho = wp.sqrt(rho2)
            if r - rho < hh - wp.abs(xl[1]) and rho > ZERO:
                nl = vec3(xl[0] / rho, ZERO, xl[2] / rho)
                return 1, vec3((r + margin) * nl[0], xl[1], (r + margin) * nl[2]), nl
            sgn = wp.where(xl[1] < ZERO, scalar(-1.0), ONE)
            return 1, vec3(xl[0], sgn * (hh + margin), xl[2]), vec3(ZERO, sgn, ZERO)
        return 0, xl, vec3()

    @wp.func
    def closest_on_triangle(p: vec3, a: vec3, b: vec3, c: vec3):
        """Closest point to ``p`` on the triangle ``abc`` (Voronoi regions of its vertices,
        edges and face), and 1 where it is inside the face (not on an edge or vertex)."""
        ab = b - a
        ac = c - a
        ap = p - a
        d1 = wp.dot(ab, ap)
        d2 = wp.dot(ac, ap)
        bp = p - b
        d3 = wp.dot(ab, bp)
        d4 = wp.dot(ac, bp)
        cp = p - c
        d5 = wp.dot(ab, cp)
        d6 = wp.dot(ac, cp)
        vc = d1 * d4 - d3 * d2
        vb = d5 * d2 - d1 * d6
        va = d3 * d6 - d5 * d4
        out = a
        on_face = 0
        if d1 <= ZERO and d2 <= ZERO:
            out = a
        elif d3 >= ZERO and d4 <= d3:
            out = b
        elif vc <= ZERO and d1 >= ZERO and d3 <= ZERO:
            out = a + ab * (d1 / (d1 - d3))
        elif d6 >= ZERO and d5 <= d6:
            out = c
        elif vb <= ZERO and d2 >= ZERO and d6 <= ZERO:
            out = a + ac * (d2 / (d2 - d6))
        elif va <= ZERO and (d4 - d3) >= ZERO and (d5 - d6) >= ZERO:
            out = b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)))
        else:
            den = ONE / (va + vb + vc)
            out = a + ab * (vb * den) + ac * (vc * den)
            on_face = 1
        return out, on_face

    @wp.func
    def mesh_entry(xl: vec3, xs: vec3, mesh: wp.uint64, lo: vec3, hi: vec3, margin: scalar,
                   verts: wp.array(dtype=vec3), tris: wp.array(dtype=wp.int32), vofs: int, fofs: int):
        """Where the path ``xs -> xl`` (the mesh's own frame) first enters a face of the closed
        mesh, put ``margin`` outward of it, and the face's normal; hit 0 where it enters none.
        The float32 ray only picks the face: the crossing is computed on it from the mesh's
        vertices in the model's precision."""
        # Both ends beyond the padded bounds on the same side: no contact.
        a = wp.min(xl, xs)
        b = wp.max(xl, xs)
        if b[0] < lo[0] or b[1] < lo[1] or b[2] < lo[2] or a[0] > hi[0] or a[1] > hi[1] or a[2] > hi[2]:
            return 0, xl, vec3()
        seg = xl - xs
        seg_len = wp.length(seg)
        if seg_len > ZERO:
            dirf = wp.vec3f(wp.float32(seg[0] / seg_len), wp.float32(seg[1] / seg_len), wp.float32(seg[2] / seg_len))
            start = wp.vec3f(wp.float32(xs[0]), wp.float32(xs[1]), wp.float32(xs[2]))
            ray = wp.mesh_query_ray(mesh, start, dirf, wp.float32(seg_len))
            if ray.result and wp.dot(dirf, ray.normal) < wp.float32(0.0):
                f = 3 * (fofs + ray.face)
                va = verts[vofs + tris[f]]
                vb = verts[vofs + tris[f + 1]]
                vc = verts[vofs + tris[f + 2]]
                nl = wp.normalize(wp.cross(vb - va, vc - va))
                den = wp.dot(seg, nl)
                if den < ZERO:
                    # Where the path crosses the face's plane (the face the float32 ray hit).
                    t = wp.clamp(wp.dot(va - xs, nl) / den, ZERO, ONE)
                    return 1, xs + t * seg + margin * nl, nl
        return 0, xl, vec3()

    @wp.func
    def shape_mesh(xl: vec3, xs: vec3, mesh: wp.uint64, lo: vec3, hi: vec3, margin: scalar,
                   verts: wp.array(dtype=vec3), tris: wp.array(dtype=wp.int32), vofs: int, fofs: int):
        """Closed mesh in its own frame: the entry point of the relative path ``xs -> xl``
        if it enters a face, else the nearest surface point if ``xl`` ends inside.

        Warp's mesh queries are float32: they only pick the face (and inside / outside); the
        entry point and the nearest point are then computed on that face from the mesh's
        vertices in the model's precision, so a float64 run has float64 contact geometry
        and its gradient matches central differences."""
        hit, xc, nl = mesh_entry(xl, xs, mesh, lo, hi, margin, verts, tris, vofs, fofs)
        if hit != 0:
            return hit, xc, nl
        a = wp.min(xl, xs)
        b = wp.max(xl, xs)
        if b[0] < lo[0] or b[1] < lo[1] or b[2] < lo[2] or a[0] > hi[0] or a[1] > hi[1] or a[2] > hi[2]:
            return 0, xl, vec3()
        qf = wp.vec3f(wp.float32(xl[0]), wp.float32(xl[1]), wp.float32(xl[2]))
        far = wp.float32(wp.length(hi - lo))
        res = wp.mesh_query_point(mesh, qf, far)
        if res.result:
            f = 3 * (fofs + res.face)
            va = verts[vofs + tris[f]]
            vb = verts[vofs + tris[f + 1]]
            vc = verts[vofs + tris[f + 2]]
            cl, on_face = closest_on_triangle(xl, va, vb, vc)
            fn = wp.normalize(wp.cross(vb - va, vc - va))
            d = cl - xl
            dl = wp.length(d)
            # Within the margin the face's own plane, in the model's precision, says where the
            # particle is, not float32's sign, which is wrong within its resolution of the
            # face: 99 of 100 particles resting 0 to 2e-8 m above a face 0.3 m from the
            # mesh's origin read inside and were put the margin inside it, their inward speed
            # kept (and one on the edge between two faces went the margin sideways, along
            # round-off's direction of d). Outside but within the margin counts as touching, as the other
            # shapes' grown surfaces do: a particle put the margin out is found there again
            # the next step, not falling back through the margin to be lifted again (a
            # bouncing rest).
            if on_face != 0 and dl < margin:
                return 1, cl + margin * fn, fn
            inside = res.sign < wp.float32(0.0)
            if dl < margin:
                # Nearest an edge or vertex: outside where in front of this face's plane,
                # inside where behind it; in its plane (beyond the edge) float32's sign stands.
                side = wp.dot(fn, -d)
                if side > ZERO:
                    inside = False
                elif side < ZERO:
                    inside = True
            if scalar(1.0e3) * dl <= margin:
                # On an edge or vertex: d is round-off, its direction none to move along.
                return 1, cl + margin * fn, fn
            if inside:
                nl = d / dl
                return 1, cl + margin * nl, nl
            if dl < margin:
                nl = -d / dl
                return 1, cl + margin * nl, nl
        return 0, xl, vec3()

    # Tools of the swept kinds (box, sphere, capsule, cylinder: KINDS[1:5], stored in that
    # order from offsets[1]) differ only in their two contact tests: tool offsets[1] + c's,
    # chosen at code generation (the loop over them is unrolled).
    by_kind = {"box": (swept_box, shape_box), "sphere": (swept_sphere, shape_sphere),
               "capsule": (swept_capsule, shape_capsule), "cylinder": (swept_cylinder, shape_cylinder)}
    tests = [by_kind[kind] for kind, n in zip(KINDS, counts) for _ in range(n) if kind in by_kind]
    swept_test = [t[0] for t in tests]
    inside_test = [t[1] for t in tests]

    @wp.kernel(module="unique")
    def integrate(
        x_in: wp.array(dtype=vec3),
        x_lo_in: wp.array(dtype=vec3),
        v_in: wp.array(dtype=vec3),
        f: wp.array(dtype=vec3),
        mass: wp.array(dtype=scalar),
        gravity: vec3,
        dt: scalar,
        sc: StaticColliders,
        pose_p: wp.array(dtype=vec3),
        pose_q: wp.array(dtype=quat),
        pose_dp: wp.array(dtype=vec3),
        pose_dr: wp.array(dtype=vec3),
        param: wp.array(dtype=vec3),
        mu_s: wp.array(dtype=scalar),
        mu_k: wp.array(dtype=scalar),
        mesh_id: wp.array(dtype=wp.uint64),
        mesh_lo: wp.array(dtype=vec3),
        mesh_hi: wp.array(dtype=vec3),
        mesh_verts: wp.array(dtype=vec3),
        mesh_tris: wp.array(dtype=wp.int32),
        mesh_vofs: wp.array(dtype=wp.int32),
        mesh_fofs: wp.array(dtype=wp.int32),
        margin: scalar,
        pin: wp.array(dtype=wp.int32),
        rest_x: wp.array(dtype=vec3),
        pin_center: wp.array(dtype=vec3),
        world: wp.array(dtype=wp.int32),
        n_tools: int,
        alpha: wp.array(dtype=scalar),
        x_out: wp.array(dtype=vec3),
        x_lo_out: wp.array(dtype=vec3),
        v_out: wp.array(dtype=vec3),
        rforce: wp.array(dtype=vec3),
        rtorque: wp.array(dtype=vec3),
        cforce: wp.array(dtype=vec3),
        ctorque: wp.array(dtype=vec3),
    ):
        i = wp.tid()
        m = mass[i]
        # Every world meets the same tools; each reports its own reaction rows.
        base = world[i] * n_tools
        xe, x_lo, v = kin.symplectic_euler(x_in[i], x_lo_in[i], v_in[i], f[i], m, gravity, dt)
        x = xe
        free = True
        if wp.static(n_pins > 0):
            free = pin[i] < 0
        if free:
            # A pinned particle's place is its pin's: a collider's or tool's response on it
            # was overridden below and yet counted in that collider's reaction (a particle
            # floor under the ground had its weight read twice, once on the ground's row).
            x, v = kin.static_colliders(xe, v, dt, sc, m, world[i] * wp.static(n_planes + n_spheres + n_boxes), cforce, ctorque,
                                        x_in[i], i, alpha)
            for c in range(wp.static(counts[0])):
                k = wp.static(offsets[0]) + c
                hit, xc, nl = shape_plane(local(pose_p[2 * k + 1], pose_q[2 * k + 1], x), param[k])
                x, v = apply(x, v, x_in[i], hit, xc, nl, k, base + k, m, dt, sc.ramp, pose_p, pose_q, pose_dp, pose_dr, mu_s, mu_k, rforce, rtorque)
            for c in range(wp.static(len(swept_test))):
                k = wp.static(offsets[1]) + c
                # The entry point first (a path from outside), the nearest face only for a
                # particle that was already inside: the nearest face of a thin plate that moved
                # past most of a particle could be its back.
                xl = local(pose_p[2 * k + 1], pose_q[2 * k + 1], x)
                hit, xc, nl = wp.static(swept_test[c])(local(pose_p[2 * k], pose_q[2 * k], x_in[i]), xl, param[k], margin)
                if hit == 0:
                    hit, xc, nl = wp.static(inside_test[c])(xl, param[k], margin)
                x, v = apply(x, v, x_in[i], hit, xc, nl, k, base + k, m, dt, sc.ramp, pose_p, pose_q, pose_dp, pose_dr, mu_s, mu_k, rforce, rtorque)
            for c in range(wp.static(counts[5])):
                k = wp.static(offsets[5]) + c
                xl = local(pose_p[2 * k + 1], pose_q[2 * k + 1], x)
                xs = local(pose_p[2 * k], pose_q[2 * k], x_in[i])
                hit, xc, nl = shape_mesh(xl, xs, mesh_id[k], mesh_lo[k], mesh_hi[k], margin, mesh_verts, mesh_tris, mesh_vofs[k], mesh_fofs[k])
                x, v = apply(x, v, x_in[i], hit, xc, nl, k, base + k, m, dt, sc.ramp, pose_p, pose_q, pose_dp, pose_dr, mu_s, mu_k, rforce, rtorque)
                if hit != 0:
                    # The contact's tangential move along the face it met may enter another face
                    # of the same mesh, where a convex shape has none: a particle sliding on a
                    # floor into a 2 mm fin of it at 4 mm a step went through the fin. That
                    # move, from the contact point, meets the mesh as a path does.
                    hit, xc, nl = mesh_entry(local(pose_p[2 * k + 1], pose_q[2 * k + 1], x), xc, mesh_id[k], mesh_lo[k],
                                             mesh_hi[k], margin, mesh_verts, mesh_tris, mesh_vofs[k], mesh_fofs[k])
                    x, v = apply(x, v, x_in[i], hit, xc, nl, k, base + k, m, dt, sc.ramp, pose_p, pose_q, pose_dp, pose_dr, mu_s, mu_k, rforce, rtorque)
        if wp.static(n_pins > 0):
            k = pin[i]
            if k >= 0:
                # x = X + (p - c) + (R - I)(X - c): bit for bit X while the pose is at rest.
                X = rest_x[i]
                c0 = pin_center[k]
                xr = X - c0
                p1 = pose_p[2 * k + 1]
                r1 = wp.quat_rotate(pose_q[2 * k + 1], xr)
                x1 = X + (p1 - c0) + (r1 - xr)
                # The chord (x1 - x0) / dt from the step's displacement: the difference of the
                # two places carried float32's resolution of them (pose_dp).
                v1 = (pose_dp[2 * k + 1] + wp.quat_rotate(pose_q[2 * k], rotation_delta(pose_dr[2 * k + 1], xr))) / dt
                fr = m * (v1 - v_in[i]) / dt - f[i] - m * gravity
                wp.atomic_add(rforce, base + k, fr)
                wp.atomic_add(rtorque, base + k, wp.cross(x1 - p1, fr))
                x = x1
                v = v1
                # The pin's place is the position, whole: an integrated position that rounded
                # onto it kept the integration's round-off, which the next step's fits read as
                # a displacement of a particle that did not move.
                x_lo = vec3()
        x_out[i] = x
        x_lo_out[i] = kin.placed_round_off(x, xe, x_lo)
        v_out[i] = v

    pk = pose_kernels(scalar)
    return types.SimpleNamespace(poses=pk.poses, integrate=integrate, accumulate=pk.accumulate, work=pk.work, quat=quat)


@functools.cache
def _mesh_depth_kernel():
    @wp.kernel(module="unique")
    def mesh_depth(mesh: wp.uint64, x: wp.array(dtype=wp.vec3f), far: wp.float32, depth: wp.array(dtype=wp.float32),
                   closest: wp.array(dtype=wp.vec3f)):
        """How deep ``x[i]`` (in the mesh's frame) lies inside the closed mesh, as the
        contact's own query sees it (``shape_mesh``: inside by ``mesh_query_point``'s sign);
        negative outside; and the nearest point of the mesh (``x[i]`` where none is found)."""
        i = wp.tid()
        depth[i] = wp.float32(-1.0e30)
        closest[i] = x[i]
        res = wp.mesh_query_point(mesh, x[i], far)
        if res.result:
            c = wp.mesh_eval_position(mesh, res.face, res.u, res.v)
            d = wp.length(c - x[i])
            depth[i] = wp.where(res.sign < wp.float32(0.0), d, -d)
            closest[i] = c

    return mesh_depth


# --------------------------------------------------------------------------- tool set
def keyframe_times_problem(times, npf) -> str | None:
    """Why keyframe ``times`` (increasing in float64) are not increasing and finite once cast to
    the numpy type ``npf``, or None."""
    cast = np.asarray(times, dtype=np.float64).astype(npf)
    bad = np.nonzero(~(np.diff(cast) > 0.0))[0]
    prec = np.dtype(npf).name
    if bad.size:
        return f"{times[bad[0]]!r} and {times[bad[0] + 1]!r} are equal in {prec}"
    if not np.isfinite(cast).all():
        return f"they are beyond the {prec} range"
    return None


class _Samples(tuple):
    """The pose kernel's sample arrays (``ToolSet._sample_arrays``) and, on the CPU, numpy
    views of their memory once made (None before)."""

    views = None


def by_kind(tool_colliders: list[Collider]) -> list[Collider]:
    """The tools in the order ``ToolSet`` holds them: by kind (``KINDS``: the order of the
    integrate kernel's loops), each kind's in the order given."""
    return sorted(tool_colliders, key=lambda c: KINDS.index(c.kind))


def tool_names(tool_colliders: list[Collider], pins: list[PinSet]) -> list[str]:
    """The names of the reaction rows of a scene's tools and pinned sets (``ToolSet.names``, one
    world's): the tools ``by_kind``, then the pinned sets. Of a builder's lists too, before the
    model is built."""
    return [c.name for c in by_kind(tool_colliders)] + [p.name for p in pins]


class ToolSet:
    """The model's moving colliders and pinned sets (``model.tools``), and their arrays.

    Differentiable (when the model ``requires_grad``): ``friction`` and ``static_friction``
    (one per tool), ``keyframe_positions`` / ``keyframe_orientations`` (all keyframes of all
    tools, tool ``k``'s from ``keyframe_start[k]``), ``velocity`` and ``angular_velocity`` (one
    per tool; zero for keyframed tools).

    Worlds (``SceneBuilder.finalize(worlds=W)``): every world meets the same tools (one
    motion, one set of parameters, like the shared static colliders) and reports its own
    reaction: ``state.reaction_force`` has one row per world and tool, row ``w * count + k``,
    named ``row_names[w * count + k] = "w<w>/<name>"``. ``world_pins[w][j]``: the particles
    (world-local indices) of pinned set ``j`` in world ``w``; default: ``pins[j].indices``
    in every world.
    """

    def __init__(self, model, tool_colliders: list[Collider], pins: list[PinSet], world_pins=None):
        S, dev = model.scalar, model.device
        T = model.types
        npf = T.np_dtype
        self.colliders = by_kind(tool_colliders)
        self.pins = list(pins)
        self.names = tool_names(self.colliders, self.pins)
        self.counts = tuple(sum(1 for c in self.colliders if c.kind == kind) for kind in KINDS)
        n = len(self.names)
        self.count = n
        W = model.world_count
        self.world_count = W
        #: Names of the reaction rows: the tool names, or with worlds ``"w<w>/<name>"``.
        self.row_names = list(self.names) if W == 1 else [f"w{w}/{name}" for w in range(W) for name in self.names]
        self.scalar = S
        k_ = kernels(S, len(model.planes), len(model.spheres), len(model.boxes), self.counts, len(self.pins))
        self.quat = k_.quat
        self.margin = CONTACT_MARGIN * model.spacing

        x0 = model.particle_x0
        pin_of = np.full(model.particle_count, -1, dtype=np.int32)
        centers = np.zeros((max(n, 1), 3), dtype=npf)
        if world_pins is None:
            world_pins = [[ps.indices for ps in self.pins]] * W
        for j, ps in enumerate(self.pins):
            k = len(self.colliders) + j
            for w in range(W):
                idx = np.asarray(world_pins[w][j]) + model.world_start[w]
                if (pin_of[idx] >= 0).any():
                    raise ValueError(f"pin {ps.name!r} is not allowed: it shares particles with pin {self.names[pin_of[idx].max()]!r}")
                pin_of[idx] = k
                c = x0[idx].astype(np.float64).mean(axis=0)  # a float32 sum drifted 0.27 mm at 1000 m
                if w == 0:
                    centers[k] = c
                elif np.abs(c - centers[k]).max() > 1e-9 * max(1.0, np.abs(centers[k]).max()):
                    # One motion moves the set's frame, whose rest pose is the centroid.
                    raise ValueError(f"pin {ps.name!r} is not allowed with worlds: its rest centroid in world {w} "
                                     f"({c.tolist()}) is not the one in world 0 ({centers[k].tolist()})")

        # Rest pose of each tool: colliders' from their motion, pinned sets' (centroid, I).
        kf_t, kf_p, kf_q, start, lin, ang = [], [], [], [], [], []
        self.motions = [c.motion for c in self.colliders] + [p.motion for p in self.pins]
        for k, motion in enumerate(self.motions):
            rest_p = tuple(centers[k]) if k >= len(self.colliders) else (0.0, 0.0, 0.0)
            start.append(len(kf_p))
            if isinstance(motion, Keyframes):
                kf_t.extend(motion.times)
                kf_p.extend(motion.positions)
                kf_q.extend(motion.orientations)
                lin.append((0.0,) * 3)
                ang.append((0.0,) * 3)
            elif isinstance(motion, Velocity):
                kf_t.append(0.0)
                kf_p.append(motion.position if motion.position is not None else rest_p)
                kf_q.append(motion.orientation if motion.orientation is not None else IDENTITY)
                lin.append(motion.velocity)
                ang.append(motion.angular_velocity)
            else:  # Scripted: the host writes its poses every step
                kf_t.append(0.0)
                kf_p.append(rest_p)
                kf_q.append(IDENTITY)
                lin.append((0.0,) * 3)
                ang.append((0.0,) * 3)
        # Keyframe times that collapse in the model's precision were refused by the builder
        # (SceneBuilder._check_precision, which names a scene file's keys) before the model
        # was made; a split or replicated model keeps its source's precision.
        self.keyframe_start = start
        rg = model.requires_grad

        def arr(values, dtype, grad=False, width=3):
            values = list(values) or [(0.0,) * width if width > 1 else 0.0]
            return wp.array(np.array(values, dtype=npf), dtype=dtype, device=dev, requires_grad=grad and rg)

        self.keyframe_times = arr(kf_t, S, True, 1)
        self.keyframe_positions = arr(kf_p, T.vec3, True)
        self.keyframe_orientations = arr(kf_q, self.quat, True, 4)
        self.velocity = arr(lin, T.vec3, True)
        self.angular_velocity = arr(ang, T.vec3, True)
        self.param = arr([c.param for c in self.colliders] + [(0.0,) * 3] * len(self.pins), T.vec3)
        self.friction = arr([c.friction for c in self.colliders] + [0.0] * len(self.pins), S, True, 1)
        self.static_friction = arr([c.static_friction for c in self.colliders] + [0.0] * len(self.pins), S, True, 1)
        # Meshes: kept referenced here for the model's lifetime (docs/method.md, Warp pitfall 3).
        self.meshes = []
        ids, lo, hi = [], [], []
        # Every mesh's vertices in the model's precision and its triangles, concatenated
        # (the contact geometry, ``shape_mesh``); tool k's from mesh_vofs[k] / mesh_fofs[k].
        verts, tris, vofs, fofs = [], [], [], []
        for c in self.colliders:
            vofs.append(sum(len(v) for v in verts))
            fofs.append(sum(len(t) for t in tris))
            if c.kind == "mesh":
                verts.append(np.asarray(c.mesh_points, dtype=np.float64))
                tris.append(np.asarray(c.mesh_triangles, dtype=np.int32).reshape(-1, 3))
                pts = np.asarray(c.mesh_points, dtype=np.float32)
                mesh = wp.Mesh(points=wp.array(pts, dtype=wp.vec3f, device=dev),
                               indices=wp.array(np.asarray(c.mesh_triangles, dtype=np.int32).ravel(), dtype=wp.int32, device=dev))
                self.meshes.append(mesh)
                ids.append(mesh.id)
                pad = 2.0 * model.support_radius
                lo.append(pts.min(axis=0) - pad)
                hi.append(pts.max(axis=0) + pad)
            else:
                ids.append(0)
                lo.append((0.0,) * 3)
                hi.append((0.0,) * 3)
        self.mesh_id = wp.array(np.array(ids or [0], dtype=np.uint64), dtype=wp.uint64, device=dev)
        self.mesh_lo = arr(lo, T.vec3)
        self.mesh_hi = arr(hi, T.vec3)
        self.mesh_verts = arr(np.concatenate(verts) if verts else [], T.vec3)
        self.mesh_tris = wp.array(np.concatenate(tris).ravel() if tris else np.zeros(3, np.int32), dtype=wp.int32, device=dev)
        self.mesh_vofs = wp.array(np.array(vofs or [0], dtype=np.int32), dtype=wp.int32, device=dev)
        self.mesh_fofs = wp.array(np.array(fofs or [0], dtype=np.int32), dtype=wp.int32, device=dev)
        self.pin = wp.array(pin_of, dtype=wp.int32, device=dev)
        self._pin_of, self._centers = pin_of, centers
        self._still = None  # still_particles(), set by check_arrays from the arrays it checked
        self.rest_x = wp.array(x0, dtype=T.vec3, device=dev)
        self.pin_center = wp.array(centers, dtype=T.vec3, device=dev)
        self.kernels = k_
        self.model = model
        self._warned_scripted = False
        self._held_samples = None
        self._checked_times = None  # (keyframe_times' bytes, motions) that _times_now last found valid
        self._times_view = None  # (keyframe_times, a view of its memory) on the CPU, for _times_now
        self._checked_arrays = None  # the bytes of the other arrays check_arrays last found valid
        self._array_stage = None  # check_arrays' one buffer on a GPU (allocated on first use)
        self._array_views = None  # check_arrays' views of the arrays on the CPU, with the arrays
        self._scripted = [k for k, mo in enumerate(self.motions) if isinstance(mo, Scripted)]
        self._scripted_last = None  # (t0, positions, quaternions) of the last step's samples
        #: ``{(tool, t): (position, quaternion)}`` of the Scripted poses evaluated while a
        #: ``Rollout`` records them (its forward, and the re-runs it checks against that forward).
        self._pose_log = None
        self._reach_of = {}

    def mesh_depth(self, k: int, xl: np.ndarray, closest: bool = False):
        """How deep each point ``xl`` (N, 3), in mesh tool ``k``'s own frame, lies inside it
        (negative: outside; float32, as the contact's mesh queries); ``closest=True``: and the
        nearest point of the mesh to each, ``(depth, points)``."""
        c = self.colliders[k]
        pts = np.asarray(c.mesh_points, dtype=np.float64)
        far = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
        if not len(xl):
            return (np.zeros(0), np.zeros((0, 3))) if closest else np.zeros(0)
        dev = self.model.device
        out = wp.empty(len(xl), dtype=wp.float32, device=dev)
        near = wp.empty(len(xl), dtype=wp.vec3f, device=dev)
        wp.launch(_mesh_depth_kernel(), len(xl), [wp.uint64(int(self.mesh_id.numpy()[k])),
                  wp.array(np.asarray(xl, dtype=np.float32), dtype=wp.vec3f, device=dev), far], [out, near], device=dev)
        depth = out.numpy().astype(np.float64)
        return (depth, near.numpy().astype(np.float64)) if closest else depth

    def _owner(self, k: int) -> str:
        """Tool ``k`` as messages name it."""
        return f"{'tool' if k < len(self.colliders) else 'pinned set'} {self.names[k]!r}"

    def _scripted_pose(self, k: int, t: float):
        """Tool ``k``'s ``Scripted`` pose at ``t``, checked against the model's precision (a
        pose at 1e39 m in float32 wrote NaN poses and the run went on)."""
        owner = self._owner(k)
        p, q = self.motions[k].pose(t, owner)
        far = _far(self.model.types.np_dtype)
        if max(abs(c) for c in p) > far:
            prec = np.dtype(self.model.types.np_dtype).name
            raise ValueError(f"{owner}: its scripted motion at t = {t:g} is not allowed in {prec}: it returned position = "
                             f"{p!r}, beyond {far:.3g} m; use dtype=float64 or a nearer position")
        if self._pose_log is not None:
            self._pose_log[(k, t)] = (p, q)
        return p, q

    def _times_now(self) -> np.ndarray:
        """The keyframe times as they are now (an optimiser may have changed the array)."""
        if not any(isinstance(mo, Keyframes) for mo in self.motions):
            return np.zeros(0)
        arr = self.keyframe_times
        held = self._times_view
        if held is not None and held[0] is arr:
            raw = held[1]
        else:
            raw = arr.numpy()
            # On the CPU a view of the array's memory, kept while it is the same array: a view
            # made at each of the step's two calls cost more than the checks it keys.
            self._times_view = (arr, raw) if arr.device.is_cpu else None
        kt = raw.astype(np.float64)
        # Every step asks: the checks below ran on these very values at an earlier call.
        key = (raw.tobytes(), tuple(self.motions))
        if self._checked_times == key:
            return kt
        for k, mo in enumerate(self.motions):
            if isinstance(mo, Keyframes):
                ts = kt[self.keyframe_start[k]:self.keyframe_start[k] + len(mo.times)]
                if not np.isfinite(ts).all() or np.any(np.diff(ts) <= 0.0):
                    raise ValueError(f"keyframe_times of tool {self.names[k]!r} = {checks.shorten(ts.tolist())!r} is not allowed: must be finite and increasing")
        self._checked_times = key
        return kt

    def check_arrays(self) -> None:
        """Refuse (``ValueError``) the tools' differentiable arrays as they are now where no
        tool could hold them (an optimiser, or a caller, writes them in place): keyframe times
        finite and increasing (``_times_now``), friction coefficients finite and >= 0,
        velocities and keyframe positions finite, keyframe orientations finite and non-zero.
        ``Solver.step`` calls it before its first launch. Unchecked, a NaN keyframe position
        took the tool out of the contact and a negative friction drove the material along it,
        and the run went on without a word; a NaN friction ran to NaN positions."""
        self._times_now()
        names = ("friction", "static_friction", "velocity", "angular_velocity", "keyframe_positions", "keyframe_orientations")
        arrays = [getattr(self, name) for name in names]
        if self.model.device.is_cpu:
            # Views of the arrays' memory, kept while they are the same arrays: nothing is copied,
            # and a view made per array and step cost twice the check.
            held = self._array_views
            if held is None or any(a is not b for a, b in zip(held[0], arrays)):
                held = self._array_views = (arrays, [a.numpy() for a in arrays])
            raw = held[1]
        else:
            # One transfer: each read of a device array waits for the device, and every step asks.
            flat = [a.view(self.scalar).flatten() if a.ndim == 1 and a.dtype != self.scalar else a for a in arrays]
            sizes = [f.shape[0] for f in flat]
            stage = self._array_stage
            if stage is None or stage.shape[0] != sum(sizes):
                stage = self._array_stage = wp.empty(sum(sizes), dtype=self.scalar, device=self.model.device)
            offset = 0
            for f, size in zip(flat, sizes):
                wp.copy(stage, f, dest_offset=offset, count=size)
                offset += size
            host, offset, raw = stage.numpy(), 0, []
            for a, size in zip(arrays, sizes):
                raw.append(host[offset:offset + size].reshape(a.shape[0], -1))
                offset += size
        key = b"".join(np.ascontiguousarray(r).tobytes() for r in raw)
        # Every step asks: the values below were found valid at an earlier call.
        if self._checked_arrays == key:
            return
        values = {name: np.asarray(r, dtype=np.float64).reshape(a.shape[0], -1) for name, r, a in zip(names, raw, arrays)}

        def refuse(name, k, value, allowed):
            shown = checks.shorten(np.round(value, 12).tolist())
            raise ValueError(f"{name} of {self._owner(k)} = {checks.shorten(shown)!r} is not allowed: {allowed}")

        for k in range(len(self.colliders)):  # a pinned set has no friction
            for name in ("friction", "static_friction"):
                v = float(values[name][k, 0])
                if not (math.isfinite(v) and v >= 0.0):
                    refuse(name, k, v, "must be a finite number >= 0")
        for k, motion in enumerate(self.motions):
            for name in ("velocity", "angular_velocity"):
                if not np.isfinite(values[name][k]).all():
                    refuse(name, k, values[name][k], "must be finite")
            rows = slice(self.keyframe_start[k], self.keyframe_start[k] + (len(motion.times) if isinstance(motion, Keyframes) else 1))
            p, q = values["keyframe_positions"][rows], values["keyframe_orientations"][rows]
            if not np.isfinite(p).all():
                refuse("keyframe_positions", k, p, "must be finite")
            if not np.isfinite(q).all() or not (np.abs(q).max(axis=1) > 0.0).all():
                refuse("keyframe_orientations", k, q, "must be finite quaternions (x, y, z, w), none zero")
        self._still = self._still_flags(values)
        self._checked_arrays = key

    def _still_flags(self, values: dict):
        """``still_particles`` of the arrays' checked ``values``: a pinned set stays at its
        rest pose, bit for bit, under a ``Velocity`` motion with both velocities 0 from the
        set's own rest pose (its position the rest centroid as stored, its orientation the
        identity): every pinned place is then ``X + 0 + 0`` (``integrate``)."""
        still = []
        for k in range(len(self.colliders), self.count):
            start = self.keyframe_start[k]
            if (isinstance(self.motions[k], Velocity) and not values["velocity"][k].any()
                    and not values["angular_velocity"][k].any()
                    and (values["keyframe_positions"][start] == self._centers[k]).all()
                    and (values["keyframe_orientations"][start] == IDENTITY).all()):
                still.append(k)
        if not still:
            return None
        # Each set's own number (+ 1): a pair of two sets' particles moves both their rows.
        flags = np.where(np.isin(self._pin_of, still), np.asarray(self._pin_of) + 1, 0).astype(np.int32)
        held = self._still
        if held is not None and np.array_equal(held.numpy(), flags):
            return held
        return wp.array(flags, dtype=wp.int32, device=self.model.device)

    def still_particles(self):
        """Per particle its set's number + 1 where it is pinned to a set that stays at its rest
        pose (``_still_flags``) as the tools' arrays were at the last ``check_arrays`` (which
        ``Solver.step`` calls before its first launch: an optimiser that moves such a set is
        seen at the next step), else 0; None where no set stays at rest. The fused step leaves
        out the neighbour passes of those with only their own set's such particles in their
        rows (``fused.out_of_reach``)."""
        return self._still

    def motion_gradient(self, name: str) -> dict[str, np.ndarray]:
        """The gradient a backward pass left on tool ``name``'s motion parameters:
        ``Keyframes``: ``{"times", "positions", "orientations"}`` (its keyframes' rows);
        ``Velocity``: ``{"velocity", "angular_velocity"}``; a held tool (``motion=None``) is
        a ``Velocity`` of zero. A ``Scripted`` motion is evaluated on the host and has no
        gradient: ``ValueError`` rather than zeros that would read as "no sensitivity"."""
        k = self.index(name)
        motion = self.motions[k]
        if isinstance(motion, Scripted):
            raise ValueError(f"tool {name!r} follows a tools.Scripted motion, which is not allowed here: a Python callable "
                             "is evaluated on the host and has no gradient; give the motion as tools.Keyframes or "
                             "tools.Velocity to differentiate through it")
        if not self.model.requires_grad:
            raise ValueError(f"tool {name!r}: the model has requires_grad = False, which is not allowed here: build it "
                             "with SceneBuilder.finalize(requires_grad=True) to get gradients")

        def grad(a, rows):
            g = a.grad
            return np.zeros((len(rows),) + a.numpy().shape[1:]) if g is None else g.numpy()[rows].astype(np.float64)

        if isinstance(motion, Keyframes):
            rows = np.arange(self.keyframe_start[k], self.keyframe_start[k] + len(motion.times))
            return {"times": grad(self.keyframe_times, rows), "positions": grad(self.keyframe_positions, rows),
                    "orientations": grad(self.keyframe_orientations, rows)}
        return {"velocity": grad(self.velocity, [k])[0], "angular_velocity": grad(self.angular_velocity, [k])[0]}

    def _warn_scripted_on_tape(self):
        if self._warned_scripted:
            return
        names = [n for n, mo in zip(self.names, self.motions) if isinstance(mo, Scripted)]
        if names:
            self._warned_scripted = True
            warnings.warn(f"tools {names!r} follow tools.Scripted motions, evaluated on the host: a taped step records "
                          "their poses as constants, so no gradient flows to their motion (other parameters' gradients "
                          "are unaffected); use tools.Keyframes or tools.Velocity for a differentiable motion",
                          stacklevel=4)

    def index(self, name: str) -> int:
        if name not in self.names:
            raise ValueError(f"name = {checks.shorten(name)!r} is not allowed: must be one of the tools {self.names!r}")
        return self.names.index(name)

    # ------------------------------------------------------------------ per step
    def _samples(self, t0: float, t1: float):
        n = self.count
        i0 = np.zeros(2 * n, dtype=np.int32)
        i1 = np.zeros(2 * n, dtype=np.int32)
        w = np.zeros(2 * n)
        ts = np.zeros(2 * n)
        direct = np.zeros(2 * n, dtype=np.int32)
        sp = np.zeros((2 * n, 3))
        sq = np.zeros((2 * n, 4))
        sq[:] = IDENTITY
        sdp = np.zeros((2 * n, 3))
        sdr = np.zeros((2 * n, 3))
        kt = self._times_now().tolist()
        for k, motion in enumerate(self.motions):
            for j, t in enumerate((t0, t1)):
                s = 2 * k + j
                ts[s] = t
                base = self.keyframe_start[k]
                if isinstance(motion, Keyframes):
                    a, b, w[s] = sample_times(kt[base:base + len(motion.times)], t)
                    i0[s], i1[s] = base + a, base + b
                elif isinstance(motion, Velocity):
                    i0[s] = i1[s] = base
                else:
                    direct[s] = 1
                    sp[s], sq[s] = self._scripted_pose(k, t)
            if direct[2 * k]:
                # A Scripted step's displacement and rotation, differenced in float64 here
                # (pose_dp); another motion's rows hold the origin and the identity, whose
                # difference is the zeros they were made with.
                sdp[2 * k + 1] = sp[2 * k + 1] - sp[2 * k]
                sdr[2 * k + 1] = _np_log(_np_mul(_np_conj(sq[2 * k]), sq[2 * k + 1]))
        if self._scripted:
            self._scripted_last = (t0, sp, sq)
        return i0, i1, w, ts, direct, sp, sq, sdp, sdr

    def _sample_arrays(self, host, held):
        """``_samples`` on the device, refilled into ``held`` (the arrays of an earlier
        call) where they match, else in new arrays (an array made each step cost more than
        the pose kernel at small particle counts)."""
        m = self.model
        T = m.types
        dtypes = (wp.int32, wp.int32, m.scalar, m.scalar, wp.int32, T.vec3, self.quat, T.vec3, T.vec3)
        if held is None or any(a.shape[0] != h.shape[0] or a.dtype != d for a, h, d in zip(held, host, dtypes)):
            return _Samples(wp.array(h if d is wp.int32 else h.astype(T.np_dtype), dtype=d, device=m.device)
                            for h, d in zip(host, dtypes))
        views = None
        if held[0].device.is_cpu:
            # Views of the arrays' memory, kept with them, the untaped set's and each taped
            # state's alike (a view made per array and step cost about as much as the pose
            # kernel at small particle counts).
            views = held.views
            if views is None:
                views = held.views = [a.numpy() for a in held]
        for k, (a, h, d) in enumerate(zip(held, host, dtypes)):
            if views is not None:
                # Assigning the float64 samples casts them as astype would, without its copy.
                views[k][...] = h
            else:
                a.assign(h if d is wp.int32 else h.astype(T.np_dtype))
        return held

    def integrate(self, solver, state_in, state_out, dt: float):
        """Poses at the step's start and end, then the integrate kernel (see module doc)."""
        m = self.model
        S, dev, T = m.scalar, m.device, m.types
        n = self.count
        taping = _taping()
        # A tape reads the samples again in its backward pass: each output state keeps its
        # own, refilled when a later step writes that state again (which overwrites what an
        # earlier tape recorded into it anyway); untaped steps share one set.
        held = getattr(state_out, "tool_samples", None) if taping else self._held_samples
        samples = self._sample_arrays(self._samples(state_in.time, state_in.time + dt), held)
        step = S(dt)
        if taping:
            if samples is not held:  # setting a State attribute makes the next step check it again
                state_out.tool_samples = samples
            self._warn_scripted_on_tape()
        else:
            self._held_samples = samples
        self.model.launches(
            self.kernels.poses, 2 * n,
            [self.keyframe_times, self.keyframe_positions, self.keyframe_orientations, self.velocity, self.angular_velocity, *samples,
             step],
            [state_out.tool_pose_p, state_out.tool_pose_q, state_out.tool_pose_dp, state_out.tool_pose_dr], device=dev,
        )
        state_out.reaction_force.zero_()
        state_out.reaction_torque.zero_()
        state_out.collider_force.zero_()
        state_out.collider_torque.zero_()
        reactions = (state_out.reaction_force, state_out.reaction_torque, state_out.collider_force,
                     state_out.collider_torque)
        # The generated adjoint replays the forward's atomic adds into the reaction rows: a
        # backward pass left them 2-3x the step's (tests/test_contracts.py).
        with kept_through_backward(*reactions):
            self.model.launches(
                self.kernels.integrate,
                m.particle_count,
                [
                    state_in.x, state_in.x_lo, state_in.v, state_out.force, m.particle_mass, T.vec3(*m.gravity), step,
                    static_collider_struct(m),
                    state_out.tool_pose_p, state_out.tool_pose_q, state_out.tool_pose_dp, state_out.tool_pose_dr, self.param, self.static_friction, self.friction,
                    self.mesh_id, self.mesh_lo, self.mesh_hi, self.mesh_verts, self.mesh_tris, self.mesh_vofs,
                    self.mesh_fofs, S(self.margin),
                    self.pin, self.rest_x, self.pin_center, m.particle_world, int(n), state_in.alpha,
                ],
                [state_out.x, state_out.x_lo, state_out.v, *reactions],
                device=dev,
            )
        acc = getattr(solver, "tool_impulse", None)
        if acc is not None and not taping:
            rows = n * self.world_count
            self.model.launches(self.kernels.accumulate, rows, [state_out.reaction_force, step], [acc[0]], device=dev)
            self.model.launches(self.kernels.accumulate, rows, [state_out.reaction_torque, step], [acc[1]], device=dev)
        work = getattr(solver, "tool_work", None)
        if work is not None and not taping:
            self.launch_work(state_out, work)

    def launch_work(self, state, dst: wp.array):
        """``work``: add to ``dst`` (float64, one per reaction row) the work each row did in the
        step that produced ``state``, from the reactions and tool motion ``state`` holds."""
        self.model.launches(self.kernels.work, self.count * self.world_count,
                            [state.reaction_force, state.reaction_torque, state.tool_pose_q, state.tool_pose_dp,
                             state.tool_pose_dr, int(self.count)], [dst], device=self.model.device)

    # ----------------------------------------------------------------- queries
    def reaction(self, state) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """``{tool name: (force, torque)}`` the tool exerted on the material in the step that
        produced ``state`` (N and N m; torque about the tool's position at the step end).
        With worlds, one entry per world and tool, keyed ``"w<w>/<name>"`` (``row_names``)."""
        f = state.reaction_force.numpy()
        tq = state.reaction_torque.numpy()
        return {name: (f[r].astype(np.float64), tq[r].astype(np.float64)) for r, name in enumerate(self.row_names)}

    def pose(self, state) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """``{tool name: (position, quaternion (x, y, z, w))}`` at ``state.time``."""
        return {name: self.pose_at(k, state.time) for k, name in enumerate(self.names)}

    def reach(self, k: int) -> float:
        """The largest distance from tool ``k``'s origin to a point of it that may meet the
        material: a shape's farthest surface point, a pinned set's farthest particle from its
        centroid; a plane's (unbounded) the farthest particle from its first position."""
        x0 = np.asarray(self.model.particle_x0, dtype=np.float64)
        if k >= len(self.colliders):
            idx = np.asarray(self.pins[k - len(self.colliders)].indices)
            return float(np.linalg.norm(x0[idx] - x0[idx].mean(axis=0), axis=1).max())
        c = self.colliders[k]
        a, b, _ = (float(v) for v in c.param)
        if c.kind == "plane":
            p, _ = self.pose_at(k, 0.0)
            return float(np.linalg.norm(x0 - p, axis=1).max()) if len(x0) else 0.0
        if c.kind == "box":
            return float(np.linalg.norm(c.param))
        if c.kind == "capsule":
            return a + b
        if c.kind == "cylinder":
            return math.hypot(a, b)
        if c.kind == "mesh":
            return float(np.linalg.norm(np.asarray(c.mesh_points, dtype=np.float64), axis=1).max())
        return a

    def fastest(self, t0: float, t1: float) -> list[tuple[int, float, float]]:
        """``(k, speed, t)`` for each tool and pinned set whose motion is known before the run
        (``Keyframes``, ``Velocity``; a ``Scripted`` one is checked at each step of a run,
        ``check_scripted_step``): the bound
        ``|v| + |omega| reach`` on the speed of its points between times ``t0`` and ``t1``, and
        when it is reached (a keyframe segment's start, or ``t0``)."""
        out = []
        vel = self.velocity.numpy().astype(np.float64)
        ang = self.angular_velocity.numpy().astype(np.float64)
        for k, motion in enumerate(self.motions):
            if isinstance(motion, Scripted):
                continue
            r = self.reach(k)
            best, when = float(np.linalg.norm(vel[k]) + np.linalg.norm(ang[k]) * r), t0
            if isinstance(motion, Keyframes):
                base = self.keyframe_start[k]
                ts = self._times_now()[base:base + len(motion.times)]
                kp = self.keyframe_positions.numpy().astype(np.float64)[base:base + len(ts)]
                kq = self.keyframe_orientations.numpy().astype(np.float64)[base:base + len(ts)]
                kq = kq / np.linalg.norm(kq, axis=1, keepdims=True)
                lin = best
                for j in range(len(ts) - 1):
                    if ts[j + 1] <= t0 or ts[j] >= t1:
                        continue
                    span = ts[j + 1] - ts[j]
                    turn = 2.0 * math.acos(min(1.0, abs(float(np.dot(kq[j], kq[j + 1])))))
                    speed = lin + (np.linalg.norm(kp[j + 1] - kp[j]) + turn * r) / span
                    if speed > best:
                        best, when = float(speed), max(float(ts[j]), t0)
            out.append((k, best, when))
        return out

    def check_speed(self, dt: float, t0: float, t1: float) -> None:
        """Refuse a tool or pinned set that moves more than one spacing in a step of ``dt``
        between ``t0`` and ``t1``, as a start faster than that is refused
        (``simulate.check_start_speed``): the contact is swept, so such a tool passes no
        particle, but every particle it meets is given its speed, more than one spacing a step,
        and the material can no longer follow (a box at 3 spacings a step flattened a block
        into a sheet half a millimetre thick and the run exited 0). A ``Scripted`` motion is
        not called here: it may read what the run's callback sets, so ``simulate`` checks it
        at each step, from the poses the step evaluates (``check_scripted_step``)."""
        for k, speed, when in self.fastest(t0, t1):
            if not speed <= self.model.spacing / dt:
                raise self._too_fast(k, speed, when, dt)

    def _too_fast(self, k: int, speed: float, when: float, dt: float) -> ValueError:
        from .simulate import StepRefusal  # noqa: PLC0415 (simulate imports this module)

        limit = self.model.spacing / dt
        return StepRefusal(
            f"{self._owner(k)}: its {type(self.motions[k]).__name__} motion moves its points at up to {speed:.3g} m/s "
            f"(|v| + |omega| r, r = {self.reach(k):.3g} m; from t = {when:.4g} s), which is not allowed at dt = "
            f"{dt:.4g} s: a step may carry a tool at most one spacing ({self.model.spacing:g} m), so at most "
            f"{limit:.3g} m/s", TOO_FAST_ADVICE)

    def check_scripted_step(self, dt: float) -> None:
        """Refuse (``ValueError``, ``check_speed``'s message) a ``Scripted`` tool or pinned set
        that the last step moved more than one spacing, bounded as ``|dp| / dt + |d angle| r /
        dt`` from the poses that step evaluated at its start and end (the callable is not
        called again: it may be slow, have side effects, or read what the run has set since)."""
        last = self._scripted_last
        if last is None:
            return
        t0, sp, sq = last
        for k in self._scripted:
            p0, p1 = sp[2 * k], sp[2 * k + 1]
            q0, q1 = sq[2 * k], sq[2 * k + 1]
            turn = 2.0 * math.acos(min(1.0, abs(float(np.dot(q0, q1)))))
            if turn:
                turn *= self._scripted_reach(k)
            speed = (float(np.linalg.norm(p1 - p0)) + turn) / dt
            if not speed <= self.model.spacing / dt:
                raise self._too_fast(k, speed, t0, dt)

    def scripted_step_motion(self, dt: float) -> dict:
        """``{k: (linear speed, angular speed, start position, end position)}`` of each
        ``Scripted`` motion over the last step of ``dt``, from the poses that step evaluated
        (the callable is not called again, as in ``check_scripted_step``); empty before a step."""
        last = self._scripted_last
        if last is None:
            return {}
        _, sp, sq = last
        seen = {}
        for k in self._scripted:
            turn = 2.0 * math.acos(min(1.0, abs(float(np.dot(sq[2 * k], sq[2 * k + 1])))))
            seen[k] = (float(np.linalg.norm(sp[2 * k + 1] - sp[2 * k])) / dt, turn / dt, sp[2 * k], sp[2 * k + 1])
        return seen

    def _scripted_reach(self, k: int) -> float:
        # Computed once: a plane's reads its pose at t = 0, which would call the function again.
        if k not in self._reach_of:
            self._reach_of[k] = self.reach(k)
        return self._reach_of[k]

    def pose_at(self, k: int, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Pose of tool ``k`` at time ``t`` evaluated on the host (the same formulas as ``poses``)."""
        motion = self.motions[k]
        base = self.keyframe_start[k]
        kp = self.keyframe_positions.numpy().astype(np.float64)
        kq = self.keyframe_orientations.numpy().astype(np.float64)
        if isinstance(motion, Scripted):
            p, q = self._scripted_pose(k, t)
            return np.array(p), np.array(q)
        if isinstance(motion, Keyframes):
            a, b, w = sample_times(self._times_now()[base:base + len(motion.times)], t)
        else:
            a, b, w = 0, 0, 0.0
        p = kp[base + a] * (1 - w) + kp[base + b] * w + self.velocity.numpy()[k] * t
        q = _np_mul(_np_exp(self.angular_velocity.numpy()[k].astype(np.float64) * t), _np_slerp(kq[base + a], kq[base + b], w))
        return p, q


@functools.cache
def _far(np_dtype) -> float:
    """The farthest position a scripted pose may take in ``np_dtype`` (the square root of its
    largest number); asked twice a step."""
    return math.sqrt(float(np.finfo(np_dtype).max))


def _taping() -> bool:
    from .sim.solver import tape_recording  # noqa: PLC0415 (solver imports this module)

    return tape_recording()


def _np_exp(r):
    th = np.linalg.norm(r)
    if th < 1e-12:
        return np.array([0.0, 0.0, 0.0, 1.0])
    a = r / th * math.sin(th / 2)
    return np.array([a[0], a[1], a[2], math.cos(th / 2)])


def _np_mul(a, b):
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ])


def _norm(v) -> float:
    """``np.linalg.norm`` of a float64 vector by its own formula, without its dispatch (asked
    several times a step of a scripted tool): the same bits."""
    return math.sqrt(v.dot(v))


def _np_conj(q):
    q = np.asarray(q, dtype=np.float64)
    q = q / _norm(q)
    return np.array([-q[0], -q[1], -q[2], q[3]])


def _np_log(q):
    """Rotation vector of the (normalised) quaternion ``q``, as ``quat_log`` in the pose kernel."""
    q = np.asarray(q, dtype=np.float64)
    q = q / _norm(q)
    sv = _norm(q[:3])
    return q[:3] * (2.0 * math.atan2(sv, q[3]) / sv if sv > 1e-12 else 2.0 / q[3])


def _np_slerp(a, b, w):
    d = float(np.dot(a, b))
    if d > 0.99999:
        q = a * (1 - w) + b * w
        return q / np.linalg.norm(q)
    th = math.acos(min(d, 1.0))
    return (a * math.sin((1 - w) * th) + b * math.sin(w * th)) / math.sin(th)


def quat_to_matrix(q) -> np.ndarray:
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def allocate_state(model, state, requires_grad: bool):
    """The per-step tool arrays of a ``State`` (poses at the step's start and end, reaction
    force and torque per tool); none when the model has no tools."""
    tools = getattr(model, "tools", None)
    if tools is None:
        return
    n, T, dev = tools.count, model.types, model.device
    rows = n * tools.world_count
    state.tool_pose_p = wp.zeros(2 * n, dtype=T.vec3, device=dev, requires_grad=requires_grad)
    state.tool_pose_q = wp.zeros(2 * n, dtype=tools.quat, device=dev, requires_grad=requires_grad)
    state.tool_pose_dp = wp.zeros(2 * n, dtype=T.vec3, device=dev, requires_grad=requires_grad)
    state.tool_pose_dr = wp.zeros(2 * n, dtype=T.vec3, device=dev, requires_grad=requires_grad)
    state.reaction_force = wp.zeros(rows, dtype=T.vec3, device=dev, requires_grad=requires_grad)
    state.reaction_torque = wp.zeros(rows, dtype=T.vec3, device=dev, requires_grad=requires_grad)


# --------------------------------------------------------------------------- selection
#: How far outside a pin's ``region`` (in spacings) a particle is still taken: round-off of the
#: lattice's coordinates, not a margin (a face 1e-9 m off a layer at spacing 0.01 still leaves it
#: out). Far from the origin the coordinates' own round-off is added
#: (``meshes.coordinate_round_off``: a few float64 roundings at their magnitude).
REGION_TOLERANCE = 1e-9


def select_particles(builder, *, indices=None, body=None, region=None, where=None, name: str) -> np.ndarray:
    """Indices of the particles selected by all the given criteria (intersection): an index
    array, a body (its name or index), an axis-aligned box ``region = (lo, hi)`` and a predicate ``where``
    on rest positions ``(N, 3) -> bool (N,)``."""
    n = builder.particle_count
    points = np.concatenate(builder._points) if builder._points else np.zeros((0, 3))
    mask = np.ones(n, dtype=bool)
    if indices is None and body is None and region is None and where is None:
        raise ValueError(f"pin {name!r}: no selection is not allowed: give indices, body, region and/or where")
    if indices is not None:
        idx = np.asarray(indices)
        if idx.size == 0:  # [] read as floats was "must be integers"; an empty array "holds no particle"
            raise ValueError(f"pin {name!r} is not allowed: indices = {checks.shorten(indices)!r} select no particle")
        if idx.dtype == bool:
            if idx.shape != (n,):
                raise ValueError(f"indices with shape {idx.shape} is not allowed: a boolean mask must have one entry per particle ({n})")
            sel = idx
        else:
            if idx.ndim != 1 or not np.issubdtype(idx.dtype, np.integer) or (idx.size and (idx.min() < 0 or idx.max() >= n)):
                # Shortened: a list of 1e5 indices with one out of range was a message of 0.7 MB,
                # a 2-D array's repr one of several lines.
                raise ValueError(f"indices = {checks.shorten(indices)!r} is not allowed: must be integers in [0, {n - 1}]")
            sel = np.zeros(n, dtype=bool)
            sel[idx] = True
        mask &= sel
    if body is not None:
        # A name or the index an add_* returned, as add_particle_floor and add_compression_field
        # take it (an index was refused here alone).
        b = builder._bodies[builder._body_index(body)]
        sel = np.zeros(n, dtype=bool)
        sel[b.start:b.start + b.count] = True
        mask &= sel
    if region is not None:
        try:
            lo, hi = (np.array(checks.vector("region", r)) for r in region)
        except (TypeError, ValueError):
            raise ValueError(f"region = {checks.shorten(region)!r} is not allowed: must be (lo, hi), two 3-vectors of "
                             "finite numbers") from None
        if np.any(hi < lo):
            raise ValueError(f"region = {checks.shorten(region)!r} is not allowed: lo must be <= hi in every axis")
        # A face written at a lattice layer's value takes that layer: the lattice's coordinates
        # carry round-off (0.1 - 0.04 is 0.06000000000000001), and a face at 0.06 had left the
        # bottom layer out while a face at the top layer's value took it (a quarter of such faces
        # missed their layer). The lattice's own count takes the same 1e-9 spacings. Far out the
        # coordinates' own round-off passes that (at |x| = 1e5, 1.5e-11 m a rounding, 1.5e-9 of a
        # 0.01 spacing: three in four faces so written missed their layer); it is float64's, as
        # the builder's coordinates are in either precision.
        tol = REGION_TOLERANCE * builder.spacing + coordinate_round_off(points)
        mask &= np.all((points >= lo - tol) & (points <= hi + tol), axis=1)
    if where is not None:
        mask &= checks.selection("where", where, points, "rest_positions")
    out = np.nonzero(mask)[0]
    if out.size == 0:
        raise ValueError(f"pin {name!r} is not allowed: the selection holds no particle")
    return out


# ------------------------------------------------------------------------ tool meshes
def box_mesh(half_extents) -> tuple[np.ndarray, np.ndarray]:
    """A closed box mesh ``(points, triangles)`` centred at the origin, outward wound."""
    hx, hy, hz = checks.positive_vector("half_extents", half_extents)
    p = np.array([[sx * hx, sy * hy, sz * hz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return p, np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], dtype=np.int32)


def blade_mesh(length: float, height: float, thickness: float) -> tuple[np.ndarray, np.ndarray]:
    """A closed knife blade: a triangular prism along z (``length``), its sharp edge at
    y = 0 and its back (``thickness`` wide in x) at y = ``height``, outward wound."""
    L, H, T = (checks.positive(n, v) for n, v in (("length", length), ("height", height), ("thickness", thickness)))
    p = np.array([[0.0, 0.0, -L / 2], [-T / 2, H, -L / 2], [T / 2, H, -L / 2],
                  [0.0, 0.0, L / 2], [-T / 2, H, L / 2], [T / 2, H, L / 2]])
    tris = np.array([[0, 2, 1], [3, 4, 5], [0, 1, 4], [0, 4, 3], [0, 3, 5], [0, 5, 2], [1, 2, 5], [1, 5, 4]], dtype=np.int32)
    return p, np.ascontiguousarray(tris[:, ::-1])


# ------------------------------------------------------------------------------- USD
USD_ROOT = "/World/Tools"


def usd_author(stage, model, key: str = "warp_esph", plane_size: float = 1.0):
    """One Xform prim per tool under ``/World/Tools`` (pose written per frame by
    ``usd_write_frame``) with its geometry in the tool's frame as a child ``geom``; pinned
    sets get an Xform only. Static custom data: kind, friction coefficients."""
    from pxr import Gf, Sdf, Usd, UsdGeom, Vt  # noqa: PLC0415 (USD only when writing it)

    tools = getattr(model, "tools", None)
    if tools is None:
        return
    UsdGeom.Scope.Define(stage, USD_ROOT)
    steel = Vt.Vec3fArray([Gf.Vec3f(0.62, 0.64, 0.7)])
    for k, (name, prim_name) in enumerate(zip(tools.names, usd_names(tools.names))):
        path = f"{USD_ROOT}/{prim_name}"
        xf = UsdGeom.Xform.Define(stage, path)
        xf.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble)
        xf.AddOrientOp(UsdGeom.XformOp.PrecisionDouble)
        prim = xf.GetPrim()
        prim.SetCustomDataByKey(f"{key}:tool_name", name)
        prim.CreateAttribute(f"{key}:reaction_force", Sdf.ValueTypeNames.Double3)
        prim.CreateAttribute(f"{key}:reaction_torque", Sdf.ValueTypeNames.Double3)
        if k >= len(tools.colliders):
            prim.SetCustomDataByKey(f"{key}:tool", "pin")
            prim.SetCustomDataByKey(f"{key}:particle_count", int(len(tools.pins[k - len(tools.colliders)].indices)))
            continue
        c = tools.colliders[k]
        prim.SetCustomDataByKey(f"{key}:tool", c.kind)
        prim.SetCustomDataByKey(f"{key}:friction", float(c.friction))
        prim.SetCustomDataByKey(f"{key}:static_friction", float(c.static_friction))
        g = f"{path}/geom"
        if c.kind == "box":
            geom = UsdGeom.Cube.Define(stage, g)
            geom.CreateSizeAttr(2.0)
            geom.AddScaleOp().Set(Gf.Vec3f(*c.param))
        elif c.kind == "sphere":
            geom = UsdGeom.Sphere.Define(stage, g)
            geom.CreateRadiusAttr(float(c.param[0]))
        elif c.kind in ("capsule", "cylinder"):
            geom = (UsdGeom.Capsule if c.kind == "capsule" else UsdGeom.Cylinder).Define(stage, g)
            geom.CreateRadiusAttr(float(c.param[0]))
            geom.CreateHeightAttr(2.0 * float(c.param[1]))
            geom.CreateAxisAttr(UsdGeom.Tokens.y)
        else:
            if c.kind == "plane":
                n = np.asarray(c.param, dtype=np.float64)
                t1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 0.0, 1.0])
                t1 /= np.linalg.norm(t1)
                t2 = np.cross(n, t1)
                h = 0.5 * plane_size
                pts = np.array([-h * t1 - h * t2, h * t1 - h * t2, h * t1 + h * t2, -h * t1 + h * t2])
                tris = np.array([[0, 1, 2, 3]])
            else:
                pts, tris = np.asarray(c.mesh_points), np.asarray(c.mesh_triangles)
            geom = UsdGeom.Mesh.Define(stage, g)
            geom.CreatePointsAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, p)) for p in pts]))
            geom.CreateFaceVertexCountsAttr(Vt.IntArray([int(tris.shape[1])] * len(tris)))
            geom.CreateFaceVertexIndicesAttr(Vt.IntArray([int(i) for i in tris.ravel()]))
            geom.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
            geom.CreateDoubleSidedAttr(c.kind == "plane")
            geom.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, pts.min(axis=0))), Gf.Vec3f(*map(float, pts.max(axis=0)))]))
        if not geom.GetExtentAttr().HasAuthoredValue():
            # USD asks an extent of whoever authors a radius, height or size: without one, a
            # sphere, capsule or cylinder read the schema's fallback extent (radius 1), not its own.
            geom.CreateExtentAttr(UsdGeom.Boundable.ComputeExtentFromPlugins(geom, Usd.TimeCode.Default()))
        geom.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(steel)


def usd_write_frame(stage, model, state, time_code, key: str = "warp_esph"):
    """Each tool's pose at ``state.time`` (time-sampled translate and orient) and the reaction
    force and torque of the step that produced ``state`` (time-sampled attributes; with
    worlds, world 0's: the others are in ``state.reaction_force``)."""
    from pxr import Gf  # noqa: PLC0415

    tools = getattr(model, "tools", None)
    if tools is None:
        return
    f = state.reaction_force.numpy().astype(np.float64)
    tq = state.reaction_torque.numpy().astype(np.float64)
    for k, prim_name in enumerate(usd_names(tools.names)):
        prim = stage.GetPrimAtPath(f"{USD_ROOT}/{prim_name}")
        p, q = tools.pose_at(k, state.time)  # a pinned set's frame: (centroid, identity) at rest
        prim.GetAttribute("xformOp:translate").Set(Gf.Vec3d(*map(float, p)), time_code)
        prim.GetAttribute("xformOp:orient").Set(Gf.Quatd(float(q[3]), float(q[0]), float(q[1]), float(q[2])), time_code)
        prim.GetAttribute(f"{key}:reaction_force").Set(Gf.Vec3d(*f[k]), time_code)
        prim.GetAttribute(f"{key}:reaction_torque").Set(Gf.Vec3d(*tq[k]), time_code)


def usd_names(names) -> list[str]:
    """The prim name under ``USD_ROOT`` of each tool, unique: a valid identifier is kept; any
    other is cleaned and carries the tool's index (so 'a+' and 'a-' stay two prims), and a
    suffix ``_<j>`` where that still meets another tool's prim ('x y' at index 0 and
    'tool_0_x_y' both made ``tool_0_x_y``, and the second prim's xformOps were authored twice,
    which made the run's own output unreadable). Readers find a tool by its
    ``tool_name`` custom data, not by its prim name."""
    import re  # noqa: PLC0415

    out: list[str | None] = []
    for name in names:  # valid names first: they are their own prims whatever comes before
        out.append(name if re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name) else None)
    taken = {n for n in out if n is not None}
    for k, name in enumerate(names):
        if out[k] is None:
            base = f"tool_{k}_{re.sub(r'[^A-Za-z0-9_]', '_', name)}"
            prim, j = base, 1
            while prim in taken:
                prim, j = f"{base}_{j}", j + 1
            taken.add(prim)
            out[k] = prim
    return out


# ---------------------------------------------------------------------- reaction log
class ReactionLog:
    """Per-frame record of every tool's pose and its mean reaction force and torque over the
    frame (impulse / frame time, summed on the device each step), for ``warp-esph run``'s
    ``<output>_tools.csv`` / ``.json``; then the same for every static collider (``plane<k>``,
    ``sphere<k>``, ``box<k>``, ``Solver.collider_reactions``), whose pose is its reference
    point (the torque's origin) with the identity orientation. Attach with
    ``ReactionLog(solver)``, call ``record(frame, state)`` after each frame."""

    def __init__(self, solver):
        from .sim import integrate  # noqa: PLC0415

        m = solver.model
        self.tools = m.tools
        self.solver = solver
        vec3, dev = m.types.vec3, m.device
        if self.tools is not None:
            rows = len(self.tools.row_names)
            solver.tool_impulse = (wp.zeros(rows, dtype=vec3, device=dev), wp.zeros(rows, dtype=vec3, device=dev))
        self.static_names = integrate.static_collider_names(m)
        if self.static_names:
            rows = len(self.static_names)
            solver.collider_impulse = (wp.zeros(rows, dtype=vec3, device=dev), wp.zeros(rows, dtype=vec3, device=dev))
        self.rows: list[dict] = []
        self._t_last = None
        self._kept = None
        #: The run the log belongs to (``warp-esph run``'s ``run_id``), written in the JSON and
        #: compared by ``resume``; None: not named.
        self.run_id: str | None = None

    def resume(self, stem: str, frame: int):
        """Continue the log ``write(stem)`` wrote before, from ``frame`` (a resumed run): its
        rows up to ``frame`` are kept (the resumed run's first record, at ``frame``, has no
        preceding frame and only sets the start). A log that names another run than
        ``run_id`` (a later run's, over the same output) is refused: its rows are not this run's."""
        import json  # noqa: PLC0415

        path = f"{stem}_tools.json"
        try:
            with open(path) as fh:
                doc = json.load(fh)
            rows = doc["rows"]
            if not isinstance(rows, list):
                raise TypeError("its 'rows' is not a list")
        except FileNotFoundError:
            if frame > 0:
                warnings.warn(f"the force log {checks.shown_path(path, False)} of the run to resume is not there: the resumed log holds the "
                              f"frames from {frame} on only", UserWarning, stacklevel=2)
            return  # no earlier log: the resumed frames only
        except (OSError, ValueError, KeyError, TypeError, RecursionError) as e:
            # Rewriting it with the resumed frames only would lose the finished run's rows.
            why = checks.read_reason(e)
            raise ValueError(f"the force log {checks.shown_path(path, False)} of the run to resume cannot be read ({why}): resuming would replace "
                             "its rows of the finished frames; move it away to resume without them") from None
        theirs = doc.get("run_id") if isinstance(doc, dict) else None
        if theirs != self.run_id and (theirs is not None):
            # Another run wrote it since (or the checkpoint's run named none): its rows up to the
            # checkpoint were taken as this run's, exit 0.
            ours = f"the run {self.run_id!r}" if self.run_id is not None else "the run (which names none)"
            raise ValueError(f"the force log {checks.shown_path(path, False)} belongs to another run (run id {theirs!r}), not {ours} to resume: "
                             "put back that run's own log, or move it away to resume without its rows")
        self.rows = [r for r in rows if isinstance(r, dict) and isinstance(r.get("frame"), int) and r["frame"] <= frame]
        self._kept = frame if any(r["frame"] == frame for r in self.rows) else None

    def _take(self, impulse):
        if impulse is None:
            return None
        out = tuple(a.numpy().astype(np.float64) for a in impulse)
        for a in impulse:
            a.zero_()
        return out

    def record(self, frame: int, state):
        tool = self._take(getattr(self.solver, "tool_impulse", None) if self.tools is not None else None)
        static = self._take(self.solver.collider_impulse if self.static_names else None)
        span = None if self._t_last is None else state.time - self._t_last
        self._t_last = state.time
        if frame == self._kept:
            self._kept = None
            return  # the earlier run's row of this frame stands
        identity = [float(v) for v in IDENTITY]

        def row(name, p, q, imp, ang, k):
            f = imp[k] / span if span else np.zeros(3)
            t = ang[k] / span if span else np.zeros(3)
            self.rows.append({
                "frame": int(frame), "time": float(state.time), "tool": name,
                "position": [float(v) for v in p], "orientation": [float(v) for v in q],
                "force": [float(v) for v in f], "torque": [float(v) for v in t],
            })

        if tool is not None:
            for k, name in enumerate(self.tools.row_names):
                p, q = self.tools.pose_at(k % self.tools.count, state.time)
                row(name, p, q, *tool, k)
        if static is not None:
            # Read at each frame, as the kernels read the arrays: a plane moved in place between
            # frames has its torque about its new point.
            from .sim.integrate import static_collider_references  # noqa: PLC0415

            refs = static_collider_references(self.solver.model)
            for k, (name, ref) in enumerate(zip(self.static_names, refs)):
                row(name, ref, identity, *static, k)

    def write(self, stem: str) -> tuple[str, str]:
        """``stem + '_tools.csv'`` and ``stem + '_tools.json'``; returns both paths (the CLI passes
        the whole output name, ``a.usdc`` -> ``a.usdc_tools.csv``)."""
        import csv  # noqa: PLC0415
        import json  # noqa: PLC0415

        csv_path, json_path = f"{stem}_tools.csv", f"{stem}_tools.json"
        # Every digit the run's precision holds: 9 significant digits round-trip float32, a
        # float64 run's values need 17 (at 9 its CSV, which `fit --target` reads, rounded them).
        digits = ".17g" if self.solver.model.scalar == wp.float64 else ".9g"

        def write_csv(fh):
            w = csv.writer(fh)
            w.writerow(["frame", "time", "tool", "px", "py", "pz", "qx", "qy", "qz", "qw", "fx", "fy", "fz", "tx", "ty", "tz"])
            for r in self.rows:
                w.writerow([r["frame"], format(r["time"], digits), r["tool"],
                            *(format(v, digits) for v in r["position"] + r["orientation"] + r["force"] + r["torque"])])

        def write_json(fh):
            json.dump({
                "units": {"time": "s", "position": "m", "force": "N", "torque": "N m"},
                "definition": "mean force and torque each tool or static collider exerted on the material over the "
                              "frame ending at 'time' (torque about the tool's position; a static collider's position is "
                              "its reference point); the material exerts minus these on it",
                **({"run_id": self.run_id} if self.run_id is not None else {}),
                "rows": self.rows,
            }, fh, indent=1)

        # Written beside and renamed over: the log is rewritten at every checkpoint and at the
        # end, and a signal or a full disk in the middle of a write left it cut short (a resume
        # then refused it; the CSV was read as fewer rows).
        # Both are written before either is renamed, so a failed write leaves the two agreeing.
        tmps = [os.path.join(folder, f".{name}.{os.getpid()}.tmp") for folder, name in map(os.path.split, (csv_path, json_path))]
        try:
            for tmp, fill, newline in zip(tmps, (write_csv, write_json), ("", None)):
                with open(tmp, "w", newline=newline) as fh:
                    fill(fh)
            for tmp, path in zip(tmps, (csv_path, json_path)):
                os.replace(tmp, path)
        finally:
            for tmp in tmps:
                if os.path.lexists(tmp):
                    os.remove(tmp)
        return csv_path, json_path
