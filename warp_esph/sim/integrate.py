"""Symplectic Euler with gravity and collider response (docs/method.md §1.5):

    u <- u + dt (f / m + g),   x <- x + dt u,   then colliders.

Reaction of the static colliders (``state_out.collider_force`` / ``collider_torque``, one row
per world and collider, planes then spheres then boxes, row ``w * n_static + c``): the force
each exerted on the material in the step, ``sum_i m_i (v_i^after - v_i^before) / dt`` over
the particles it responded to (``v^before``: the velocity entering that collider's
response), and its torque about the collider's reference point (a plane's point
``offset * normal`` nearest the origin, a sphere's or box's centre), ``(x_i^after - ref) x
f_i``. The same definition as the moving tools' rows (``warp_esph/tools.py``).

The ground with floor images (``SceneBuilder.add_ground(images=True)``) also acts on the
material through its images, in the elastic, pressure and viscous forces, and a body at rest
on it may not touch the plane at all. Its row adds that force: the sum of the step's internal
forces ``state_out.force`` over the world's particles, which without the images is zero to
round-off (every internal force comes in equal and opposite parts), less the force fields'
share, and its torque ``(x_i - ref) x f_i`` at the step's start positions, where those forces
act (``launch_floor_image_reaction``).
"""

import functools
import types

import warp as wp

from .._types import type_set
from . import colliders, fields, plasticity
from .replay import pointer_key, recording_tape, weak_tape
from .roundoff import compensated_sum


@functools.cache
def struct(scalar):
    """The static colliders' arrays (planes, spheres, boxes: ``colliders.py``), the contact
    ramp (``Model.contact_ramp``) and the Tresca ground's hold (``Model.shear_cap``) as one
    ``wp.struct``, what ``static_colliders``
    reads; ``static_collider_struct(model)`` fills it."""
    T = type_set(scalar)

    @wp.struct
    class StaticColliders:
        plane_normal: wp.array(dtype=T.vec3)
        plane_offset: wp.array(dtype=scalar)
        plane_friction: wp.array(dtype=scalar)
        sphere_center: wp.array(dtype=T.vec3)
        sphere_radius: wp.array(dtype=scalar)
        sphere_friction: wp.array(dtype=scalar)
        box_center: wp.array(dtype=T.vec3)
        box_half: wp.array(dtype=T.vec3)
        box_friction: wp.array(dtype=scalar)
        # The Tresca ground's hold (``colliders.tresca_traction``): the shear yield stress of each
        # particle's material, hardened by its ``alpha``, over its area, on the plane ``cap_plane``
        # (-1: none).
        yield_stress: wp.array(dtype=scalar)
        hardening: wp.array(dtype=scalar)
        particle_material: wp.array(dtype=wp.int32)
        particle_volume: wp.array(dtype=scalar)
        ramp: scalar
        cap_plane: int
        shear_cap: scalar
        spacing: scalar

    return StaticColliders


