"""Built-in scenes (the scene-file loader is ``warp_esph.scene_file``).

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
from collections.abc import Callable

import numpy as np

from . import checks
from .builder import SceneBuilder, finalize_worlds
from .material import Material
from .meshes import lattice_points
from .scene_file import Scene, load_scene_file

__all__ = [
    "Scene", "SCENES", "DEFAULT_SCENE", "FIGURE_SCENES", "TABLE1", "PaperRun", "get_scene", "load_scene", "load_scene_file",
    "paper_run_scene", "scene_names",
]


def _scale(scale) -> float:
    return checks.positive("scale", scale)


class ScaleRefused(checks.Rebuilt, ValueError):
    """A scene's refusal of a scale at which it builds but cannot show what it is for (too
    few particles for its bodies' deformation): ``scale`` is not allowed ``why``; give one
    ``allowed``. ``load_scaled_scene`` passes it on naming the option or setting that gave
    the scale (``message(what)``), where other refusals at a scale other than 1 it blames on
    the spacing."""

    def __init__(self, scale: float, why: str, allowed: str):
        self.scale, self.why, self.allowed = scale, why, allowed
        super().__init__(self.message("scale"))

    def message(self, what: str) -> str:
        return f"{what} = {self.scale:g} is not allowed {self.why}; give {what} {self.allowed}"


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
#: viscosity settles the elastic one: undamped, with the paper's force, its ringing after
#: the impact grows until the run diverges (about 1 s after landing). ``None`` leaves the
#: force to ``Material``'s default, as a user's material would: named, it counted as given,
#: and ``replace(deformation="additive")`` refused it.
def _cylinder_materials(elastic_force: str | None = None) -> list[tuple[str, Material]]:
    E, nu = 3.0e4, 0.3
    base = dict(density=1000.0, viscosity=5.0, elastic_force=elastic_force)
    return [
        ("elastic", Material.from_young(E, nu, **base)),
        ("plastic", Material.from_young(E, nu, yield_stress=400.0, flow_rate=20.0, hardening=2000.0, **base)),
        ("very_plastic", Material.from_young(E, nu, yield_stress=100.0, flow_rate=100.0, **base)),
    ]


def _cylinder_bodies(b: SceneBuilder, only=None, elastic_force: str | None = None):
    """Fig. 2: three upright cylinders (radius 5 cm, 15 cm tall) dropped 10 cm, 16 cm apart."""
    for k, (name, mat) in enumerate(_cylinder_materials(elastic_force)):
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
# down so a frame is a whole number of steps: ``--scale 0.3`` is a quick, stable look
# (fig3_pile from 0.45: below it its bodies are one layer thick, refused by ``load_scaled_scene``).
#
# The frame rate is 25 fps: 1/25 s is a whole number of the paper's steps (400 of 0.1 ms,
# 80 of 0.5 ms); at 30 fps neither step divides a frame.
FIGURE_FPS = 25.0
#: The figure scenes reproduce the paper, so their materials use its elastic force
#: (eqs. 10-13), not the library's default (``Material.elastic_force``).
PAPER = "paper"


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
        raise ValueError(f"only = {checks.shorten(tuple(only))!r} is not allowed: scene {scene!r} has no body {missing[0] if missing else only!r}")


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
                                viscosity=12.0, model="non_newtonian", elastic_force=PAPER)
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
    _cylinder_bodies(b, only, elastic_force=PAPER)
    _check_only("fig2_three_cylinders", only, b)
    return Scene("fig2_three_cylinders", _doc(fig2_three_cylinders), b, frames=50, fps=FIGURE_FPS,
                 dt=_figure_dt(1.0e-4, scale), figure="Fig. 2", view=(15.0, 15.0))


def fig3_pile(scale: float = 1.0, only=None) -> Scene:
    """Paper Fig. 3: twelve clay bodies of two shapes (bricks and discs) fall in a column and form a pile."""
    spacing = 0.01 / _scale(scale)
    b = SceneBuilder(spacing=spacing)
    brick = Material.preset("clay", elastic_force=PAPER)
    disc = Material.preset("clay", yield_stress=1200.0, elastic_force=PAPER)
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
    dough = Material.preset("dough", elastic_force=PAPER)
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
        ("stiff", -0.12, Material.from_young(2.0e5, 0.3, density=1000.0, viscosity=3.0, model="hyperelastic", elastic_force=PAPER)),
        ("soft", 0.12, Material.from_young(2.0e4, 0.3, density=1000.0, viscosity=5.0, model="hyperelastic", elastic_force=PAPER)),
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
        _star_body(b, material=Material.preset("dough", yield_stress=60.0, flow_rate=40.0, elastic_force=PAPER))
    else:
        b.add_ground(friction=0.6)
    _check_only("fig6_dough_star", only, b)
    return Scene("fig6_dough_star", _doc(fig6_dough_star), b, frames=75, fps=FIGURE_FPS,
                 dt=_figure_dt(1.0e-4, scale), figure="Fig. 6", view=(20.0, 45.0))


def _grid_materials() -> list[tuple[str, str, Material]]:
    """Fig. 7: (row, column, material) of the 3 x 2 grid; each row varies one plastic parameter."""
    base = dict(density=1000.0, viscosity=4.0, elastic_force=PAPER)
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


def _fig8_materials(elastic_force: str | None = PAPER) -> list[tuple[str, Material]]:
    """Fig. 8: (row, material) of the elastic (top) and very plastic (bottom) rows."""
    # SPH viscosity damps the ringing after the release, so the final shape is read at rest.
    # The additive model has only the paper's force: the figure's other cubes use it too, so
    # the three columns differ only in the deformation model. Its pair forces are not central,
    # so the free cubes' spin drifts after the release (the elastic incremental one +7.9 % by
    # 1 s; the variational force keeps it: docs/physics.md, "Angular momentum of free bodies").
    base = dict(density=1000.0, viscosity=20.0, elastic_force=elastic_force)
    E, nu = 5.0e4, 0.3
    return [
        ("elastic", Material.from_young(E, nu, **base)),
        ("plastic", Material.from_young(E, nu, yield_stress=1000.0, flow_rate=100.0, **base)),
    ]


#: Fig. 8 columns: the deformation model of each (left to right, docs/method.md §7).
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
#: The smallest scale of ``fig8_comparison`` with its very plastic incremental and additive
#: cubes (6 particles across). The compression squeezes them into a column along y a few
#: particles wide; coarser, the column is too thin for the deformation fit (paper §4), its
#: fits lose their neighbours, and its particles, holding each other no more, fly apart at
#: the speed the squeeze gave them. Measured, each cube alone at the scene's dt, float32 and
#: float64 alike (docs/gallery.md): at 0.3 (3 across) the incremental one becomes a line of
#: particles by the release and its highest particle is 1.85 m up at 1 s (0.37 m at the
#: start), flying at 1.9 m/s; at 0.4 both come apart; at 0.5 the additive one still loses
#: fits (5k few-neighbour particle-steps) and the incremental one keeps stretching (its
#: deformation's kinetic energy 0.16 J at 0.5 s, 0.55 J at 1 s); from 0.6 no fit is lost and
#: the incremental one comes to rest a column. The plastic rest-configuration cube blows up
#: at every scale measured (``diverges``), and the elastic cubes keep their shape from 0.3.
FIG8_PLASTIC_MIN_SCALE = 0.6


def fig8_comparison(scale: float = 1.0, only=None) -> Scene:
    """Paper Fig. 8: incremental (ours), rest-configuration and additive models, elastic and very plastic, compressed then released.

    ``scale`` is at least ``FIG8_PLASTIC_MIN_SCALE`` (0.6) with the very plastic incremental or
    additive cube: coarser, the compression squeezes them into a column too thin for the
    deformation fit and their particles fly apart (``ScaleRefused``); ``only`` without them
    runs at any scale.
    """
    b = _fig8_builder(scale, only)
    thin = [body for body in b._bodies if body.name in ("plastic_incremental", "plastic_additive")]
    if thin and scale < FIG8_PLASTIC_MIN_SCALE:
        names = ", ".join(body.name for body in thin)
        raise ScaleRefused(scale, f"for fig8_comparison's very plastic cubes ({names}): at {round(thin[0].count ** (1 / 3))} "
                           "particles across, the compression squeezes them into a column too thin for the deformation fit "
                           "(paper §4), and they come apart",
                           f">= {FIG8_PLASTIC_MIN_SCALE:g}, or leave them out (scenes.fig8_comparison(only=...))")
    frames = round(FIG8_DURATION * FIGURE_FPS)
    # Its speed reaches 1.8e5 m/s 0.36 s in at scale 1 (finite): the monitor must not stop the figure.
    diverges = tuple(n for n in ("plastic_rest",) if n in {body.name for body in b._bodies})
    return Scene("fig8_comparison", _doc(fig8_comparison), b, frames=frames, fps=FIGURE_FPS,
                 dt=_figure_dt(1.0e-4, scale), figure="Fig. 8", view=(0.0, 50.0), diverges=diverges)


def _fig8_builder(scale: float, only) -> SceneBuilder:
    """The builder of ``fig8_comparison``, at any scale (the tests' measure of the smallest one)."""
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
                # The paper's spiky pressure force, as the paper's figure: with the energy force
                # (the default) the elastic rest-configuration cube diverges from 0.45 s at
                # scale 0.8 (either fit guard), where the paper's shows it returning: its two
                # middle layers merge, since the energy force's push between two layers fades
                # to 0 as they meet and the spiky one's does not (docs/physics.md, "The Fig. 8
                # rest-configuration cube and the energy pressure force").
                b.add_box(center, (0.2, 0.2, 0.2), mat.replace(deformation=deformation, pressure_force="spiky"), name=name,
                          angular_velocity=(FIG8_SPIN, 0.0, 0.0))
                b.add_compression_field(center, FIG8_STRENGTH, 0.0, FIG8_RELEASE, body=name)
    _check_only("fig8_comparison", only, b)
    return b


# ------------------------------------------------------------------ lab tests (tools.py)
# The standard tests of a texture or materials lab, with moving tools and pinned sets. Each
# tool's pose and mean reaction force per frame go to <output>_tools.csv/.json
# (warp-esph run); docs/tools.md says what each scene measures.
def _lab_elastic(E: float, nu: float = 0.3, density: float = 1000.0, viscosity: float = 5.0) -> Material:
    return Material.from_young(E, nu, density=density, viscosity=viscosity, pressure_stiffness=0.0)


def lab_compression(scale: float = 1.0) -> Scene:
    """Texture-analyser compression: a 4 cm cylinder of firm dough squeezed 30 % between a fixed and a descending plate."""
    from . import tools  # noqa: PLC0415

    b = SceneBuilder(spacing=0.0025 / _scale(scale))
    r, h = 0.02, 0.03
    # Firmer than the dough preset (yield 150 Pa), which slumps under its own weight
    # (rho g h = 340 Pa) before the plate arrives.
    firm = Material.preset("dough").replace(yield_stress=1000.0)
    b.add_cylinder((0.0, h / 2, 0.0), r, h, firm, name="sample")
    # Tools on the outer particle layers (their centres), half a spacing inside the faces:
    # a platen at the face would travel half a spacing before it touched anything.
    bottom, top = float(b._points[-1][:, 1].min()), float(b._points[-1][:, 1].max())
    b.add_tool("plane", position=(0.0, bottom, 0.0), friction=0.3, name="base")
    speed = 0.3 * (top - bottom) / 2.0  # 30 % strain over the 2 s run
    b.add_tool("box", half_extents=(0.04, 0.005, 0.04), friction=0.3,
               motion=tools.Velocity((0.0, -speed, 0.0), position=(0.0, top + 0.005, 0.0)), name="plate")  # touching
    return Scene("lab_compression", _doc(lab_compression), b, frames=60, fps=30.0)


def lab_squeeze_flow(scale: float = 1.0) -> Scene:
    """Squeeze flow: a toothpaste disc between no-slip plates, the top one closing the gap from 2 to 1 cm."""
    from . import tools  # noqa: PLC0415

    b = SceneBuilder(spacing=0.004 / _scale(scale))
    r, h = 0.04, 0.02
    b.add_cylinder((0.0, h / 2, 0.0), r, h, Material.preset("toothpaste"), name="sample")
    b.add_tool("plane", position=(0.0, 0.0, 0.0), friction=1.0, static_friction=2.0, name="base")
    b.add_tool("box", half_extents=(0.1, 0.005, 0.1), friction=1.0, static_friction=2.0,
               motion=tools.Keyframes([0.0, 2.0], [(0.0, h + 0.005, 0.0), (0.0, h / 2 + 0.005, 0.0)]), name="plate")
    return Scene("lab_squeeze_flow", _doc(lab_squeeze_flow), b, frames=60, fps=30.0)


def lab_indentation(scale: float = 1.0) -> Scene:
    """Sphere indentation: a 2 cm steel ball pressed 4 mm into a rubbery block on the ground, then withdrawn."""
    from . import tools  # noqa: PLC0415

    b = SceneBuilder(spacing=0.005 / _scale(scale))
    b.add_box((0.0, 0.02, 0.0), (0.08, 0.04, 0.08), _lab_elastic(1.0e5), name="block")
    # The ball starts touching the top particle layer (centres, half a spacing below the
    # block's face), so that it goes the full 4 mm into the particles.
    bottom, top = float(b._points[-1][:, 1].min()), float(b._points[-1][:, 1].max())
    b.add_tool("plane", position=(0.0, bottom, 0.0), friction=0.5, name="base")
    R = 0.02
    b.add_tool("sphere", radius=R, friction=0.0, name="indenter",
               motion=tools.Keyframes([0.0, 1.0, 2.0], [(0.0, top + R, 0.0), (0.0, top + R - 0.004, 0.0), (0.0, top + R, 0.0)]))
    return Scene("lab_indentation", _doc(lab_indentation), b, frames=60, fps=30.0)


def lab_three_point_bending(scale: float = 1.0) -> Scene:
    """Three-point bending: a 24 cm beam on two support pins 18 cm apart, pushed down at mid-span."""
    from . import tools  # noqa: PLC0415

    t, half_span = 0.04, 0.09
    spacing = 0.005 / _scale(scale)
    # A column over each support needs a whole number of spacings in the half span: at other
    # scales the supports stood between two columns, up to 0.32 mm below the beam (scale 0.8),
    # the span the beam rested on differed from 18 cm by up to a spacing, and at scale 0.7
    # the pin missed the mid-span column by half a spacing. So the spacing is the nearest
    # that divides it (scales 0.5 and 1 keep theirs exactly).
    steps = max(1, round(half_span / spacing))
    if abs(steps * spacing - half_span) > 1e-9 * half_span:
        spacing = half_span / steps
    b = SceneBuilder(spacing=spacing)
    # An odd number of particle columns, about 24 cm plus a spacing, so that one column is at
    # mid-span under the pin (and, the half span whole spacings, one over each support).
    b.add_box((0.0, 0.02 + t / 2, 0.0), ((2 * round(0.12 / spacing) + 1) * spacing, t, t), _lab_elastic(1.0e6),
              name="beam")
    bottom, top = float(b._points[-1][:, 1].min()), float(b._points[-1][:, 1].max())
    along_z = (math.sin(math.pi / 4), 0.0, 0.0, math.cos(math.pi / 4))  # a cylinder's y axis turned onto z
    # Supports and pin touch the outer particle layers (centres) at t = 0.
    for name, x in (("support_left", -half_span), ("support_right", half_span)):
        b.add_tool("cylinder", radius=0.01, half_height=0.05, position=(x, bottom - 0.01, 0.0), orientation=along_z, name=name)
    b.add_tool("cylinder", radius=0.01, half_height=0.05, name="loading_pin",
               motion=tools.Velocity((0.0, -0.005, 0.0), position=(0.0, top + 0.01, 0.0), orientation=along_z))
    return Scene("lab_three_point_bending", _doc(lab_three_point_bending), b, frames=60, fps=30.0)


def lab_cantilever(scale: float = 1.0) -> Scene:
    """Clamped cantilever: a 20 cm beam, 5 x 5 cm, held at one end, sagging under its own weight."""
    b = SceneBuilder(spacing=0.005 / _scale(scale))
    L, t = 0.2, 0.05
    clamp = 3 * b.spacing
    b.add_box(((L - clamp) / 2, t / 2, 0.0), (L + clamp, t, t), _lab_elastic(1.0e6, viscosity=20.0), name="beam")
    b.pin(body="beam", region=((-1.0, -1.0, -1.0), (0.0, 1.0, 1.0)), name="clamp")
    return Scene("lab_cantilever", _doc(lab_cantilever), b, frames=60, fps=30.0)


def lab_cutting(scale: float = 1.0) -> Scene:
    """Cutting: a knife blade (a closed triangle mesh) pushed down through a block of firm dough at 5 cm/s."""
    from . import tools  # noqa: PLC0415

    b = SceneBuilder(spacing=0.004 / _scale(scale))
    b.add_box((0.0, 0.02, 0.0), (0.1, 0.04, 0.06), Material.preset("dough").replace(yield_stress=1000.0), name="dough")
    b.add_tool("plane", position=(0.0, 0.0, 0.0), friction=0.5, name="board")
    # A wedge (1 cm back over 6 cm) whose edge meets a column of particles: a blade thinner
    # than the spacing between two columns would touch none (docs/tools.md).
    edge_x = float(np.unique(b._points[-1][:, 0])[len(np.unique(b._points[-1][:, 0])) // 2])
    b.add_tool("mesh", mesh=tools.blade_mesh(0.12, 0.06, 0.01), friction=0.2, name="blade",
               motion=tools.Velocity((0.0, -0.05, 0.0), position=(edge_x, 0.041, 0.0)))
    return Scene("lab_cutting", _doc(lab_cutting), b, frames=30, fps=30.0)


def lab_fig8_plates(scale: float = 1.0) -> Scene:
    """Fig. 8's compression done with moving plates: an elastic and a very plastic cube squeezed 15 % from four sides, then released."""
    from . import tools  # noqa: PLC0415

    b = SceneBuilder(spacing=0.02 / _scale(scale), gravity=(0.0, 0.0, 0.0), bodies_interact=False)
    squeeze = 0.15
    # The default (variational) force, left to its default as a user's: a lab test, not a
    # reproduction of the figure.
    for (row, mat), z0 in zip(_fig8_materials(None), (-0.35, 0.35)):
        center = np.array([0.0, 0.3, z0])
        b.add_box(tuple(center), (0.2, 0.2, 0.2), mat, name=row)
        pts = b._points[-1]
        half = 0.5 * (pts.max(axis=0) - pts.min(axis=0))  # plates start on the outer particle layers
        for axis, sign in ((0, 1), (0, -1), (2, 1), (2, -1)):
            # Finite plates (boxes 1 cm thick): an infinite plane would also push the other cube.
            plate = np.full(3, 0.15)
            plate[axis] = 0.005
            start = center.copy()
            start[axis] += sign * (half[axis] + plate[axis])
            end = start.copy()
            end[axis] -= sign * half[axis] * squeeze
            b.add_tool("box", half_extents=tuple(plate), name=f"{row}_plate_{'xz'[axis // 2]}{'_plus' if sign > 0 else '_minus'}",
                       motion=tools.Keyframes([0.0, FIG8_RELEASE, FIG8_RELEASE + 0.02], [start, end, start + sign * 0.1 * np.eye(3)[axis]]))
    frames = round(FIG8_DURATION * FIGURE_FPS)
    return Scene("lab_fig8_plates", _doc(lab_fig8_plates), b, frames=frames, fps=FIGURE_FPS, view=(0.0, 50.0))


#: Built-in scenes by name: the everyday scenes, then one per figure of the paper.
SCENES: dict[str, Callable[..., Scene]] = {
    "dough_drop": dough_drop,
    "star": star,
    "rubber_bounce": rubber_bounce,
    "clay_on_sphere": clay_on_sphere,
    "three_cylinders": three_cylinders,
    "lab_compression": lab_compression,
    "lab_squeeze_flow": lab_squeeze_flow,
    "lab_indentation": lab_indentation,
    "lab_three_point_bending": lab_three_point_bending,
    "lab_cantilever": lab_cantilever,
    "lab_cutting": lab_cutting,
    "lab_fig8_plates": lab_fig8_plates,
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


def _unknown(name, file: str | None = None) -> ValueError:
    """``file``: a scene file the user may have meant (``name`` and ``.toml``, found here)."""
    close = difflib.get_close_matches(str(name), SCENES, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    if file is not None:
        hint += f"; the scene file {file!r} is here: give its path, {file!r}"
    return ValueError(f"scene = {checks.shorten(name)!r} is not allowed: unknown scene{hint}; the built-in scenes are {', '.join(SCENES)}, "
                      f"or give the path of a .toml scene file")


def get_scene(name: str = DEFAULT_SCENE, scale: float = 1.0) -> Scene:
    """The built-in scene ``name`` at ``scale`` (a refusal only the scale causes names it; a
    scale at which a body is under-resolved is refused, ``unresolved_bodies``)."""
    if not isinstance(name, str) or name not in SCENES:
        raise _unknown(name)
    return load_scaled_scene(name, scale, "scale")


def load_scene(name_or_path: str | os.PathLike | None = None, scale: float = 1.0) -> Scene:
    """A built-in scene by name, or a scene file (``.toml``) by path; ``None``: the default. A
    refusal that only the scale causes names ``scale`` (``load_scaled_scene``)."""
    return load_scaled_scene(name_or_path, scale, "scale")


def _load(name_or_path, scale) -> Scene:
    if name_or_path is None:
        name_or_path = DEFAULT_SCENE
    if not isinstance(name_or_path, (str, bytes, os.PathLike)):
        # 3 or a list met a TypeError from os.fspath, naming no parameter.
        raise ValueError(f"scene = {checks.shorten(name_or_path)!r} is not allowed: must be a built-in scene name or the path of a .toml "
                         "scene file")
    text = os.fsdecode(name_or_path)  # a path in bytes failed at str.endswith
    if text in SCENES:
        return SCENES[text](scale=scale)
    if text.lower().endswith(".toml") or os.sep in text or (os.altsep and os.altsep in text) or os.path.exists(text):
        stem = text[:-len(".toml")] if text.lower().endswith(".toml") else None
        if stem in SCENES and not os.path.exists(text):
            # 'run dough_drop.toml' read as a file nobody wrote: the built-in scene is named bare.
            try:
                return load_scene_file(text, scale)
            except ValueError as e:
                raise ValueError(f"{e}; {stem!r} is a built-in scene: give its name alone, {stem!r}") from None
        return load_scene_file(text, scale)
    # A bare name is a built-in scene's; a file is read by its path alone.
    raise _unknown(text, text + ".toml" if os.path.isfile(text + ".toml") else None)


def load_scaled_scene(name_or_path: str | os.PathLike | None, scale: float, what: str = "--scale",
                      resolution: bool = True) -> Scene:
    """``load_scene(name_or_path, scale)``, with a refusal that only the scale causes named as
    ``what``'s (the option or setting that gave it).

    A scale far from 1 makes the spacing absurd (``--scale 1e-300``: a spacing of 5e+298 m),
    and the scene's own checks then blamed a body ('it is smaller than the spacing 5e+298')
    or its centre: where the scene builds at scale 1, the fault is the scale's.

    A scene with an under-resolved body (``unresolved_bodies``: a body one particle layer
    thick) is refused naming the body, ``what`` and the smallest scale above ``scale`` that
    resolves it; it builds the model once on the CPU, in float64, to read its rest
    neighbourhoods, without the rest density and the overlap check it does not read (measured on
    2 busy cores: 0.34-0.46 s for Fig. 1's 52,309 particles at scale 1, 0.64-0.71 s for Fig. 7's
    73,002, where the whole model took 0.62-0.80 s and 1.13-1.44 s). Where Warp has not started, it starts here as ``init_warp()`` starts it, printing
    nothing; the check's kernel loads print nothing either, and ``wp.config.log_level`` is left
    as the caller had it. ``resolution=False`` leaves that check, the first to launch a kernel,
    to the caller (``refuse_unresolved``), which reads its own inputs against the scene first
    (``warp-esph fit``'s targets).
    """
    try:
        scene = _load(name_or_path, scale)
    except ScaleRefused as e:
        raise ValueError(e.message(what)) from None
    except ValueError as e:
        try:
            scale_ok = _scale(scale) != 1.0
        except ValueError:
            raise e from None  # the scale's own refusal (NaN, 0, text), as given
        if not scale_ok:
            raise
        try:
            _load(name_or_path, 1.0)
        except Exception:  # noqa: BLE001 (the scene's own fault: its error, as given at this scale)
            raise e from None
        scene = os.fsdecode(DEFAULT_SCENE if name_or_path is None else name_or_path)
        raise ValueError(f"{what} = {scale:g} is not allowed for {scene}: it builds at {what} 1, but with its spacing "
                         f"divided by {scale:g}: {e}; give a {what} nearer 1") from None
    if resolution:
        refuse_unresolved(scene, name_or_path, scale, what)
    return scene


#: A body whose rest fit the guards of paper §4 skip (too few neighbours, or a neighbourhood
#: too flat for a 3-D fit) for more than this share of its particles is under-resolved: its
#: deformation is not computed where it is skipped, so it answers nonsense without failing. A
#: body one particle layer thick loses every particle (the squeeze-flow disc at scale 0.3, the
#: star at 0.3, Fig. 3's discs at 0.4: 100 %); lattice bodies of two or more layers lose none;
#: coarse meshes a few corners (Fig. 1's bear at scale 0.1: 14 %, Fig. 4's bunny: 10 %).
UNRESOLVED_SHARE = 0.25
#: ``load_scaled_scene`` looks for the smallest scale that resolves a refused scene in steps of this.
SCALE_STEP = 0.05
#: ... up to this many times the scale given, and no further than this many times the particles
#: of the scene refused (plus 1000): a body one layer thick needs twice the scale, eight times
#: the particles of a slab (the squeeze-flow disc: 3.3 times, 0.3 to 0.4), and each scale tried
#: builds the model.
SCALE_SEARCH = (4.0, 8.0)
#: ... trying at most this many scales.
SCALE_TRIES = 40


def unresolved_bodies(builder: SceneBuilder) -> list[tuple[str, int, int, int]]:
    """``(name, skipped, particles, layers)`` of each body of ``builder`` whose rest fit the guards of
    paper §4 (``Solver``'s defaults) skip for more than ``UNRESOLVED_SHARE`` of its particles;
    ``layers``: the particle layers across its thinnest side (of its bounding box)."""
    import warp as wp  # noqa: PLC0415

    from .startup import init_warp  # noqa: PLC0415

    # get_scene is often a script's first Warp call: started here, Warp printed its banner, the
    # missing-CUDA note and a line per kernel module loaded, none of it asked for. Warp starts
    # quietly (init_warp) and the check's own loads are quiet; the caller's level comes back.
    level = wp.config.log_level
    try:
        init_warp(log_level=max(level, wp.LOG_WARNING))
        try:
            # float64: a scene float32 cannot hold (a mesh tool far out) runs with --dtype float64,
            # and its refusal is finalize's, with the dtype asked for.
            model = finalize_worlds([builder], device="cpu", dtype=wp.float64, _guards_only=True)
        except ValueError:
            return []  # refused where the scene's model is built, in the caller's words
        model.rest_neighbors()
        held = model.rest_guard.numpy() != 0
    finally:
        wp.config.log_level = level
    x0 = model.particle_x0.astype(np.float64)
    out = []
    for b in model.bodies:
        skipped = int(np.count_nonzero(held[b.start:b.start + b.count]))
        if skipped > UNRESOLVED_SHARE * b.count:
            span = np.ptp(x0[b.start:b.start + b.count], axis=0)
            out.append((b.name, skipped, b.count, int(round(float(span.min()) / model.spacing)) + 1))
    if out:
        try:
            builder._check_overlap()  # left out above: a scene it refuses is refused as finalize's
        except ValueError:
            return []
    return out


def refuse_unresolved(scene: Scene, name_or_path, scale: float, what: str):
    """Refuses ``scene`` (built at ``scale``) where a body is under-resolved (``unresolved_bodies``),
    naming the body, ``what`` and the smallest scale above ``scale`` (in ``SCALE_STEP``) that
    resolves every body: run, it would have skipped their deformation silently."""
    bad = unresolved_bodies(scene.builder)
    if not bad:
        return
    name, skipped, count, layers = bad[0]
    label = os.fsdecode(DEFAULT_SCENE if name_or_path is None else name_or_path)
    thick = f"it is {layers} particle layer{'s' if layers > 1 else ''} thick, and " if layers <= 2 else ""
    more = f" (and {len(bad) - 1} more {'body' if len(bad) == 2 else 'bodies'})" if len(bad) > 1 else ""
    # s: the last scale the search checked (a scale whose model would pass the particle bound is
    # not checked, and a refusal must not say it was).
    least, s, bound = None, scale, ""
    limit = SCALE_SEARCH[1] * scene.builder._count + 1000
    k = math.floor(scale / SCALE_STEP + 1e-9) + 1
    for k in range(k, k + SCALE_TRIES):
        if k * SCALE_STEP > SCALE_SEARCH[0] * scale + 1e-9:
            break
        trial_scale = round(k * SCALE_STEP, 10)
        try:
            trial = _load(name_or_path, trial_scale)
        except ValueError:
            continue
        if trial.builder._count > limit:
            bound = f" (at {trial_scale:g} it would hold {trial.builder._count} particles, past the search's bound of {limit:g})"
            break
        s = trial_scale
        if not unresolved_bodies(trial.builder):
            least = s
            break
    why = (f"body {name!r}{more} is under-resolved at spacing {scene.builder.spacing:.3g}: {thick}{skipped} of its {count} "
           "particles have too few neighbours, or too flat a neighbourhood, for the deformation fit (paper §4), which "
           "would skip them silently")
    spacing = scene.builder.spacing * scale  # the file's own
    if scale == 1.0 and label not in SCENES:
        # A scene file as written: its spacing is the fault, and the scale is the other way out.
        hint = (f"the largest spacing that resolves it is {spacing / least:.3g} ({what} {least:g})" if least is not None else
                f"no spacing down to {spacing / s:.3g} ({what} {s:g}) resolves it{bound}; give the body more particle layers")
        raise ValueError(f"{label}: [scene] spacing = {spacing:g} is not allowed: {why}; {hint}")
    hint = (f"the smallest {what} above {scale:g} that resolves it is {least:g}" if least is not None else
            f"no {what} up to {s:g} resolves it{bound}; give the body more particle layers" if s > scale else
            f"give a larger {what}, or the body more particle layers")
    raise ValueError(f"{what} = {scale:g} is not allowed for {label}: {why}; {hint}")
