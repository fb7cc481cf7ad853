"""Static colliders: planes (the ground), spheres and axis-aligned boxes.

A particle found inside a collider after the position update is moved to its surface;
the inward normal velocity is removed and the tangential velocity loses ``friction`` times
it (Coulomb friction; it stops when that exceeds it). With ``Model.contact_ramp > 0``
(the default, ``CONTINUOUS_CONTACT_RAMP``) a touchdown step moves the particle out by, and
removes, only the share ``touchdown_share`` of the depth and of the normal velocity, smooth
in how far past the surface the step's drift went, and the stick-slip transition is rounded,
which keeps the step C1 in the state where a particle lands, and a particle so left inside
that leaves the next step is let out smoothly (``exit_correction``), so a loss is smooth in
the parameters through contact (docs/method.md §1, "Contact"); ``contact_ramp = 0``
(``INSTANT_CONTACT_RAMP``) is the first law.
The position is corrected by ``dt`` times the velocity friction removed: the drift moved the
particle with the velocity before friction, so without it a particle that friction holds
still slides ``a_t dt^2`` per step, a creep at speed ``a_t dt`` that kept slumped plastic
piles sinking (docs/physics.md, "The slump creep").
"""

import dataclasses
import functools
import types

import numpy as np
import warp as wp

from .._types import type_set
from . import smoothing

#: Collider loops are unrolled at compile time (a dynamic loop that carries positions
#: through non-linear projections would get a wrong adjoint, docs/method.md, Warp pitfall 1).
MAX_PER_KIND = 16
#: ``Model.contact_ramp`` of the continuous contact: a touchdown step removes only the share
#: ``touchdown_share`` of the inward normal velocity of a particle found inside, and the
#: stick-slip transition is rounded, so the step is C1 in the state where a particle lands
#: (docs/method.md §1, "Contact").
CONTINUOUS_CONTACT_RAMP = 1.0
#: ``Model.contact_ramp`` of the instant contact, the first law: the whole inward normal
#: velocity is removed, discontinuous where a particle crosses the surface.
INSTANT_CONTACT_RAMP = 0.0
#: Default ``Model.contact_ramp``: the continuous contact. A loss through the instant one
#: jumps wherever a particle's first contact moves from one step to the next.
CONTACT_RAMP = CONTINUOUS_CONTACT_RAMP
#: Units in the last place, of the largest coordinate a contact's depth is computed from,
#: taken as that depth's round-off (``depth_round_off``): a particle resting on a float32 tool
#: starts each step a few of them on either side of the surface, and read as landing when
#: outside, kept up to a fifth of its inward speed (docs/physics.md, "The touchdown share's
#: round-off").
DEPTH_ROUND_OFF_ULPS = 2.0
#: The largest share of a step's normal drift that ``touchdown_share`` counts as round-off.
#: At a half its rounding starts at ``q = 0``, as it must to leave the share 0 with slope 0
#: there; a drift shorter than twice the round-off (a float32 particle at rest on a sphere tool
#: 0.5 m across in steps of 0.1 ms) is all round-off, and one started within half of it of the
#: surface is taken as resting.
MAX_ROUND_OFF_SHARE = 0.5
#: The Tresca ground's band (``tresca_traction``), in spacings from its plane of a particle's
#: centre at the step's start: full hold below the first, none beyond the second, faded with
#: zero slope at both ends between (a hard band at one spacing made the hold jump where a
#: particle crossed it). Centred on one spacing, it holds as many particles as that hard band
#: where their heights are spread evenly, as under a flowed pile (0.25-1.2 spacings): the band
#: (0.5, 1.0) held fewer, and the S = 0.2 slump at 8 across rested at -9.1 % of the 1-D height
#: against -7.5 % (docs/physics.md, "The Tresca ground (built)"). A lattice's second layer, at 1.5, is outside.
TRESCA_BAND = (0.75, 1.25)