@functools.cache
def funcs(scalar, n_planes: int, n_spheres: int, n_boxes: int) -> types.SimpleNamespace:
    """The step's kinematics, specialised to the model's static collider counts so the
    collider loops unroll. ``warp_esph/tools.py`` calls the same funcs before its moving
    tools and pinned sets."""
    T = type_set(scalar)
    vec3 = T.vec3
    col = colliders.funcs(scalar)
    yield_surface = plasticity.funcs(scalar).yield_surface
    StaticColliders = struct(scalar)
    # Divided in Python (float64) and cast once: Warp evaluates ``2.0 / 3.0`` inside a kernel in
    # float32, whatever the scalar it is cast to (a float64 hold 2.3e-7 off at V = (2 cm)^3).
    two_thirds = scalar(2.0 / 3.0)

    @wp.func
    def symplectic_euler(x: vec3, x_lo: vec3, v: vec3, f: vec3, mass: scalar, gravity: vec3, dt: scalar):
        """``u <- u + dt (f / m + g)``, then ``x <- x + dt u`` (docs/method.md §1.5), of the
        position ``x + x_lo`` with its round-off carried (``roundoff.py``, ``State.x_lo``);
        returns the new ``x, x_lo, u``."""
        v_new = v + dt * (f / mass + gravity)
        x_new, x_new_lo = compensated_sum(x, x_lo + dt * v_new)
        return x_new, x_new_lo, v_new

    @wp.func
    def placed_round_off(x: vec3, x_moved: vec3, x_lo: vec3) -> vec3:
        """``x_lo`` of a particle whose integrated position ``x_moved`` a collider, tool or
        pin may have replaced by ``x``: 0 where it did (``x`` is then the position)."""
        out = x_lo
        if wp.length_sq(x - x_moved) > scalar(0.0):
            out = vec3()
        return out

    @wp.func
    def react(x: vec3, v: vec3, v0: vec3, mass: scalar, dt: scalar, ref: vec3, row: int,
              cforce: wp.array(dtype=vec3), ctorque: wp.array(dtype=vec3)):
        """A static collider's force ``m (v - v0) / dt`` on one particle and its torque about
        ``ref``, added to the collider's row (only where it responded: particles out of
        contact would all contend for the row to add zero)."""
        dv = v - v0
        if wp.length_sq(dv) > scalar(0.0):
            f = mass * dv / dt
            wp.atomic_add(cforce, row, f)
            wp.atomic_add(ctorque, row, wp.cross(x - ref, f))

    @wp.func
    def tresca_hold(sc: StaticColliders, i: int, alpha: wp.array(dtype=scalar)) -> scalar:
        """``K tau_y A`` of particle ``i`` on the Tresca ground: ``tau_y = Y / sqrt(2)``
        (``Material.shear_yield_stress``) of the yield stress ``Y = yield_stress + hardening
        alpha`` the plastic flow reads for it this step (``plasticity.yield_surface``, of its
        ``alpha`` at the step's start: 0 where softening has taken it to 0 or below, so that
        ``tresca_traction`` holds nothing, never pushes), ``A = V^(2/3)`` of its volume."""
        m = sc.particle_material[i]
        tau_y = yield_surface(sc.yield_stress[m], sc.hardening[m], alpha[i]) * scalar(0.7071067811865476)
        return sc.shear_cap * tau_y * wp.pow(sc.particle_volume[i], two_thirds)

    @wp.func
    def static_colliders(x: vec3, v: vec3, dt: scalar, sc: StaticColliders, mass: scalar, row: int,
                         cforce: wp.array(dtype=vec3), ctorque: wp.array(dtype=vec3), x0: vec3, i: int,
                         alpha: wp.array(dtype=scalar)):
        """Every static plane, sphere and box in turn (``colliders.py``), each adding its
        reaction on this particle to its row ``row + c`` (module doc); the Tresca ground's
        traction (``x0``: particle ``i``'s position at the step's start, ``alpha`` the
        hardening variables there) is its plane's."""
        for c in range(wp.static(n_planes)):
            v0 = v
            x, v = col.collide_plane(x, v, sc.plane_normal[c], sc.plane_offset[c], sc.plane_friction[c], dt, sc.ramp)
            if c == sc.cap_plane:
                x, v = col.tresca_traction(x, v, x0, sc.plane_normal[c], sc.plane_offset[c], tresca_hold(sc, i, alpha),
                                           mass, dt, sc.spacing)
            react(x, v, v0, mass, dt, sc.plane_offset[c] * sc.plane_normal[c], row + c, cforce, ctorque)
        for c in range(wp.static(n_spheres)):
            v0 = v
            x, v = col.collide_sphere(x, v, sc.sphere_center[c], sc.sphere_radius[c], sc.sphere_friction[c], dt, sc.ramp)
            react(x, v, v0, mass, dt, sc.sphere_center[c], row + wp.static(n_planes) + c, cforce, ctorque)
        for c in range(wp.static(n_boxes)):
            v0 = v
            x, v = col.collide_box(x, v, sc.box_center[c], sc.box_half[c], sc.box_friction[c], dt, sc.ramp)
            react(x, v, v0, mass, dt, sc.box_center[c], row + wp.static(n_planes + n_spheres) + c, cforce, ctorque)
        return x, v

    return types.SimpleNamespace(symplectic_euler=symplectic_euler, placed_round_off=placed_round_off,
                                 static_colliders=static_colliders)


