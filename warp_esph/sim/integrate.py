"""Symplectic Euler with gravity and collider response (docs/method.md §1.5):

    u <- u + dt (f / m + g),   x <- x + dt u,   then colliders.
"""

import functools
import types

import warp as wp

from .._types import type_set
from . import colliders


@functools.cache
def funcs(scalar, n_planes: int, n_spheres: int, n_boxes: int) -> types.SimpleNamespace:
    """The step's kinematics, specialised to the model's static collider counts so the
    collider loops unroll. ``warp_esph/tools.py`` calls the same funcs before its moving
    tools and pinned sets."""
    T = type_set(scalar)
    vec3 = T.vec3
    col = colliders.funcs(scalar)

    @wp.func
    def symplectic_euler(x: vec3, v: vec3, f: vec3, mass: scalar, gravity: vec3, dt: scalar):
        """``u <- u + dt (f / m + g)``, then ``x <- x + dt u`` (docs/method.md §1.5)."""
        v_new = v + dt * (f / mass + gravity)
        return x + dt * v_new, v_new

    @wp.func
    def static_colliders(
        x: vec3,
        v: vec3,
        dt: scalar,
        plane_normal: wp.array(dtype=vec3),
        plane_offset: wp.array(dtype=scalar),
        plane_friction: wp.array(dtype=scalar),
        sphere_center: wp.array(dtype=vec3),
        sphere_radius: wp.array(dtype=scalar),
        sphere_friction: wp.array(dtype=scalar),
        box_center: wp.array(dtype=vec3),
        box_half: wp.array(dtype=vec3),
        box_friction: wp.array(dtype=scalar),
        ramp: scalar,
    ):
        """Every static plane, sphere and box in turn (``colliders.py``)."""
        for c in range(wp.static(n_planes)):
            x, v = col.collide_plane(x, v, plane_normal[c], plane_offset[c], plane_friction[c], dt, ramp)
        for c in range(wp.static(n_spheres)):
            x, v = col.collide_sphere(x, v, sphere_center[c], sphere_radius[c], sphere_friction[c], dt, ramp)
        for c in range(wp.static(n_boxes)):
            x, v = col.collide_box(x, v, box_center[c], box_half[c], box_friction[c], dt, ramp)
        return x, v

    return types.SimpleNamespace(symplectic_euler=symplectic_euler, static_colliders=static_colliders)


@functools.cache
def kernels(scalar, n_planes: int, n_spheres: int, n_boxes: int) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3 = T.vec3
    fn = funcs(scalar, n_planes, n_spheres, n_boxes)

    @wp.kernel
    def integrate(
        x_in: wp.array(dtype=vec3),
        v_in: wp.array(dtype=vec3),
        f: wp.array(dtype=vec3),
        mass: wp.array(dtype=scalar),
        gravity: vec3,
        dt: scalar,
        plane_normal: wp.array(dtype=vec3),
        plane_offset: wp.array(dtype=scalar),
        plane_friction: wp.array(dtype=scalar),
        sphere_center: wp.array(dtype=vec3),
        sphere_radius: wp.array(dtype=scalar),
        sphere_friction: wp.array(dtype=scalar),
        box_center: wp.array(dtype=vec3),
        box_half: wp.array(dtype=vec3),
        box_friction: wp.array(dtype=scalar),
        ramp: scalar,
        x_out: wp.array(dtype=vec3),
        v_out: wp.array(dtype=vec3),
    ):
        i = wp.tid()
        x, v = fn.symplectic_euler(x_in[i], v_in[i], f[i], mass[i], gravity, dt)
        x, v = fn.static_colliders(
            x, v, dt, plane_normal, plane_offset, plane_friction, sphere_center, sphere_radius, sphere_friction,
            box_center, box_half, box_friction, ramp,
        )
        x_out[i] = x
        v_out[i] = v

    return types.SimpleNamespace(integrate=integrate)


def static_collider_arrays(model) -> list:
    """The static colliders' arrays in the order ``static_colliders`` takes them."""
    m = model
    return [
        m.plane_normal, m.plane_offset, m.plane_friction,
        m.sphere_center, m.sphere_radius, m.sphere_friction,
        m.box_center, m.box_half, m.box_friction, m.scalar(m.contact_ramp),
    ]


def launch_integrate(model, state_in, state_out, dt):
    """Symplectic Euler of ``state_in`` under ``state_out.force`` and gravity, then the
    colliders, into ``state_out.x``, ``state_out.v``."""
    S = model.scalar
    m = model
    wp.launch(
        kernels(S, len(m.planes), len(m.spheres), len(m.boxes)).integrate,
        m.particle_count,
        [state_in.x, state_in.v, state_out.force, m.particle_mass, m.types.vec3(*m.gravity), S(dt), *static_collider_arrays(m)],
        [state_out.x, state_out.v],
        device=m.device,
    )