@dataclasses.dataclass(frozen=True)
class Plane:
    normal: tuple[float, float, float]
    offset: float  # the plane is dot(normal, x) = offset; the solid side is below it
    friction: float
    #: Whether the plane's mirror images of the particles near it enter their fits and the
    #: elastic energy as a rough floor (``SceneBuilder.add_ground(images=True)``,
    #: docs/physics.md, "The ground collider's thin-layer strength").
    images: bool = False
    #: ``K`` of the Tresca ground (``SceneBuilder.add_ground(shear_cap=K)``): the frictionless
    #: imaged ground holds each particle near it tangentially up to ``K tau_y A`` (``tresca_traction``);
    #: 0: no hold.
    shear_cap: float = 0.0

    def __repr__(self) -> str:
        # A checkpoint's fingerprint hashes the repr: a plane without the cap keeps the one it had.
        cap = f", shear_cap={self.shear_cap!r}" if self.shear_cap else ""
        return (f"Plane(normal={self.normal!r}, offset={self.offset!r}, friction={self.friction!r}, "
                f"images={self.images!r}{cap})")


@dataclasses.dataclass(frozen=True)
class Sphere:
    center: tuple[float, float, float]
    radius: float
    friction: float


@dataclasses.dataclass(frozen=True)
class Box:
    center: tuple[float, float, float]
    half_extents: tuple[float, float, float]
    friction: float