@functools.cache
def kernels(scalar, n_planes: int, n_spheres: int, n_boxes: int) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3 = T.vec3
    fn = funcs(scalar, n_planes, n_spheres, n_boxes)
    StaticColliders = struct(scalar)

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
        world: wp.array(dtype=wp.int32),
        alpha: wp.array(dtype=scalar),
        x_out: wp.array(dtype=vec3),
        x_lo_out: wp.array(dtype=vec3),
        v_out: wp.array(dtype=vec3),
        cforce: wp.array(dtype=vec3),
        ctorque: wp.array(dtype=vec3),
    ):
        i = wp.tid()
        m = mass[i]
        xe, x_lo, v = fn.symplectic_euler(x_in[i], x_lo_in[i], v_in[i], f[i], m, gravity, dt)
        x, v = fn.static_colliders(xe, v, dt, sc, m, world[i] * wp.static(n_planes + n_spheres + n_boxes), cforce, ctorque,
                                   x_in[i], i, alpha)
        x_out[i] = x
        x_lo_out[i] = fn.placed_round_off(x, xe, x_lo)
        v_out[i] = v

    @wp.kernel(module="unique")
    def accumulate(src: wp.array(dtype=vec3), scale: scalar, dst: wp.array(dtype=vec3)):
        k = wp.tid()
        dst[k] = dst[k] + scale * src[k]

    return types.SimpleNamespace(integrate=integrate, accumulate=accumulate)


def launch_integrate(model, state_in, state_out, dt):
    """Symplectic Euler of ``state_in`` under ``state_out.force`` and gravity, then the
    colliders, into ``state_out.x``, ``state_out.v``, and the static colliders' reaction
    into ``state_out.collider_force``, ``collider_torque``.

    Under a tape the launch is not recorded; the tape gets, in its place, a function that
    launches the kernel's generated adjoint (replayed, ``sim/replay.py``), whose replay of the
    forward adds into ``spare_reaction_rows`` instead of the state's rows: recorded as a
    launch, it added the step's reaction to them once more (3x the step's after a backward
    pass, ``tests/test_contracts.py``), and keeping them took a copy of the rows at every step
    of the backward (``replay.kept_through_backward``)."""
    S = model.scalar
    m = model
    state_out.collider_force.zero_()
    state_out.collider_torque.zero_()
    kernel = kernels(S, len(m.planes), len(m.spheres), len(m.boxes)).integrate
    colliders = static_collider_struct(m)
    inputs = [state_in.x, state_in.x_lo, state_in.v, state_out.force, m.particle_mass, m.types.vec3(*m.gravity), S(dt),
              colliders, m.particle_world, state_in.alpha]
    outputs = [state_out.x, state_out.x_lo, state_out.v, state_out.collider_force, state_out.collider_torque]
    tape = recording_tape()
    model.launches(kernel, m.particle_count, inputs, outputs, device=m.device, record_tape=tape is None)
    if tape is None:
        return
    # Weakly: the tape keeps this backward, and a backward holding the tape made a reference
    # cycle that left every dropped tape with its step records to the cyclic collector.
    tape_ref = weak_tape(tape)

    def backward():
        tape = tape_ref()
        adj = tape.get_adjoint
        spare = spare_reaction_rows(m, state_out.collider_force)
        for a in spare:
            a.zero_()
        replayed = [*outputs[:3], *spare]
        m.launches(kernel, m.particle_count, inputs, replayed,
                   adj_inputs=[static_collider_adjoint(m, tape, a) if a is colliders else adj(a) for a in inputs],
                   adj_outputs=[adj(a) for a in outputs], adjoint=True, device=m.device, record_tape=False)

    tape.record_func(backward, [])


def accumulate_impulse(model, state_out, dt, impulse):
    """Add ``dt`` times the step's static-collider force and torque rows to ``impulse``
    (a pair of arrays of the rows' shape; ``tools.ReactionLog``, untaped steps only)."""
    k = kernels(model.scalar, len(model.planes), len(model.spheres), len(model.boxes)).accumulate
    S = model.scalar
    for src, dst in zip((state_out.collider_force, state_out.collider_torque), impulse):
        model.launches(k, src.shape[0], [src, S(dt)], [dst], device=model.device)


