"""Built-in scenes and the TOML scene-file loader.

A scene is a configured ``SceneBuilder`` plus run settings (``Scene``). Every built-in
scene function takes ``scale``: the particle spacing is divided by it, so the geometry
stays the same and the particle count goes with ``scale**3`` (``scale < 1``: fewer
particles, e.g. for tests). Scene files are described in ``docs/scene_format.md``.

Two kinds of built-in scenes: everyday ones (a few thousand particles, the stable time
step), and one per figure of the paper (``fig1_...`` to ``fig8_...``), which run at the
paper's particle count and time step (Table 1, ``TABLE1``) at scale 1.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import sys
from collections.abc import Callable

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: the same parser as the tomli package
    try:
        import tomli as tomllib
    except ModuleNotFoundError:
        tomllib = None

import numpy as np

from . import checks
from .builder import SceneBuilder
from .material import PRESETS, Material
from .meshes import lattice_points

__all__ = [
    "Scene", "SCENES", "DEFAULT_SCENE", "FIGURE_SCENES", "TABLE1", "PaperRun", "get_scene", "load_scene", "load_scene_file",
    "paper_run_scene", "scene_names",
]


@dataclasses.dataclass
class Scene:
    """A scene ready to run: ``builder.finalize()`` makes the model.

    ``dt = None`` lets ``simulate`` pick the stable step of the model. ``figure`` names
    the paper's figure a scene reproduces (``"Fig. 2"``), ``None`` for the others.
    ``view``: a suggested camera direction (azimuth, elevation) in degrees, written to
    the USD file for ``warp-esph render`` (``None``: the renderer's default).
    ``diverges``: names of bodies the scene shows blowing up (a method's failure, as the
    paper's Fig. 8 does); ``simulate``'s divergence monitor leaves them out.
    """

    name: str
    description: str
    builder: SceneBuilder
    frames: int = 60
    fps: float = 30.0
    dt: float | None = None
    figure: str | None = None
    view: tuple[float, float] | None = None
    diverges: tuple[str, ...] = ()


def _scale(scale) -> float:
    return checks.positive("scale", scale)


def _doc(fn) -> str:
    """The first line of a scene function's docstring: the scene's one-line description."""
    return (fn.__doc__ or "").strip().splitlines()[0]


# ------------------------------------------------------------------ everyday scenes
# Small scenes (a few thousand particles at 1-2 cm spacing) that run in seconds to
# minutes on one CPU core, at the stable time step.
def dough_drop(scale: float = 1.0) -> Scene:
    """A 15 cm box of bread dough dropped 10 cm onto the ground; it slumps and spreads."""
    b = SceneBuilder(spacing=0.01 / _scale(scale))
    b.add_box((0.0, 0.175, 0.0), (0.15, 0.15, 0.15), Material.preset("dough"), name="dough")
    b.add_ground(friction=0.5)
    return Scene("dough_drop", _doc(dough_drop), b, frames=60, fps=30.0)


def _star_body(b: SceneBuilder, name: str = "star", material: Material | None = None):
    """The dough star of Fig. 6: 30 cm across, 4 cm thick, lying flat just above the ground."""
    b.add_star((0.0, 0.07, 0.0), outer_radius=0.15, inner_radius=0.065, thickness=0.04,
               material=material or Material.preset("dough"), name=name)
    b.add_ground(friction=0.6)


def star(scale: float = 1.0) -> Scene:
    """An extruded five-point star of dough dropped flat on the ground (Fig. 6 setup, 1 cm spacing)."""
    b = SceneBuilder(spacing=0.01 / _scale(scale))
    _star_body(b)
    return Scene("star", _doc(star), b, frames=60, fps=30.0)


def rubber_bounce(scale: float = 1.0) -> Scene:
    """A rubber ball dropped from 40 cm: it bounces and returns to its rest shape."""
    b = SceneBuilder(spacing=0.015 / _scale(scale))
    b.add_sphere((0.0, 0.48, 0.0), 0.08, Material.preset("rubber"), name="ball")
    b.add_ground(friction=0.3)
    return Scene("rubber_bounce", _doc(rubber_bounce), b, frames=60, fps=30.0)


def clay_on_sphere(scale: float = 1.0) -> Scene:
    """A clay ball falling on a fixed sphere; it wraps around it and keeps the dent."""
    b = SceneBuilder(spacing=0.01 / _scale(scale))
    b.add_sphere((0.02, 0.42, 0.0), 0.08, Material.preset("clay"), name="clay")
    b.add_sphere_collider((0.0, 0.12, 0.0), 0.12, friction=0.5)
    b.add_ground(friction=0.5)
    return Scene("clay_on_sphere", _doc(clay_on_sphere), b, frames=60, fps=30.0)


#: Fig. 2's materials: one stiffness, increasing plasticity (left to right). A little
#: viscosity settles the elastic one: undamped, its ringing after the impact grows until
#: the run diverges (about 1 s after landing).
def _cylinder_materials() -> list[tuple[str, Material]]:
    E, nu = 3.0e4, 0.3
    return [
        ("elastic", Material.from_young(E, nu, density=1000.0, viscosity=5.0)),
        ("plastic", Material.from_young(E, nu, yield_stress=400.0, flow_rate=20.0, hardening=2000.0, density=1000.0, viscosity=5.0)),
        ("very_plastic", Material.from_young(E, nu, yield_stress=100.0, flow_rate=100.0, density=1000.0, viscosity=5.0)),
    ]


def _cylinder_bodies(b: SceneBuilder, only=None):
    """Fig. 2: three upright cylinders (radius 5 cm, 15 cm tall) dropped 10 cm, 16 cm apart."""
    for k, (name, mat) in enumerate(_cylinder_materials()):
        if _wanted(only, name):
            b.add_cylinder(((k - 1) * 0.16, 0.175, 0.0), radius=0.05, height=0.15, material=mat, axis="y", name=name)
    b.add_ground(friction=0.5)


def three_cylinders(scale: float = 1.0) -> Scene:
    """Three cylinders of one stiffness and increasing plasticity fall on the ground (Fig. 2 setup, 1 cm spacing)."""
    b = SceneBuilder(spacing=0.01 / _scale(scale))
    _cylinder_bodies(b)
    return Scene("three_cylinders", _doc(three_cylinders), b, frames=60, fps=30.0)


# ------------------------------------------------------------------ the paper's figures
# Each figure scene runs, at scale 1, at the particle count and time step of the paper's
# Table 1 (docs/gallery.md lists what each one shows, docs/table1.md how fast it runs).
# Counts are those of lattice sampling at the chosen spacing; ``tests/test_figures.py``
# checks each is within 5 % of the paper. At ``scale`` S the spacing is divided by S and
# the time step follows the spacing (dt = paper dt / S: the same Courant number), rounded
# down so a frame is a whole number of steps: ``--scale 0.3`` is a quick, stable look.
#
# The frame rate is 25 fps: 1/25 s is a whole number of the paper's steps (400 of 0.1 ms,
# 80 of 0.5 ms); at 30 fps neither step divides a frame.
FIGURE_FPS = 25.0


def _figure_dt(paper_dt: float, scale: float, fps: float = FIGURE_FPS) -> float:
    """``paper_dt / scale`` rounded down to a whole number of steps per frame."""
    frame = 1.0 / fps
    steps = max(1, math.ceil(frame / (paper_dt / scale) - 1e-9))
    return frame / steps


def _wanted(only, name: str) -> bool:
    return only is None or name in only


def _check_only(scene: str, only, builder: SceneBuilder):
    """``only`` (a subset of body names, for one run of a multi-run figure) must name bodies of the scene."""
    if only is None:
        return
    built = {body.name for body in builder._bodies}
    missing = [n for n in only if n not in built]
    if missing or not built:
        raise ValueError(f"only = {tuple(only)!r} is not allowed: scene {scene!r} has no body {missing[0] if missing else only!r}")


def _asset(name: str) -> str:
    """Path of a mesh bundled with Warp (``bunny.usd``, ``bear.usd``)."""
    import warp.examples  # noqa: PLC0415 (ships with warp-lang)

    return os.path.join(warp.examples.get_asset_directory(), name)


def _rotation(axis, degrees: float) -> np.ndarray:
    """Rotation matrix about ``axis`` by ``degrees`` (Rodrigues)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    t = np.radians(degrees)
    return np.eye(3) + np.sin(t) * K + (1.0 - np.cos(t)) * (K @ K)


def _rotated_box_points(center, size: float, rotation: np.ndarray, spacing: float) -> np.ndarray:
    """World-lattice points inside a cube of edge ``size`` turned by ``rotation`` (as a mesh is sampled)."""
    c = np.asarray(center, dtype=np.float64)
    r = 0.5 * math.sqrt(3.0) * size
    p = lattice_points(-np.full(3, r), np.full(3, r), spacing)
    inside = (np.abs(p @ rotation) <= 0.5 * size + 1e-12).all(axis=1)  # body coordinates R^T p
    return p[inside] + c


def fig1_non_newtonian(scale: float = 1.0, only=None) -> Scene:
    """Paper Fig. 1: a non-Newtonian bear (Warp's bear.usd, 0.9 m tall) lands hard, rebounds a little, then flows."""
    spacing = 0.02 / _scale(scale)
    b = SceneBuilder(spacing=spacing)
    # Flow rate divided by the stress (paper §4): the hard landing barely flows and the bear
    # rebounds; once the stress has dropped it flows into a puddle within about a second.
    # Stable at dt = 0.5 ms with 2 cm spacing (stable step 0.7 ms). Softer settings, a
    # higher drop or less viscosity give a bigger bounce but diverge on landing: large
    # elastic deformation is where the method breaks down (paper §4).
    putty = Material.from_young(5.0e4, 0.3, yield_stress=500.0, flow_rate=2.0e5, density=1100.0,
                                viscosity=12.0, model="non_newtonian")
    if _wanted(only, "bear"):
        # bear.usd is 5.5 m tall: scaled by 0.163 it is 0.90 m tall, 1.6 m long, and the
        # 2 cm lattice holds 52,309 particles (paper: 52,316). Bottom 0.3 m above the ground.
        b.add_mesh(_asset("bear.usd"), putty, scale=0.163, translation=(0.0, 0.3, 0.0), name="bear")
    b.add_ground(friction=0.6)
    _check_only("fig1_non_newtonian", only, b)
    return Scene("fig1_non_newtonian", _doc(fig1_non_newtonian), b, frames=60, fps=FIGURE_FPS,
                 dt=_figure_dt(5.0e-4, scale), figure="Fig. 1", view=(55.0, 15.0))


def fig2_three_cylinders(scale: float = 1.0, only=None) -> Scene:
    """Paper Fig. 2: three cylinders, one stiffness, elastic / plastic / very plastic, fall on the ground."""
    # 4.1 mm spacing: 16,848 particles per cylinder (paper: 16,770 per run).
    b = SceneBuilder(spacing=0.0041 / _scale(scale))
    _cylinder_bodies(b, only)
    _check_only("fig2_three_cylinders", only, b)
    return Scene("fig2_three_cylinders", _doc(fig2_three_cylinders), b, frames=50, fps=FIGURE_FPS,
                 dt=_figure_dt(1.0e-4, scale), figure="Fig. 2", view=(15.0, 15.0))


def fig3_pile(scale: float = 1.0, only=None) -> Scene:
    """Paper Fig. 3: twelve clay bodies of two shapes (bricks and discs) fall in a column and form a pile."""
    spacing = 0.01 / _scale(scale)
    b = SceneBuilder(spacing=spacing)
    brick = Material.preset("clay")
    disc = Material.preset("clay", yield_stress=1200.0)
    golden = math.pi * (3.0 - math.sqrt(5.0))
    for k in range(12):
        shape = "brick" if k % 2 == 0 else "disc"
        name = f"{shape}{k}"
        if not _wanted(only, name):
            continue
        # A deterministic, slightly scattered column, bottom to top: each body 2.5 cm off the
        # axis, 7.5 cm above the one below, bricks turned 90 degrees from the one before.
        # Bodies touch only through SPH pressure (no friction between them), so shapes that
        # roll (lying cylinders, spheres) would not stay on the pile: flat ones are used.
        off = 0.025 * np.array([math.cos(k * golden), 0.0, math.sin(k * golden)])
        center = off + np.array([0.0, 0.1 + 0.075 * k, 0.0])
        if shape == "brick":
            size = (0.14, 0.05, 0.08) if (k // 2) % 2 == 0 else (0.08, 0.05, 0.14)
            b.add_box(center, size, brick, name=name)
        else:
            b.add_cylinder(center, radius=0.055, height=0.045, material=disc, axis="y", name=name)
    b.add_ground(friction=0.7)
    _check_only("fig3_pile", only, b)
    return Scene("fig3_pile", _doc(fig3_pile), b, frames=60, fps=FIGURE_FPS, dt=_figure_dt(1.0e-4, scale), figure="Fig. 3", view=(30.0, 20.0))


def fig4_bunny_on_sphere(scale: float = 1.0, only=None) -> Scene:
    """Paper Fig. 4: an elastoplastic bunny of dough (Warp's bunny.usd, 29 cm tall) falls on a fixed sphere."""
    spacing = 0.005 / _scale(scale)
    b = SceneBuilder(spacing=spacing)
    dough = Material.preset("dough")
    radius = 0.15
    # A sticky sphere (friction 1.5): the dough drapes over it and slides off slowly.
    b.add_sphere_collider((0.0, radius, 0.0), radius, friction=1.5)
    b.add_ground(friction=0.5)
    if _wanted(only, "bunny"):
        # bunny.usd is 1.6 m tall: scaled by 0.1795 it is 29 cm tall and the 5 mm lattice
        # holds 40,591 particles (paper: 40,556). Its body over the sphere, 8 cm above it.
        s = 0.1795
        b.add_mesh(_asset("bunny.usd"), dough, scale=s, translation=(0.03, 2 * radius + 0.08 - 0.0212 * s, -0.02), name="bunny")
    _check_only("fig4_bunny_on_sphere", only, b)
    return Scene("fig4_bunny_on_sphere", _doc(fig4_bunny_on_sphere), b, frames=50, fps=FIGURE_FPS,
                 dt=_figure_dt(1.0e-4, scale), figure="Fig. 4", view=(30.0, 20.0))


def fig5_hyperelastic_boxes(scale: float = 1.0, only=None) -> Scene:
    """Paper Fig. 5: two hyperelastic 10 cm cubes, stiff (left) and soft (right), dropped tilted on the ground."""
    size = 0.10
    # 8.65 lattice cells per edge: 664 particles per tilted cube (paper: 665).
    spacing = size / 8.65 / _scale(scale)
    b = SceneBuilder(spacing=spacing)
    turn = _rotation((1.0, 0.0, 1.0), 10.0)
    # Viscosity keeps the impact of these purely elastic cubes stable: the paper notes its
    # method breaks down under large elastic deformation of soft bodies.
    cubes = [
        ("stiff", -0.12, Material.from_young(2.0e5, 0.3, density=1000.0, viscosity=3.0, model="hyperelastic")),
        ("soft", 0.12, Material.from_young(2.0e4, 0.3, density=1000.0, viscosity=5.0, model="hyperelastic")),
    ]
    for name, x, mat in cubes:
        if _wanted(only, name):
            b.add_particles(_rotated_box_points((x, 0.25, 0.0), size, turn, spacing), mat, name=name, kind="box")
    b.add_ground(friction=0.4)
    _check_only("fig5_hyperelastic_boxes", only, b)
    return Scene("fig5_hyperelastic_boxes", _doc(fig5_hyperelastic_boxes), b, frames=50, fps=FIGURE_FPS,
                 dt=_figure_dt(1.0e-4, scale), figure="Fig. 5", view=(10.0, 15.0))


def fig6_dough_star(scale: float = 1.0, only=None) -> Scene:
    """Paper Fig. 6: an extruded star of slack bread dough slumps and spreads on the ground (5 mm spacing)."""
    b = SceneBuilder(spacing=0.005 / _scale(scale))
    if _wanted(only, "star"):
        # Slacker than the dough preset (yield 60 Pa, flow 40/s): it spreads by 10 % in 3 s.
        _star_body(b, material=Material.preset("dough", yield_stress=60.0, flow_rate=40.0))
    else:
        b.add_ground(friction=0.6)
    _check_only("fig6_dough_star", only, b)
    return Scene("fig6_dough_star", _doc(fig6_dough_star), b, frames=75, fps=FIGURE_FPS,
                 dt=_figure_dt(1.0e-4, scale), figure="Fig. 6", view=(20.0, 45.0))


def _grid_materials() -> list[tuple[str, str, Material]]:
    """Fig. 7: (row, column, material) of the 3 x 2 grid; each row varies one plastic parameter."""
    base = dict(density=1000.0, viscosity=4.0)
    E, nu = 5.0e4, 0.3
    return [
        ("top", "left", Material.from_young(E, nu, yield_stress=150.0, flow_rate=60.0, **base)),
        ("top", "right", Material.from_young(E, nu, yield_stress=1500.0, flow_rate=60.0, **base)),
        ("center", "left", Material.from_young(E, nu, yield_stress=300.0, flow_rate=6.0, **base)),
        ("center", "right", Material.from_young(E, nu, yield_stress=300.0, flow_rate=200.0, **base)),
        ("bottom", "left", Material.from_young(E, nu, yield_stress=300.0, flow_rate=60.0, hardening=0.0, **base)),
        ("bottom", "right", Material.from_young(E, nu, yield_stress=300.0, flow_rate=60.0, hardening=3.0e4, **base)),
    ]


#: Fig. 7 body names by (row, column): the parameter each row varies, low / high.
FIG7_BODIES = {
    ("top", "left"): "yield_low", ("top", "right"): "yield_high",
    ("center", "left"): "flow_slow", ("center", "right"): "flow_fast",
    ("bottom", "left"): "hardening_none", ("bottom", "right"): "hardening_strong",
}


def fig7_plastic_grid(scale: float = 1.0, only=None) -> Scene:
    """Paper Fig. 7: a 3 x 2 grid of box drops; rows vary yield stress, flow rate, hardening (low left, high right)."""
    # 23 cm boxes on a 1 cm lattice: 23^3 = 12,167 particles each (paper: 12,152 per run).
    b = SceneBuilder(spacing=0.01 / _scale(scale))
    rows = {"top": -0.6, "center": 0.0, "bottom": 0.6}  # z: the top row is the far one
    cols = {"left": -0.3, "right": 0.3}
    for row, col, mat in _grid_materials():
        name = FIG7_BODIES[(row, col)]
        if _wanted(only, name):
            b.add_box((cols[col], 0.4, rows[row]), (0.23, 0.23, 0.23), mat, name=name)
    b.add_ground(friction=0.6)
    _check_only("fig7_plastic_grid", only, b)
    return Scene("fig7_plastic_grid", _doc(fig7_plastic_grid), b, frames=50, fps=FIGURE_FPS,
                 dt=_figure_dt(1.0e-4, scale), figure="Fig. 7", view=(20.0, 40.0))


def _fig8_materials() -> list[tuple[str, Material]]:
    """Fig. 8: (row, material) of the elastic (top) and very plastic (bottom) rows."""
    # SPH viscosity damps the ringing after the release, so the final shape is read at rest.
    base = dict(density=1000.0, viscosity=20.0)
    E, nu = 5.0e4, 0.3
    return [
        ("elastic", Material.from_young(E, nu, **base)),
        ("plastic", Material.from_young(E, nu, yield_stress=1000.0, flow_rate=100.0, **base)),
    ]


#: Fig. 8 columns: the deformation model of each (left to right, SPEC §7).
FIG8_MODELS = ("incremental", "rest", "additive")
#: Fig. 8 timing (s): the compression acts on [0, FIG8_RELEASE), the run lasts FIG8_DURATION.
FIG8_RELEASE = 0.3
FIG8_DURATION = 1.0
#: Fig. 8 compression (1/s^2): a = -k (x - c) horizontally, 300 m/s^2 at the cubes' faces;
#: it squeezes the elastic cubes by about 10 % and the plastic ones by about 25 %.
FIG8_STRENGTH = 1500.0
#: Fig. 8 spin (rad/s) about the horizontal x axis. Over a path whose principal axes stay
#: fixed, the sum of per-step Green strains is the log strain and returns to zero on release,
#: so an additive model fails only where strained material rotates (its strain is summed in
#: world axes, not turned with the material): the cubes tumble while squeezed.
FIG8_SPIN = 12.0
#: Fig. 8 bodies: ``{row}_{model}``, e.g. ``plastic_rest``.
FIG8_BODIES = tuple(f"{row}_{model}" for model in FIG8_MODELS for row in ("elastic", "plastic"))


def fig8_comparison(scale: float = 1.0, only=None) -> Scene:
    """Paper Fig. 8: incremental (ours), rest-configuration and additive models, elastic and very plastic, compressed then released."""
    # 20 cm cubes, weightless and free (no ground): the compression, not contact, deforms
    # them, while they tumble (FIG8_SPIN) so that the additive model's strain rotates.
    # Columns (x): incremental, rest, additive; rows (z): elastic (far), very plastic (near).
    # The plastic rest-configuration cube is expected to blow up (the paper's lower middle).
    # Six separate simulations in one scene, as in the paper: the bodies do not interact, so
    # the debris of the plastic rest-configuration cube passes through the others.
    b = SceneBuilder(spacing=0.02 / _scale(scale), gravity=(0.0, 0.0, 0.0), bodies_interact=False)
    rows = {"elastic": -0.35, "plastic": 0.35}
    for k, deformation in enumerate(FIG8_MODELS):
        for row, mat in _fig8_materials():
            name = f"{row}_{deformation}"
            if _wanted(only, name):
                center = (0.6 * (k - 1), 0.3, rows[row])
                b.add_box(center, (0.2, 0.2, 0.2), mat.replace(deformation=deformation), name=name,
                          angular_velocity=(FIG8_SPIN, 0.0, 0.0))
                b.add_compression_field(center, FIG8_STRENGTH, 0.0, FIG8_RELEASE, body=name)
    _check_only("fig8_comparison", only, b)
    frames = round(FIG8_DURATION * FIGURE_FPS)
    # Its speed reaches 1.8e5 m/s 0.36 s in at scale 1 (finite): the monitor must not stop the figure.
    diverges = tuple(n for n in ("plastic_rest",) if n in {body.name for body in b._bodies})
    return Scene("fig8_comparison", _doc(fig8_comparison), b, frames=frames, fps=FIGURE_FPS,
                 dt=_figure_dt(1.0e-4, scale), figure="Fig. 8", view=(0.0, 50.0), diverges=diverges)


#: Built-in scenes by name: the everyday scenes, then one per figure of the paper.
SCENES: dict[str, Callable[..., Scene]] = {
    "dough_drop": dough_drop,
    "star": star,
    "rubber_bounce": rubber_bounce,
    "clay_on_sphere": clay_on_sphere,
    "three_cylinders": three_cylinders,
    "fig1_non_newtonian": fig1_non_newtonian,
    "fig2_three_cylinders": fig2_three_cylinders,
    "fig3_pile": fig3_pile,
    "fig4_bunny_on_sphere": fig4_bunny_on_sphere,
    "fig5_hyperelastic_boxes": fig5_hyperelastic_boxes,
    "fig6_dough_star": fig6_dough_star,
    "fig7_plastic_grid": fig7_plastic_grid,
    "fig8_comparison": fig8_comparison,
}
DEFAULT_SCENE = "dough_drop"
#: The scenes that reproduce a figure of the paper, in figure order.
FIGURE_SCENES = tuple(name for name in SCENES if name.startswith("fig"))


@dataclasses.dataclass(frozen=True)
class PaperRun:
    """One row of the paper's Table 1: a run, its step, particle count and seconds per frame
    (one core of a 2008 Xeon E5410). ``bodies``: the bodies of ``scene`` that make the run."""

    label: str
    scene: str
    bodies: tuple[str, ...]
    dt: float
    particles: int
    seconds_per_frame: float


#: The paper's Table 1, row by row, mapped to the built-in figure scenes.
TABLE1 = (
    PaperRun("Fig. 1", "fig1_non_newtonian", ("bear",), 0.5e-3, 52316, 96.4888),
    PaperRun("Fig. 4", "fig4_bunny_on_sphere", ("bunny",), 0.1e-3, 40556, 379.065),
    PaperRun("Fig. 2 (left)", "fig2_three_cylinders", ("elastic",), 0.1e-3, 16770, 138.257),
    PaperRun("Fig. 2 (center)", "fig2_three_cylinders", ("plastic",), 0.1e-3, 16770, 137.909),
    PaperRun("Fig. 2 (right)", "fig2_three_cylinders", ("very_plastic",), 0.1e-3, 16770, 141.591),
    PaperRun("Fig. 5 (left)", "fig5_hyperelastic_boxes", ("stiff",), 0.1e-3, 665, 4.76452),
    PaperRun("Fig. 5 (right)", "fig5_hyperelastic_boxes", ("soft",), 0.1e-3, 665, 4.88767),
    PaperRun("Fig. 7 (top, left)", "fig7_plastic_grid", ("yield_low",), 0.1e-3, 12152, 102.545),
    PaperRun("Fig. 7 (center, left)", "fig7_plastic_grid", ("flow_slow",), 0.1e-3, 12152, 86.9948),
    PaperRun("Fig. 7 (bottom, left)", "fig7_plastic_grid", ("hardening_none",), 0.1e-3, 12152, 94.4097),
    PaperRun("Fig. 7 (top, right)", "fig7_plastic_grid", ("yield_high",), 0.1e-3, 12152, 96.135),
    PaperRun("Fig. 7 (center, right)", "fig7_plastic_grid", ("flow_fast",), 0.1e-3, 12152, 87.1509),
    PaperRun("Fig. 7 (bottom, right)", "fig7_plastic_grid", ("hardening_strong",), 0.1e-3, 12152, 94.3632),
)


def paper_run_scene(run: PaperRun, scale: float = 1.0) -> Scene:
    """The scene of one Table 1 row: its figure scene with only that run's bodies."""
    return SCENES[run.scene](scale=scale, only=run.bodies)


def scene_names() -> list[str]:
    return list(SCENES)


def scene_descriptions() -> dict[str, str]:
    """One line per built-in scene (the first line of its function's docstring)."""
    return {name: _doc(fn) for name, fn in SCENES.items()}


def get_scene(name: str = DEFAULT_SCENE, scale: float = 1.0) -> Scene:
    """The built-in scene ``name`` at ``scale``."""
    if name not in SCENES:
        close = difflib.get_close_matches(str(name), SCENES, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ValueError(
            f"scene = {name!r} is not allowed: unknown scene{hint}; the built-in scenes are {', '.join(SCENES)}, "
            f"or give the path of a .toml scene file"
        )
    return SCENES[name](scale=scale)


def load_scene(name_or_path: str | os.PathLike | None = None, scale: float = 1.0) -> Scene:
    """A built-in scene by name, or a scene file (``.toml``) by path; ``None``: the default."""
    if name_or_path is None:
        return get_scene(DEFAULT_SCENE, scale)
    text = os.fspath(name_or_path)
    if text in SCENES:
        return get_scene(text, scale)
    if text.lower().endswith(".toml") or os.sep in text or (os.altsep and os.altsep in text) or os.path.exists(text):
        return load_scene_file(text, scale)
    return get_scene(text, scale)


# ------------------------------------------------------------------ scene files
class _Num:
    """Schema type: a real number (int or float, not bool); ``inf`` only where allowed."""

    def __init__(self, allow_inf: bool = False):
        self.allow_inf = allow_inf

    def check(self, value) -> bool:
        if isinstance(value, int) and not isinstance(value, bool) and not -_FLOAT_MAX <= value <= _FLOAT_MAX:
            return False  # TOML integers are unbounded: 10**400 overflows a float
        return isinstance(value, (int, float)) and not isinstance(value, bool) and (self.allow_inf or math.isfinite(value)) and not (isinstance(value, float) and math.isnan(value))

    def describe(self) -> str:
        return "a number" + (" (inf allowed)" if self.allow_inf else "")


_FLOAT_MAX = int(sys.float_info.max)


class _Int:
    def check(self, value) -> bool:
        return isinstance(value, int) and not isinstance(value, bool)

    def describe(self) -> str:
        return "an integer"


class _Str:
    def check(self, value) -> bool:
        return isinstance(value, str)

    def describe(self) -> str:
        return "a string"


class _Bool:
    def check(self, value) -> bool:
        return isinstance(value, bool)

    def describe(self) -> str:
        return "true or false"


class _Vec3:
    def check(self, value) -> bool:
        return isinstance(value, list) and len(value) == 3 and all(_Num().check(c) for c in value)

    def describe(self) -> str:
        return "an array of 3 numbers"


NUM, NUM_INF, INT, STR, BOOL, VEC3 = _Num(), _Num(allow_inf=True), _Int(), _Str(), _Bool(), _Vec3()

#: Every key a scene file may hold, per table: name -> (type, required).
SCENE_KEYS = {
    "name": (STR, False), "description": (STR, False), "spacing": (NUM, False), "support_radius": (NUM, False),
    "gravity": (VEC3, False), "max_neighbors": (INT, False), "frames": (INT, False), "fps": (NUM, False), "dt": (NUM, False),
}
MATERIAL_KEYS = {
    "preset": (STR, False), "E": (NUM, False), "nu": (NUM, False), "mu": (NUM, False), "lam": (NUM, False),
    "yield_stress": (NUM_INF, False), "flow_rate": (NUM, False), "hardening": (NUM, False), "density": (NUM, False),
    "pressure_stiffness": (NUM, False), "viscosity": (NUM, False), "model": (STR, False), "clamp_pressure": (BOOL, False),
    "deformation": (STR, False), "elastic_force": (STR, False),
}
BODY_COMMON = {"shape": (STR, True), "material": (STR, True), "name": (STR, False), "velocity": (VEC3, False),
               "angular_velocity": (VEC3, False)}
BODY_SHAPES = {
    "box": {"center": (VEC3, True), "size": (VEC3, True)},
    "sphere": {"center": (VEC3, True), "radius": (NUM, True)},
    "cylinder": {"center": (VEC3, True), "radius": (NUM, True), "height": (NUM, True), "axis": (STR, False)},
    "star": {"center": (VEC3, True), "outer_radius": (NUM, True), "inner_radius": (NUM, True), "thickness": (NUM, True), "points": (INT, False)},
    "mesh": {"file": (STR, True), "scale": (NUM, False), "translation": (VEC3, False), "prim_path": (STR, False)},
}
COLLIDER_TYPES = {
    "ground": {"height": (NUM, False), "friction": (NUM, False)},
    "plane": {"normal": (VEC3, True), "offset": (NUM, True), "friction": (NUM, False)},
    "sphere": {"center": (VEC3, True), "radius": (NUM, True), "friction": (NUM, False)},
    "box": {"center": (VEC3, True), "half_extents": (VEC3, True), "friction": (NUM, False)},
}
TOP_KEYS = ("scene", "materials", "bodies", "colliders")


def _did_you_mean(key: str, allowed) -> str:
    close = difflib.get_close_matches(key, list(allowed), n=1, cutoff=0.6)
    if not close:
        close = [a for a in allowed if a.lower() == key.lower()]
    return f"; did you mean {close[0]!r}?" if close else ""


def _check_table(file: str, where: str, table, schema: dict) -> dict:
    """Reject unknown keys, missing required keys and wrongly typed values."""
    if not isinstance(table, dict):
        raise ValueError(f"{file}: {where} must be a table, not {type(table).__name__} {table!r}")
    for key, value in table.items():
        if key not in schema:
            raise ValueError(
                f"{file}: unknown key {key!r} in {where}{_did_you_mean(key, schema)} "
                f"(allowed keys: {', '.join(schema)})"
            )
        kind, _ = schema[key]
        if not kind.check(value):
            raise ValueError(f"{file}: key {key!r} in {where} must be {kind.describe()}, not {type(value).__name__} {checks.shorten(value)!r}")
    for key, (_, required) in schema.items():
        if required and key not in table:
            raise ValueError(f"{file}: missing key {key!r} in {where}")
    return table


def _choice(file: str, where: str, key: str, value: str, allowed) -> str:
    if value not in allowed:
        raise ValueError(
            f"{file}: {key} = {value!r} in {where} is not allowed{_did_you_mean(value, allowed)} "
            f"(allowed: {', '.join(allowed)})"
        )
    return value


def _material(file: str, name: str, table: dict) -> Material:
    where = f"[materials.{name}]"
    _check_table(file, where, table, MATERIAL_KEYS)
    fields = {k: v for k, v in table.items() if k not in ("preset", "E", "nu")}
    if ("E" in table) != ("nu" in table):
        raise ValueError(f"{file}: {where} gives {'E' if 'E' in table else 'nu'} without {'nu' if 'E' in table else 'E'}: give both")
    if "E" in table:
        if "mu" in table or "lam" in table:
            raise ValueError(f"{file}: {where} gives E/nu and mu/lam: give one pair")
        E, nu = table["E"], table["nu"]
        if not E > 0:
            raise ValueError(f"{file}: E = {E!r} in {where} is not allowed: must be > 0")
        if not -1.0 < nu < 0.5:
            raise ValueError(f"{file}: nu = {nu!r} in {where} is not allowed: must be in (-1, 0.5)")
        fields["mu"] = E / (2.0 * (1.0 + nu))
        fields["lam"] = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    try:
        if "preset" in table:
            preset = _choice(file, where, "preset", table["preset"], tuple(PRESETS))
            if "pressure_stiffness" not in fields:
                # Recomputed from the (possibly changed) bulk modulus, as for a new material.
                fields["pressure_stiffness"] = None
            return dataclasses.replace(PRESETS[preset], **fields)
        if "mu" not in fields or "lam" not in fields:
            raise ValueError(f"{file}: {where} needs a preset, E and nu, or mu and lam")
        return Material(**fields)
    except ValueError as e:
        msg = str(e)
        if msg.startswith(file):
            raise
        raise ValueError(f"{file}: {where}: {msg}") from None


def _body(file: str, k: int, table: dict, builder: SceneBuilder, materials: dict, base_dir: str):
    where = f"[[bodies]] #{k + 1}"
    if not isinstance(table, dict):
        raise ValueError(f"{file}: {where} must be a table, not {table!r}")
    shape = table.get("shape")
    if shape is None:
        raise ValueError(f"{file}: missing key 'shape' in {where} (one of {', '.join(BODY_SHAPES)})")
    if not isinstance(shape, str):
        raise ValueError(f"{file}: key 'shape' in {where} must be a string, not {type(shape).__name__} {shape!r}")
    _choice(file, where, "shape", shape, tuple(BODY_SHAPES))
    where = f"{where} (shape {shape!r})"
    _check_table(file, where, table, {**BODY_COMMON, **BODY_SHAPES[shape]})
    mat_name = table["material"]
    if mat_name in materials:
        material = materials[mat_name]
    elif mat_name in PRESETS:
        material = materials.setdefault(mat_name, Material.preset(mat_name))
    else:
        known = list(materials) + [p for p in PRESETS if p not in materials]
        raise ValueError(
            f"{file}: material = {mat_name!r} in {where} is not allowed: no [materials.{mat_name}] table and no preset "
            f"of that name{_did_you_mean(mat_name, known)} (known: {', '.join(known)})"
        )
    args = {k: v for k, v in table.items() if k not in ("shape", "material")}
    try:
        if shape == "box":
            builder.add_box(material=material, **args)
        elif shape == "sphere":
            builder.add_sphere(material=material, **args)
        elif shape == "cylinder":
            builder.add_cylinder(material=material, **args)
        elif shape == "star":
            builder.add_star(material=material, **args)
        else:
            source = args.pop("file")
            if not os.path.isabs(source):
                source = os.path.join(base_dir, source)
            builder.add_mesh(source, material, **args)
    except ValueError as e:
        raise ValueError(f"{file}: {where}: {e}") from None


def _collider(file: str, k: int, table: dict, builder: SceneBuilder):
    where = f"[[colliders]] #{k + 1}"
    if not isinstance(table, dict):
        raise ValueError(f"{file}: {where} must be a table, not {table!r}")
    kind = table.get("type")
    if kind is None:
        raise ValueError(f"{file}: missing key 'type' in {where} (one of {', '.join(COLLIDER_TYPES)})")
    if not isinstance(kind, str):
        raise ValueError(f"{file}: key 'type' in {where} must be a string, not {type(kind).__name__} {kind!r}")
    _choice(file, where, "type", kind, tuple(COLLIDER_TYPES))
    where = f"{where} (type {kind!r})"
    _check_table(file, where, table, {"type": (STR, True), **COLLIDER_TYPES[kind]})
    args = {k: v for k, v in table.items() if k != "type"}
    try:
        if kind == "ground":
            builder.add_ground(**args)
        elif kind == "plane":
            builder.add_plane(**args)
        elif kind == "sphere":
            builder.add_sphere_collider(**args)
        else:
            builder.add_box_collider(**args)
    except ValueError as e:
        raise ValueError(f"{file}: {where}: {e}") from None


def load_scene_file(path, scale: float = 1.0) -> Scene:
    """Read a TOML scene file (format: ``docs/scene_format.md``).

    ``scale`` divides the spacing (and an explicit support radius) as for built-in
    scenes. Any problem — unreadable file, TOML syntax, unknown or misspelt key, wrong
    type, bad value — raises a ``ValueError`` that names the file, the table and the key.
    """
    scale = _scale(scale)
    file = os.fspath(path)
    if tomllib is None:
        raise ValueError(f"cannot read scene file {file!r}: reading TOML needs Python >= 3.11 or the tomli package")
    try:
        with open(file, "rb") as fh:
            data = tomllib.load(fh)
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"{file}: invalid TOML: {e}") from None
    except UnicodeDecodeError as e:
        raise ValueError(f"{file}: invalid TOML: not UTF-8 text (byte {e.start})") from None
    except OSError as e:
        raise ValueError(f"cannot read scene file {file!r}: {e.strerror or e}") from None
    for key in data:
        if key not in TOP_KEYS:
            raise ValueError(f"{file}: unknown key {key!r} at the top level{_did_you_mean(key, TOP_KEYS)} (allowed: {', '.join(TOP_KEYS)})")
    scene = _check_table(file, "[scene]", data.get("scene", {}), SCENE_KEYS)
    materials_table = data.get("materials", {})
    if not isinstance(materials_table, dict):
        raise ValueError(f"{file}: 'materials' must be a table of [materials.NAME] tables, not {materials_table!r}")
    bodies = data.get("bodies", [])
    colliders = data.get("colliders", [])
    for key, value in (("bodies", bodies), ("colliders", colliders)):
        if not isinstance(value, list):
            raise ValueError(f"{file}: '{key}' must be an array of tables ([[{key}]]), not {type(value).__name__}")
    if not bodies:
        raise ValueError(f"{file}: the scene has no bodies: add at least one [[bodies]] table")

    try:
        spacing = checks.positive("spacing", scene.get("spacing", 0.02)) / scale
        support = scene.get("support_radius")
        builder = SceneBuilder(
            spacing=spacing,
            gravity=scene.get("gravity", (0.0, -9.81, 0.0)),
            support_radius=None if support is None else checks.positive("support_radius", support) / scale,
            max_neighbors=scene.get("max_neighbors", 30),
        )
        frames = checks.positive_int("frames", scene.get("frames", 60))
        fps = checks.positive("fps", scene.get("fps", 30.0))
        dt = scene.get("dt")
        if dt is not None:
            dt = checks.positive("dt", dt)
    except ValueError as e:
        raise ValueError(f"{file}: [scene]: {e}") from None

    materials = {name: _material(file, name, table) for name, table in materials_table.items()}
    base_dir = os.path.dirname(os.path.abspath(file))
    for k, table in enumerate(bodies):
        _body(file, k, table, builder, materials, base_dir)
    for k, table in enumerate(colliders):
        _collider(file, k, table, builder)
    name = scene.get("name") or os.path.splitext(os.path.basename(file))[0]
    description = scene.get("description") or f"scene file {file}"
    return Scene(name, description, builder, frames=frames, fps=fps, dt=dt)
