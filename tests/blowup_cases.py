"""The finite blow-up that ``sweep``, ``fit`` and the torch bridge must judge alike (one
test, ``simulate.energy_growth``): a putty box beside a scripted sphere that never touches
it. A ``Scripted`` motion has no speed known beforehand, so the divergence monitor's bounds
do not run there; at ``mu = 1e6`` Pa, ``DT`` is 4.6 x its stable step and ``STEPS`` steps end
finite, particles 36 m out (5.7e5 J of kinetic + gravitational energy gained, measured in
float32); at ``mu = 1e3`` Pa the same steps are stable. The box turns, which seeds the
instability: falling as a whole it kept F = I to the bit and never blew up."""

import warp_esph as we
from warp_esph import tools

DT = 1.0 / 300.0
STEPS = 30
HEALTHY_MU, BLOWN_MU = 1e3, 1e6


def _far(t):
    return (3.0, 0.5, 0.0), (0.0, 0.0, 0.0, 1.0)


def scripted_box_builder(mu: float | None = None) -> we.SceneBuilder:
    """27 putty particles on the ground, 3 m from a scripted sphere at rest (``mu``: the
    putty's shear modulus, None: the preset's)."""
    b = we.SceneBuilder(spacing=0.1)
    putty = we.Material.preset("putty") if mu is None else we.Material.preset("putty", mu=mu)
    # Turning at 1 rad/s: the step's rotation is not rigid to second order, a strain that seeds
    # the instability (a body falling as a whole has none, F = I to the bit).
    b.add_box((0.0, 0.5, 0.0), (0.3, 0.3, 0.3), putty, name="paste", angular_velocity=(0.0, 0.0, 1.0))
    b.add_ground()
    b.add_tool("sphere", radius=0.05, motion=tools.Scripted(_far), name="far")
    return b