#: ``struct``'s fields that are values, not the model's arrays of that name.
_STRUCT_VALUES = ("ramp", "cap_plane", "shear_cap", "spacing")


def static_collider_struct(model):
    """``struct``'s instance holding the model's static collider arrays (these very arrays)
    and its contact ramp. Filled once and reused while every array, its gradient, the
    ramp and the Tresca ground's ``K`` are the same (a struct copies the pointers when filled, as
    ``Model.material_arrays``): filling it cost a tenth of a small model's step."""
    names = [name for name in struct(model.scalar).vars if name not in _STRUCT_VALUES]
    arrays = [getattr(model, name) for name in names]
    key = (pointer_key(arrays), float(model.contact_ramp), float(model.shear_cap))
    cached = model._static_collider_struct
    if cached is None or cached[0] != key:
        out = struct(model.scalar)()
        for name, a in zip(names, arrays):
            setattr(out, name, a)
        out.ramp = model.scalar(model.contact_ramp)
        cap = model.shear_cap_plane
        out.cap_plane = -1 if cap is None else cap
        out.shear_cap = model.scalar(model.shear_cap)
        out.spacing = model.scalar(model.spacing)
        cached = model._static_collider_struct = (key, out, arrays)
    return cached[1]


def static_collider_adjoint(model, tape, colliders):
    """``tape.get_adjoint(colliders)`` of ``static_collider_struct``'s instance: the struct of
    its arrays' gradients, made once per instance (whose key holds those gradients), and
    registered on ``tape`` for its ``zero()`` as ``get_adjoint`` registers it: the struct and
    each array with a gradient, which ``zero()`` clears (the struct's entry clears none of
    them; left out, a later tape's ``zero()`` left them summing over its backward passes)."""
    cached = model._static_collider_adjoint
    if cached is None or cached[0] is not colliders:
        adjoint = tape.get_adjoint(colliders)
        graded = [(a, a.grad) for a in (getattr(colliders, name) for name in colliders._cls.vars)
                  if isinstance(a, wp.array) and a.grad is not None]
        cached = model._static_collider_adjoint = (colliders, adjoint, graded)
    else:
        tape.gradients[colliders] = cached[1]
        for a, g in cached[2]:
            tape.gradients[a] = g
    return cached[1]


def spare_reaction_rows(model, rows):
    """A force and a torque array of the shape of ``rows`` (a state's ``collider_force``), kept
    on the model: where the integration's generated adjoint replays the forward's atomic adds
    into the reaction rows. Nothing in the package reads them; zeroed when made and before
    each replay, so that they hold the last replayed step's reaction, not what the allocator
    left there (made empty, they read 7e30 and NaN where a freed array had been) or a sum over
    every step of every backward pass."""
    spare = model._spare_reaction_rows
    if spare is None or spare[0].shape != rows.shape:
        spare = model._spare_reaction_rows = (wp.zeros_like(rows, requires_grad=False),
                                              wp.zeros_like(rows, requires_grad=False))
    return spare


@functools.cache
def reaction_kernels(scalar) -> types.SimpleNamespace:
    """The image floor's reaction (module doc): the sum of the internal forces, and the force
    fields' share taken out of it."""
    T = type_set(scalar)
    vec3 = T.vec3
    compression_force = fields.funcs(scalar).compression_force

    @wp.kernel(module="unique")
    def floor_image_reaction(force: wp.array(dtype=vec3), x: wp.array(dtype=vec3), world: wp.array(dtype=wp.int32),
                             ref: vec3, row0: int, n_static: int, cforce: wp.array(dtype=vec3),
                             ctorque: wp.array(dtype=vec3)):
        i = wp.tid()
        f = force[i]
        row = world[i] * n_static + row0
        wp.atomic_add(cforce, row, f)
        wp.atomic_add(ctorque, row, wp.cross(x[i] - ref, f))

    @wp.kernel(module="unique")
    def compression_out_of_floor_reaction(x: wp.array(dtype=vec3), mass: wp.array(dtype=scalar),
                                          particle_body: wp.array(dtype=wp.int32), body: int, center: vec3,
                                          strength: scalar, world: wp.array(dtype=wp.int32), ref: vec3, row0: int,
                                          n_static: int, cforce: wp.array(dtype=vec3), ctorque: wp.array(dtype=vec3)):
        i = wp.tid()
        if body >= 0 and particle_body[i] != body:
            return
        f = compression_force(x[i], mass[i], center, strength)
        row = world[i] * n_static + row0
        wp.atomic_sub(cforce, row, f)
        wp.atomic_sub(ctorque, row, wp.cross(x[i] - ref, f))

    return types.SimpleNamespace(floor_image_reaction=floor_image_reaction,
                                 compression_out_of_floor_reaction=compression_out_of_floor_reaction)