@functools.cache
def funcs(scalar) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3 = T.vec3
    ULP = scalar(DEPTH_ROUND_OFF_ULPS * float(np.finfo(T.np_dtype).eps))
    MAX_E = scalar(MAX_ROUND_OFF_SHARE)
    BAND_FULL, BAND_END = (scalar(b) for b in TRESCA_BAND)
    smoothstep = smoothing.funcs(scalar).smoothstep

    @wp.func
    def depth_round_off(scale: scalar) -> scalar:
        """Round-off of a contact's depth computed from coordinates up to ``scale`` (the sum
        of the largest magnitudes of the points and the collider's size that enter it):
        ``DEPTH_ROUND_OFF_ULPS`` units in their last place, 2.4e-7 m at 1 m in float32, 4.4e-16 m
        in float64."""
        return ULP * scale

    @wp.func
    def max_abs(a: vec3) -> scalar:
        """The largest magnitude of ``a``'s components: the scale of its round-off."""
        return wp.max(wp.max(wp.abs(a[0]), wp.abs(a[1])), wp.abs(a[2]))

    @wp.func
    def slip_speed(a: scalar, band: scalar) -> scalar:
        """Tangential speed left after Coulomb friction, ``max(a, 0)`` for the excess ``a``
        of the tangential speed over the friction impulse, rounded over ``0 < a < band`` to
        ``a^2 (2 band - a) / band^2`` (value and slope continuous at both ends, never above
        ``a``: up to 0.15 band more friction there). Stick (``a <= 0``) and sliding faster
        than ``band`` are exactly Coulomb; the rounding removes the kink of the loss at the
        stick-slip transition (docs/method.md §1, "Contact")."""
        r = a
        if a < band:
            r = a * a * (scalar(2.0) * band - a) / (band * band)
        return r

    @wp.func
    def touchdown_share(vn: scalar, depth: scalar, dt: scalar, ramp: scalar, tol: scalar) -> scalar:
        """Share of the inward normal velocity ``-vn`` removed, and of the depth undone, for
        a particle found ``depth`` inside after the drift: 1 for the instant law
        (``ramp = 0``), for one moving outward and for one whose whole drift of the step
        went past the surface (``q >= 1``, ``q = depth / (ramp (-vn) dt)``: it started the
        step on or inside the surface: resting, sticking, pressed), else ``smoothstep(q)``.
        ``q`` is the share of the step after the touchdown; the smoothstep's zero slope at
        both ends makes the response C1 where a touchdown moves across a step's end and
        where a landing particle becomes a resting one.

        ``tol`` is the round-off of ``depth`` (``depth_round_off``). A particle that started
        the step within it outside the surface is taken as resting: with ``e = tol / reach``
        (at most ``MAX_ROUND_OFF_SHARE``), ``q`` is read as ``q + (q - a)^2 / e`` above
        ``a = 1 - 2 e``, which reaches 1 at ``q = 1 - e`` with a finite slope, so the share stays
        C1 (the smoothstep's slope is 0 there) and is unchanged below ``a``. Without it a
        float32 particle resting on a tool, a few units in the last place outside, kept up to
        a fifth of its step's inward speed in single steps (docs/physics.md, "The touchdown
        share's round-off")."""
        if ramp <= scalar(0.0) or vn >= scalar(0.0):
            return scalar(1.0)
        reach = ramp * (-vn) * dt
        band = wp.min(tol, MAX_E * reach)
        if depth >= reach - band:
            return scalar(1.0)
        q = depth / reach
        if band > scalar(0.0):
            a = scalar(1.0) - scalar(2.0) * band / reach
            if q > a:
                q = q + (q - a) * (q - a) * reach / band
        s, ds = smoothstep(q)
        return s

    @wp.func
    def exit_correction(vn: scalar, depth: scalar, dt: scalar, ramp: scalar) -> scalar:
        """Distance along the outward normal by which a particle moving outward (``vn > 0``)
        is moved after the drift, ``depth`` inside (negative: outside) the surface: the whole
        depth while it is still inside, nothing if it started the step on or outside the
        surface (``u >= 1``, ``u = -depth / (ramp vn dt)``, its drift's share past the
        surface), and between, for one that started inside (a touchdown share left it there)
        and leaves within the step, ``ramp vn dt (u^2 (2 - u) - u)``: it holds the leaving
        particle back by at most 4/27 of its drift, so that its position is C1 where the
        drift just reaches the surface (plain projection: ``max(vn dt - d0, 0)``, a kink)."""
        if ramp <= scalar(0.0):
            return wp.max(depth, scalar(0.0))
        reach = ramp * vn * dt
        if depth >= scalar(0.0):
            return depth
        if -depth >= reach:
            return scalar(0.0)
        u = -depth / reach
        return reach * (u * u * (scalar(2.0) - u) - u)

    @wp.func
    def inside_band(vn: scalar, depth: scalar, dt: scalar, ramp: scalar) -> scalar:
        """``d0 / dt`` for a particle that started the step ``d0 = depth + vn dt > 0`` inside a
        static collider (a touchdown share left it there), else 0: the band of normal speed
        over which its contact is rounded where the step's force just cancels its inward
        speed. The plain law kinks there: moving in, it loses all of ``-vn`` and gets friction
        in proportion; moving out, it keeps all of ``vn`` and gets none (``max(vn, 0)``).
        Rounded, it keeps ``slip_speed(vn, band)`` of an outward speed while the drift leaves
        it inside, and its friction takes ``slip_speed(-vn, band)`` of an inward one: C1 in
        ``vn`` at 0, in the depth where the outward drift just reaches the surface (band
        ``vn``) and where ``d0`` crosses 0 (band 0: the plain law, which a particle resting on
        the surface keeps); it never adds speed (docs/physics.md, "The exit speed of a
        particle left inside")."""
        band = scalar(0.0)
        d0 = depth + vn * dt
        if ramp > scalar(0.0) and d0 > scalar(0.0):
            band = d0 / dt
        return band

    @wp.func
    def in_reach(vn: scalar, depth: scalar, dt: scalar, ramp: scalar) -> bool:
        """Whether a static collider moves a particle ``depth`` inside its surface after the
        drift: inside, or outside but leaving from inside within the step (``exit_correction``)."""
        return depth > scalar(0.0) or (ramp > scalar(0.0) and vn > scalar(0.0) and -depth < ramp * vn * dt)

    @wp.func
    def coulomb_velocity(v: vec3, vs: vec3, n: vec3, depth: scalar, share: scalar, ramp: scalar, mu_s: scalar,
                         mu_k: scalar, band: scalar):
        """``coulomb_response`` given the particle's ``touchdown_share``, for a caller that
        also moves the particle by it (``respond``: one evaluation of the share). ``band``:
        the ``inside_band`` of a particle that started the step inside a static collider
        (else 0), over which the friction's normal impulse is rounded off to zero."""
        vr = v - vs
        vn = wp.dot(vr, n)
        # A static coefficient below the kinetic one (a descent that moved a tool's
        # ``friction`` array alone; the builder refuses it) acts as the kinetic one: the slip
        # branch below it would run on a negative excess, where friction raised the
        # tangential speed (0.01 to 1.43 m/s at 0 and 0.5) or reversed it (instant law).
        mu_stick = wp.max(mu_s, mu_k)
        if vn < scalar(0.0) and depth > scalar(0.0):
            vt = vr - vn * n
            vt_len = wp.length(vt)
            if ramp > scalar(0.0):
                dvn = -vn * share
                vn_left = (vn + dvn) * n
                dvn_f = dvn
                if band > scalar(0.0):
                    dvn_f = slip_speed(dvn, band)
                if vt_len <= mu_stick * dvn_f:
                    return vs + vn_left
                slip = slip_speed(vt_len - mu_k * dvn_f, mu_k * dvn_f)
                return vs + vn_left + vt * (slip / vt_len)
            # The instant law, as it was computed (a float32 run of the rubber ball settles
            # differently under a rounding-level change of this expression).
            dvn = -vn
            if vt_len <= mu_stick * dvn:
                return vs
            return vs + vt * (scalar(1.0) - mu_k * dvn / vt_len)
        return v

    @wp.func
    def coulomb_response(v: vec3, vs: vec3, n: vec3, depth: scalar, dt: scalar, ramp: scalar, mu_s: scalar, mu_k: scalar,
                         tol: scalar):
        """Velocity after contact with a surface moving at ``vs`` (outward normal ``n``) of a
        particle found ``depth`` inside it after the drift: the share ``touchdown_share`` of
        the inward relative normal velocity ``-vn`` is removed; Coulomb friction on the
        relative tangential velocity, sticking while it is at most ``mu_s`` times the normal
        velocity removed (``mu_s`` taken as at least ``mu_k``), else reduced by ``mu_k`` times it. The one contact law of the
        static colliders and the moving tools (``warp_esph/tools.py``).

        A particle that barely crosses the surface in a step loses barely any normal
        velocity and gets barely any friction, and the rest one step later, instead of all
        of it at once or none (docs/method.md §1, "Contact"). One that starts the step on
        the surface (resting, sticking, or pressed by a moving tool) has ``depth = -vn dt``
        and loses all of it, as before. ``ramp = 0`` is the instant law (all of it,
        friction not rounded). ``tol``: the round-off of ``depth`` (``depth_round_off``)."""
        vn = wp.dot(v - vs, n)
        share = scalar(1.0)
        if vn < scalar(0.0) and depth > scalar(0.0):  # where it is used: elsewhere q may overflow
            share = touchdown_share(vn, depth, dt, ramp, tol)
        return coulomb_velocity(v, vs, n, depth, share, ramp, mu_s, mu_k, scalar(0.0))

    @wp.func
    def respond(x: vec3, v: vec3, depth: scalar, n: vec3, friction: scalar, dt: scalar, ramp: scalar, scale: scalar):
        """Move a particle ``depth`` inside along outward normal ``n`` of a static collider
        out by ``touchdown_share`` of it (all of it but in a touchdown step); one moving
        outward by ``exit_correction``; friction over the step ``dt``. ``scale``: the
        magnitude of the coordinates the depth was computed from (``depth_round_off``)."""
        vn = wp.dot(v, n)
        share = touchdown_share(vn, depth, dt, ramp, depth_round_off(scale))
        band = inside_band(vn, depth, dt, ramp)
        v_new = coulomb_velocity(v, vec3(), n, depth, share, ramp, friction, friction, band)
        if band > scalar(0.0) and vn > scalar(0.0) and depth > scalar(0.0):
            # Leaving from inside and still inside after the drift: the rounded exit speed.
            v_new = v_new + (slip_speed(vn, band) - vn) * n
        # The drift moved x by dt times the tangential velocity; friction takes back what it
        # removed from it, so a particle that sticks stays where it was.
        dv = v_new - v
        moved = share * depth
        if vn > scalar(0.0):
            moved = exit_correction(vn, depth, dt, ramp)
        return x + moved * n + dt * (dv - wp.dot(dv, n) * n), v_new

    @wp.func
    def tresca_band(d: scalar, spacing: scalar) -> scalar:
        """Share of the Tresca ground's hold on a particle whose centre started the step ``d``
        above its plane: 1 up to ``TRESCA_BAND[0]`` spacings, 0 from ``TRESCA_BAND[1]``, a
        smoothstep between (C1 where a particle enters or leaves the band)."""
        lo = BAND_FULL * spacing
        hi = BAND_END * spacing
        w = scalar(1.0)
        if d >= hi:
            w = scalar(0.0)
        elif d > lo:
            s, ds = smoothstep((d - lo) / (hi - lo))
            w = scalar(1.0) - s
        return w

    @wp.func
    def tresca_traction(x: vec3, v: vec3, x0: vec3, n: vec3, offset: scalar, hold: scalar, mass: scalar, dt: scalar,
                        spacing: scalar):
        """The Tresca ground's traction on a particle (``SceneBuilder.add_ground(shear_cap=K)``):
        its tangential velocity relative to the plane loses up to ``w hold dt / mass``, ``hold =
        K tau_y A`` the force of the material's shear yield stress ``tau_y`` over the area ``A``
        the particle stands for, ``w = tresca_band`` of where its centre ``x0`` started the step:
        a wall that holds the base up to the stress at which the material itself yields (the
        continuum's Tresca floor, docs/physics.md, "The Tresca continuum"). Sticking while the
        speed is at most that, else sliding at the excess, rounded as Coulomb's (``slip_speed``,
        C1 at the transition). The position loses ``dt`` times the velocity removed: the drift
        moved it with the velocity before (as ``respond``)."""
        w = tresca_band(wp.dot(n, x0) - offset, spacing)
        if w <= scalar(0.0) or hold <= scalar(0.0):
            return x, v
        vt = v - wp.dot(v, n) * n
        speed = wp.length(vt)
        if speed <= scalar(0.0):
            return x, v
        limit = w * hold * dt / mass
        dv = -vt
        if speed > limit:
            dv = vt * (slip_speed(speed - limit, limit) / speed - scalar(1.0))
        return x + dt * dv, v + dv

    @wp.func
    def collide_plane(x: vec3, v: vec3, n: vec3, offset: scalar, friction: scalar, dt: scalar, ramp: scalar):
        depth = offset - wp.dot(n, x)
        if in_reach(wp.dot(v, n), depth, dt, ramp):
            return respond(x, v, depth, n, friction, dt, ramp, wp.abs(offset) + max_abs(x))
        return x, v

    @wp.func
    def collide_sphere(x: vec3, v: vec3, c: vec3, radius: scalar, friction: scalar, dt: scalar, ramp: scalar):
        d = x - c
        r2 = wp.dot(d, d)
        if r2 > scalar(0.0):
            r = wp.sqrt(r2)
            n = d / r
            if in_reach(wp.dot(v, n), radius - r, dt, ramp):
                return respond(x, v, radius - r, n, friction, dt, ramp, max_abs(x) + max_abs(c) + radius)
        return x, v

    @wp.func
    def collide_box(x: vec3, v: vec3, c: vec3, half: vec3, friction: scalar, dt: scalar, ramp: scalar):
        d = x - c
        gap = vec3(wp.abs(d[0]) - half[0], wp.abs(d[1]) - half[1], wp.abs(d[2]) - half[2])
        # The nearest face from inside; from outside the face it is past, if only one.
        axis = int(0)
        if gap[1] > gap[axis]:
            axis = 1
        if gap[2] > gap[axis]:
            axis = 2
        past = int(0)
        for k in range(3):
            if gap[k] >= scalar(0.0):
                past += 1
        if past <= 1:
            n = vec3()
            n[axis] = wp.where(d[axis] < scalar(0.0), scalar(-1.0), scalar(1.0))
            # Inside: leave through the nearest face. Just outside one face (past neither of
            # its edges): a particle leaving through it (exit_correction); at edges and
            # corners the exit is not rounded.
            if in_reach(wp.dot(v, n), -gap[axis], dt, ramp):
                return respond(x, v, -gap[axis], n, friction, dt, ramp, max_abs(x) + max_abs(c) + max_abs(half))
        return x, v

    return types.SimpleNamespace(
        coulomb_response=coulomb_response, coulomb_velocity=coulomb_velocity, slip_speed=slip_speed, touchdown_share=touchdown_share,
        depth_round_off=depth_round_off, max_abs=max_abs, exit_correction=exit_correction, inside_band=inside_band, respond=respond, tresca_band=tresca_band, tresca_traction=tresca_traction, collide_plane=collide_plane, collide_sphere=collide_sphere, collide_box=collide_box
    )