def launch_floor_image_reaction(model, state_in, state_out):
    """Add the image floor's force on the material to its reaction row (module doc): run after
    the integration, when ``state_out.force`` holds every force of the step and the rows
    the colliders' contact."""
    m = model
    k = reaction_kernels(m.scalar)
    rows = m._image_reaction_rows
    if rows is None:
        # The imaged plane's row and reference point, made once from the plane built: the step
        # refuses it moved (Model.check_colliders), and reading its arrays here waited for the device.
        plane = next(c for c, p in enumerate(m.planes) if getattr(p, "images", False))
        ref = m.types.vec3(*plane_reference(m.planes[plane]))
        rows = m._image_reaction_rows = [m.particle_world, ref, plane, len(m.planes) + len(m.spheres) + len(m.boxes)]
    m.launches(k.floor_image_reaction, m.particle_count, [state_out.force, state_in.x, *rows],
               [state_out.collider_force, state_out.collider_torque], device=m.device)
    S = m.scalar
    for fld in m.force_fields:
        if fld.active(state_in.time):
            m.launches(k.compression_out_of_floor_reaction, m.particle_count,
                       [state_in.x, m.particle_mass, m.particle_body, int(fld.body), m.types.vec3(*fld.center),
                        S(fld.strength), *rows],
                       [state_out.collider_force, state_out.collider_torque], device=m.device)


def static_collider_references(model) -> list:
    """Reference point of each row of ``static_collider_names`` (the torque's origin: a
    plane's point ``offset * normal``, a sphere's or box's centre), as 3-tuples, of the
    colliders as their arrays hold them (``Model.static_colliders``), which the kernels'
    torques are about."""
    planes, spheres, boxes = model.static_colliders()
    refs = [plane_reference(p) for p in planes] + [tuple(s.center) for s in spheres] + [tuple(b.center) for b in boxes]
    return refs * model.world_count


def plane_reference(plane) -> tuple:
    """A plane's reference point, the torque's origin: its point ``offset * normal``."""
    return tuple(plane.offset * float(n) for n in plane.normal)


def static_collider_names(model) -> list[str]:
    """Row names of ``state.collider_force``: ``plane<k>``, ``sphere<k>``, ``box<k>`` in the
    order the builder added each kind, prefixed ``w<w>/`` with several worlds. Of a
    ``SceneBuilder`` too (one world), before the model is built."""
    names = ([f"plane{k}" for k in range(len(model.planes))] + [f"sphere{k}" for k in range(len(model.spheres))]
             + [f"box{k}" for k in range(len(model.boxes))])
    if getattr(model, "world_count", 1) == 1:
        return names
    return [f"w{w}/{n}" for w in range(model.world_count) for n in names]


def allocate_state(model, state, requires_grad: bool):
    """``state.collider_force`` / ``collider_torque``: one row per world and static collider
    (at least one row, so the kernels always get an array)."""
    rows = max(1, model.world_count * (len(model.planes) + len(model.spheres) + len(model.boxes)))
    T, dev = model.types, model.device
    state.collider_force = wp.zeros(rows, dtype=T.vec3, device=dev, requires_grad=requires_grad)
    state.collider_torque = wp.zeros(rows, dtype=T.vec3, device=dev, requires_grad=requires_grad)
