"""``SceneBuilder``: bodies sampled on a lattice, materials, colliders → ``Model``.

Bodies are filled with particles on a cubic lattice of the builder's ``spacing``
(each particle stands for a ``spacing^3`` cube of material). Every value is checked
when it is given, so a mistake is reported where it was made.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import os
import warnings
from collections.abc import Sequence

import numpy as np
import warp as wp

from . import checks, meshes, tools
from ._types import scalar_type
from .sim.colliders import CONTACT_RAMP, MAX_PER_KIND, Box, Plane, Sphere
from .sim.fields import precision_problem as field_precision_problem
from .sim.neighbors import PAPER_MAX_NEIGHBORS, default_max_neighbors
from .sim.smoothing import DEFAULT_FIT_WEIGHT, FIT_WEIGHTS
from .material import Material, _following_force
from .meshes import lattice_counts, lattice_points
from .model import CONTACTS, FITS, Body, Model, check_contact_ramp, material_precision_problem, wider_precision

#: Allowed support radius, in units of the spacing. Below 1.5 dx an interior particle
#: sees only its 6 face neighbours; above 3 dx a particle has more than 120 neighbours
#: and a step costs several times more (docs/method.md §1).
SUPPORT_RANGE = (1.5, 3.0)
#: Largest lattice a single body may be sampled from (about 1.6 GB of float64 points).
MAX_PARTICLES_PER_BODY = 6.4e7
#: Largest neighbour list: every state holds particles x max_neighbors entries, and the
#: support (h <= 3 spacing) holds at most 122 lattice neighbours.
MAX_NEIGHBORS = 1024
#: Most tips of a star (the polygon test costs particles x tips).
MAX_STAR_POINTS = 1000
#: Most layers of a particle floor (``SceneBuilder.add_particle_floor``): a fit reaches at
#: most 3 spacings, so more layers only cost particles.
MAX_FLOOR_LAYERS = 8
#: Most column operations of a particle floor's footprint test (rows of the margin's disc x
#: columns of the grid; about 10 s of numpy): a margin of thousands of spacings is refused
#: before it stalls the builder.
MAX_FLOOR_WORK = 5e8


def _floor_layers(support_radius: float, spacing: float) -> int:
    """A particle floor's default layer count: as many as the support reaches spacings, so the
    floor's top layer has a full neighbourhood."""
    return math.ceil(support_radius / spacing - 1e-9)


def star_polygon(outer_radius: float, inner_radius: float, points: int = 5) -> np.ndarray:
    """Vertices (2-D) of a star with ``points`` tips, the first tip on +x."""
    angles = np.pi * np.arange(2 * points) / points
    radii = np.where(np.arange(2 * points) % 2 == 0, outer_radius, inner_radius)
    return np.stack([radii * np.cos(angles), radii * np.sin(angles)], axis=1)


def _inside_polygon(p: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Even-odd rule for 2-D points ``p`` (N, 2) against a closed polygon."""
    inside = np.zeros(len(p), dtype=bool)
    x, y = p[:, 0], p[:, 1]
    for a, b in zip(poly, np.roll(poly, -1, axis=0)):
        crosses = (a[1] > y) != (b[1] > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xc = a[0] + (y - a[1]) * (b[0] - a[0]) / (b[1] - a[1])
        inside ^= crosses & (x < xc)
    return inside


_AXES = {"x": 0, "y": 1, "z": 2}


#: The shape options of each tool shape (``add_tool``); the others are refused.
_TOOL_SHAPE_OPTIONS = {"plane": ("normal",), "box": ("half_extents",), "sphere": ("radius",),
                       "capsule": ("radius", "half_height"), "cylinder": ("radius", "half_height"),
                       "mesh": ("mesh", "scale", "prim_path")}


def _float32_resolves_margin(reach: float, spacing: float) -> bool:
    """Whether float32, which Warp's mesh queries use in either precision, resolves half the
    contact's margin (a thousandth of ``spacing``) at coordinates up to ``reach`` m: a box
    mesh the particles met 130 m from its origin (placed back by its position) at spacing
    0.02, float64, put a block landing on it the margin inside it (the inside test's axis
    rays, run along the top face, hit the side faces' top edges from within), 1000 m out in
    41 of 400 steps, 10 km out in 120 and it ended there; measured wrong where float32
    resolves 0.78 of the margin and coarser, right at 0.67 (112 m) and finer: refused from a
    half. Measured since: it is where they meet that counts, not how far the mesh reaches: a
    floor 400 m (and 4 km) across about its origin under a block at its middle, 0 steps of
    2000 wrong; a small mesh met 100 m up, 128 of 3000."""
    return reach * float(np.finfo(np.float32).eps) <= 0.5 * tools.CONTACT_MARGIN * spacing


def _margin_unresolved(reach: float, spacing: float) -> str:
    margin = tools.CONTACT_MARGIN * spacing
    return (f"resolves {reach * float(np.finfo(np.float32).eps):.2g} m, more than half the contact's margin {margin:.2g} m "
            f"(a thousandth of the spacing {spacing:g}): particles that touch it would be put inside it")


#: What a body may be (``Body.kind``): given particles, or the shape of an ``add_*``.
BODY_KINDS = ("particles", "box", "sphere", "cylinder", "star", "mesh")


class SceneBuilder:
    """Collects bodies and colliders; ``finalize`` makes the ``Model``.

    ``spacing`` is the lattice spacing dx (m); ``support_radius`` the neighbourhood
    radius h (default 2 dx); ``gravity`` in m/s^2 (Y is up, as in Warp's assets and USD).

    ``max_neighbors`` is the width of a neighbour row. The default (None) is
    ``neighbors.default_max_neighbors(h / dx)`` (96 at h = 2 dx, 240 at 2.5 dx), wide enough
    that no row is cut in practice, so the loss is smooth in the parameters; ``"paper"``
    is the paper's width, 30 (``PAPER_MAX_NEIGHBORS``): the 30 nearest where rows reach ``h``;
    where they reach ``h sigma_max(F)`` (the paper's elastic force, the hourglass control, a
    comparison model) the 30 of smallest ``neighbors.weight_key``, the pairs a kernel weighs
    first, not the 30 nearest. A row that is cut is counted in
    ``Solver.guard_counts()["neighbors_cut"]`` (docs/method.md §1).

    ``fit`` and ``contact_ramp`` become the model's ``Model.fit`` (the incremental fit a
    ``Solver`` runs by default; None: ``Model.fit``'s default) and ``Model.contact_ramp`` (``contact=`` names it: one of
    ``model.CONTACTS``, "continuous", the default, or "instant"); ``hourglass`` the model's
    ``Model.hourglass`` (the strength of the hourglass control a ``Solver`` runs by default; 0:
    off; None: by the fit, ``Model.solver_choice``). Scene files set them in ``[solver]``.

    ``fit_weight`` is the model's ``Model.fit_weight``, the weights of the incremental fit
    (``smoothing.FIT_WEIGHTS``): ``"biweight"`` (the default), which keeps a flowing material's
    stress through large strain nearer the continuum's (docs/physics.md, "The fit's weight"), or
    ``"poly6"``, the paper's eq. 7.
    """

    def __init__(
        self,
        spacing: float = 0.02,
        gravity: Sequence[float] = (0.0, -9.81, 0.0),
        support_radius: float | None = None,
        max_neighbors: int | str | None = None,
        bodies_interact: bool = True,
        *,
        fit: str | None = None,
        contact: str | None = None,
        contact_ramp: float = CONTACT_RAMP,
        hourglass: float | None = None,
        fit_weight: str = DEFAULT_FIT_WEIGHT,
    ):
        spacing = checks.positive("spacing", spacing)
        self._spacing = spacing
        # The support radius (up to SUPPORT_RANGE[1] spacings) and the ratios read from it must be
        # finite: at 1e308 they overflowed to inf and the neighbour cap raised OverflowError.
        widest = float(np.finfo(np.float64).max) / SUPPORT_RANGE[1]
        if spacing > widest:
            raise ValueError(f"spacing = {checks.shorten(spacing)!r} is not allowed: must be at most {widest:.3g} (the support radius, up "
                             f"to {SUPPORT_RANGE[1]:g} spacings, must be a finite number)")
        # Below what finalize's precision check takes even in float64: at 1e-320 the coincidence
        # check's cell underflowed to 0, and two particles two spacings apart were refused as one.
        narrowest = float(np.finfo(np.float64).tiny) ** (1 / 9) / SUPPORT_RANGE[0]
        if spacing < narrowest:
            raise ValueError(f"spacing = {checks.shorten(spacing)!r} is not allowed: must be at least {narrowest:.2g} (the kernels' "
                             f"constants, 1 / h^9 of a support radius of at least {SUPPORT_RANGE[0]:g} spacings, must fit "
                             "float64)")
        self.fit_weight = fit_weight
        self.fit = fit
        if contact is not None:
            if contact_ramp != CONTACT_RAMP:
                raise ValueError(f"contact = {contact!r} and contact_ramp = {contact_ramp!r} are not allowed together: give one")
            contact_ramp = CONTACTS[checks.choice("contact", contact, tuple(CONTACTS))]
        self.contact_ramp = contact_ramp
        self.hourglass = hourglass
        self.bodies_interact = bodies_interact
        self.gravity = gravity
        # The max_neighbors given (None: the default, which follows the support radius).
        self._max_neighbors_given = None
        # The particle floors of the default layer count, ceil(support_radius / spacing) when
        # added: their pin's name -> (layers, the support radius then), which the support_radius
        # setter keeps them enough for.
        self._default_floors: dict[str, tuple[int, float]] = {}
        self.support_radius = support_radius
        self.max_neighbors = max_neighbors
        self._points: list[np.ndarray] = []
        self._velocities: list[np.ndarray] = []
        self._bodies: list[Body] = []
        self._materials: list[Material] = []
        self._material_ids: list[np.ndarray] = []
        self.planes: list[Plane] = []
        self.spheres: list[Sphere] = []
        self.boxes: list[Box] = []
        self.force_fields: list = []
        self.tools: list[tools.Collider] = []
        self.pins: list[tools.PinSet] = []
        self._count = 0
        self._floors: set[str] = set()
        #: The scene file this builder was read from (``load_scene_file``; None: built in
        #: Python), and where in it each part was given: ``("scene",)``, ``("material", k)``,
        #: ``("body", k)``, ``("plane" | "sphere" | "box", k)``, ``("tool" | "pin", name)`` ->
        #: its table (``"[[bodies]] #2 (shape 'box')"``). ``finalize`` checks the precision only
        #: then, and a refusal names the file and the key, as the loader's own do.
        self.source: str | None = None
        self.origins: dict[tuple, str] = {}

    # ----------------------------------------------------------------- bodies
    def _center(self, center) -> np.ndarray:
        """A body's centre, near enough to the origin that float64 still resolves the lattice
        there (a thousandth of the spacing): a centre at 1e300 collapsed every lattice point
        onto one and was reported as a body smaller than the spacing."""
        c = np.array(checks.vector("center", center))
        far = self._far()
        if np.abs(c).max() > far:
            raise ValueError(f"center = {checks.shorten(tuple(center))!r} is not allowed: must be within {far:.3g} of the origin "
                             f"(farther out float64 does not resolve the spacing {self.spacing:g})")
        return c

    def _far(self) -> float:
        """How far from the origin float64 still resolves a thousandth of the spacing."""
        return self.spacing * 1e-3 / float(np.finfo(np.float64).eps)  # inf past 4e302, without numpy's overflow warning

    def _lattice(self, lo, hi, name: str, value) -> np.ndarray:
        self._check_lattice_size(lo, hi, name, value)
        return lattice_points(lo, hi, self.spacing)

    def _check_lattice_size(self, lo, hi, name: str, value):
        # Refuse before allocating: a typo in a size must not exhaust memory.
        with np.errstate(over="ignore"):  # a product past the float range is inf: refused below, no numpy warning
            cells = np.prod(lattice_counts(lo, hi, self.spacing))
        if cells > MAX_PARTICLES_PER_BODY:
            raise ValueError(
                f"{name} = {checks.shorten(value)!r} is not allowed: at spacing {self.spacing:g} the body would need {cells:.3g} "
                f"lattice cells, more than {MAX_PARTICLES_PER_BODY:.3g}"
            )

    def _material_index(self, material: Material) -> int:
        if not isinstance(material, Material):
            raise ValueError(f"material = {checks.shorten(material)!r} is not allowed: must be a warp_esph.Material")
        for k, m in enumerate(self._materials):
            if m is material:
                return k
        self._materials.append(material)
        return len(self._materials) - 1

    def add_particles(self, positions, material: Material, velocity=(0.0, 0.0, 0.0), name: str | None = None, kind: str = "particles", angular_velocity=(0.0, 0.0, 0.0)) -> int:
        """Adds a body made of the given particle positions (N, 3); returns its index.

        Every ``add_*`` takes ``velocity`` (3 numbers, or one per particle) and
        ``angular_velocity`` (rad/s, about the body's centroid): the body starts with
        ``velocity + angular_velocity x (x - centroid)``.

        ``kind``: what the body is, one of ``BODY_KINDS`` (``Body.kind``; the ``add_*`` shapes
        pass their own): it names an unnamed body (``box0``) and is kept in a checkpoint's
        record of the bodies.
        """
        # Any text was kept (kind='xx' named the body 'xx0'; kind=3, '30').
        kind = checks.choice("kind", kind, BODY_KINDS)
        positions = checks.host_values("positions", positions)
        velocity = checks.host_values("velocity", velocity)
        try:
            raw = np.asarray(positions)
        except (TypeError, ValueError):  # ragged rows
            raw = np.asarray(None)
        # Complex values lost their imaginary parts (numpy warned); text and objects failed later.
        if raw.dtype.kind not in "iuf":
            what = checks.shorten(positions) if raw.dtype.kind == "O" else f"<{raw.dtype} array>"
            raise ValueError(f"positions = {what!s} is not allowed: must be an (N, 3) array of real numbers")
        pts = raw.astype(np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"positions with shape {pts.shape} is not allowed: must be (N, 3)")
        if name is None:
            # The first free one from the body's index: a body named 'box1' by its caller made
            # the next unnamed box's default ('box1') a clash the caller never wrote.
            taken, k = {b.name for b in self._bodies}, len(self._bodies)
            while f"{kind}{k}" in taken:
                k += 1
            name = f"{kind}{k}"
        if not isinstance(name, str) or not name:
            raise ValueError(f"name = {checks.shorten(name)!r} is not allowed: must be a non-empty string")
        checks.one_line("name", name, "it names the body in messages, in the USD file and in a sweep's --param")
        if name in (b.name for b in self._bodies):
            raise ValueError(f"name = {checks.shorten(name)!r} is not allowed: a body of that name exists already")
        if len(pts) == 0 and kind == "particles":
            # The shapes' words ('it is smaller than the spacing') for positions given as none.
            raise ValueError(f"positions with shape {pts.shape} is not allowed: body {name!r} would have no particles; give "
                             "at least one position")
        if len(pts) == 0:
            raise ValueError(f"body {name!r} has no particles: it is smaller than the spacing {self.spacing:g}")
        if not np.isfinite(pts).all():
            raise ValueError(f"positions of body {name!r} are not allowed: they must be finite")
        count, i = checks.coincident_points(pts, self.spacing)
        if count:
            raise ValueError(f"positions of body {name!r} are not allowed: {count} particles "
                             f"coincide with another (first at {np.round(pts[i], 6).tolist()}); each particle needs "
                             "a place of its own")
        try:
            per_particle = np.ndim(velocity) == 2
        except checks.ARRAY_ERRORS:  # ragged rows: refused below
            per_particle = False
        if per_particle:  # (one velocity's entries are refused by name below)
            checks.real_numbers("velocity", velocity, "must be 3 numbers or one row of 3 per particle")
        try:
            vel = np.asarray(velocity, dtype=np.float64)
        except (TypeError, ValueError, OverflowError):  # a dict, a generator, text, an int beyond a float (10**400)
            raise ValueError(f"velocity = {checks.shorten(velocity)!r} is not allowed: must be 3 numbers or one row "
                             f"of 3 per particle") from None
        if vel.shape == (3,):
            vel = np.broadcast_to(checks.vector("velocity", velocity), pts.shape)
        elif vel.shape != pts.shape or not np.isfinite(vel).all():
            raise ValueError(f"velocity with shape {vel.shape} is not allowed: must be 3 finite numbers or one per particle")
        omega = np.array(checks.vector("angular_velocity", angular_velocity))
        if omega.any():
            vel = vel + np.cross(omega, pts - pts.mean(axis=0))
        mat = self._material_index(material)
        self._points.append(pts)
        self._velocities.append(np.array(vel, dtype=np.float64))
        self._material_ids.append(np.full(len(pts), mat, dtype=np.int32))
        self._bodies.append(Body(name=name, start=self._count, count=len(pts), material=mat, kind=kind))
        self._count += len(pts)
        return len(self._bodies) - 1

    def add_box(self, center, size, material: Material, velocity=(0.0, 0.0, 0.0), name: str | None = None, angular_velocity=(0.0, 0.0, 0.0)) -> int:
        """A solid box of full edge lengths ``size`` centred at ``center``."""
        c = self._center(center)
        s = np.array(checks.positive_vector("size", size))
        return self.add_particles(self._lattice(c - s / 2, c + s / 2, "size", size), material, velocity, name, "box", angular_velocity)

    def add_sphere(self, center, radius: float, material: Material, velocity=(0.0, 0.0, 0.0), name: str | None = None, angular_velocity=(0.0, 0.0, 0.0)) -> int:
        """A solid ball of ``radius`` centred at ``center``: the lattice points within it."""
        c = self._center(center)
        r = checks.positive("radius", radius)
        p = self._lattice(c - r, c + r, "radius", radius)
        return self.add_particles(p[np.linalg.norm(p - c, axis=1) <= r], material, velocity, name, "sphere", angular_velocity)

    def add_cylinder(self, center, radius: float, height: float, material: Material, axis: str = "y",
                     velocity=(0.0, 0.0, 0.0), name: str | None = None, angular_velocity=(0.0, 0.0, 0.0)) -> int:
        """A solid cylinder of ``radius`` and ``height`` along ``axis`` ('x', 'y' or 'z')."""
        c = self._center(center)
        r = checks.positive("radius", radius)
        hgt = checks.positive("height", height)
        a = _AXES[checks.choice("axis", axis, tuple(_AXES))]
        half = np.full(3, r)
        half[a] = hgt / 2
        p = self._lattice(c - half, c + half, "radius/height", (radius, height))
        radial = np.delete(p - c, a, axis=1)
        return self.add_particles(p[np.linalg.norm(radial, axis=1) <= r], material, velocity, name, "cylinder", angular_velocity)

    def add_star(self, center, outer_radius: float, inner_radius: float, thickness: float, material: Material,
                 points: int = 5, velocity=(0.0, 0.0, 0.0), name: str | None = None, angular_velocity=(0.0, 0.0, 0.0)) -> int:
        """An extruded star lying flat (extruded along y), the paper's dough shape (Fig. 6)."""
        c = self._center(center)
        ro = checks.positive("outer_radius", outer_radius)
        ri = checks.positive("inner_radius", inner_radius)
        if ri >= ro:
            raise ValueError(f"inner_radius = {checks.shorten(inner_radius)!r} is not allowed: must be < outer_radius = {ro:g}")
        t = checks.positive("thickness", thickness)
        npts = checks.positive_int("points", points, maximum=MAX_STAR_POINTS, minimum=3)
        p = self._lattice(c - np.array([ro, t / 2, ro]), c + np.array([ro, t / 2, ro]), "outer_radius/thickness", (ro, t))
        inside = _inside_polygon((p - c)[:, [0, 2]], star_polygon(ro, ri, npts))
        return self.add_particles(p[inside], material, velocity, name, "star", angular_velocity)

    def add_mesh(self, source, material: Material, *, scale: float = 1.0, translation=(0.0, 0.0, 0.0),
                 velocity=(0.0, 0.0, 0.0), name: str | None = None, prim_path: str | None = None, angular_velocity=(0.0, 0.0, 0.0)) -> int:
        """A closed triangle mesh filled with particles (winding-number inside test).

        ``source`` is a file (anything meshio reads, or ``.usd/.usda/.usdc``) or a tuple
        ``(points, triangles)``; ``prim_path`` names a USD file's Mesh prim (without it, the
        stage's only one, or the only one it shows: ``meshes.load_mesh``). The mesh is scaled
        by ``scale`` then moved by ``translation``; placed, its points must lie as near the
        origin as a body's ``center`` (float64 resolving a thousandth of the spacing).

        The body's default name is a file's name without its extension (``'bunny'``; then
        ``'bunny_1'``, ``'bunny_2'``, ... when it is taken), or ``mesh<index>`` for a tuple.
        """
        s = checks.positive("scale", scale)
        t = checks.vector("translation", translation)
        points, triangles = meshes.load_mesh(source, prim_path=prim_path)
        is_file = meshes._is_path(source)
        label = repr(os.fsdecode(os.fspath(source))) if is_file else "(points, triangles)"
        with np.errstate(over="ignore", invalid="ignore"):
            points = points * s
        if not np.isfinite(points).all():
            raise ValueError(f"scale = {checks.shorten(scale)!r} is not allowed for mesh {label}: it takes the mesh's "
                             f"points beyond a float64")
        # Named by what made the mesh large: the scale given, or the mesh's own extent. Sized
        # before it is moved: far out, float64 rounds the extent itself.
        extent = tuple(float(v) for v in points.max(axis=0) - points.min(axis=0))
        self._check_lattice_size(points.min(axis=0), points.max(axis=0), *(
            ("scale", scale) if scale != 1.0 else ("the mesh's extent (scale 1)", checks.shorten(extent))))
        # Where it is placed, not the translation alone: a mesh modelled far from its origin
        # may be moved back. Beyond reach the lattice collapsed and the spacing was blamed.
        with np.errstate(over="ignore", invalid="ignore"):
            points = points + np.array(t)
        reach, far = float(np.abs(points).max()), self._far()
        if not reach <= far:
            # Named by what put it there: the translation given, or the mesh's own coordinates.
            what = (f"translation = {checks.shorten(t)!r} is not allowed for mesh {label}: it places the mesh's points" if any(t) else
                    f"mesh {label} is not allowed: its points (scale {s:g}, no translation) lie")
            raise ValueError(f"{what} up to {reach:.3g} m from the origin; they must be within {far:.3g} m (farther out "
                             f"float64 does not resolve the spacing {self.spacing:g}); pass a translation that brings them nearer")
        inside = meshes.sample_inside(points, triangles, self.spacing)
        if name is None and is_file:
            # Unique as every default name is: a second body of one file was refused for the
            # first one's name.
            taken = {b.name for b in self._bodies}
            # A file's name may hold a newline; as a default the name only labels, so it is cleaned.
            stem = name = checks.one_line_label(meshes.mesh_name(source))
            k = 1
            while name in taken:
                name, k = f"{stem}_{k}", k + 1
        return self.add_particles(inside, material, velocity, name, "mesh", angular_velocity)

    def add_particle_floor(self, body, *, margin: float | None = None, layers: int | None = None, where=None, name: str | None = None,
                           elastic: bool = False, ghost: bool = False, slip: bool = False) -> str:
        """A rough floor that enters the fits: ``layers`` lattice layers of ``body``'s own
        particles under it, pinned (``pin``); returns the pin's name (default ``"<body>_floor"``).

        ``body`` (a name, or the index an ``add_*`` returned) must be the body added last: the
        floor particles are appended to it, so they are in every fit of its particles (a
        floor of another body, or the ground collider, is not: the bottom layer's fit is
        then one-sided, docs/physics.md, thin layers in shear). The floor lies under the
        body along -y (Y is up), its top layer one spacing below the body's lowest particle,
        on the body's lattice (that of its lowest particle), under every column within
        ``margin`` (m, horizontally) of one of the body's columns: the footprint plus a
        margin wide enough for the material to spread on. ``layers`` defaults to
        ``ceil(support_radius / spacing)`` (2 at the default h = 2 dx): the floor's top layer
        then has a full neighbourhood too. ``where``, a predicate on the floor positions
        ``(N, 3) -> bool (N,)``, keeps only some of them (e.g. a disc).

        The floor's particles are of the body's material, so they flow plastically with the
        material sheared over them, and the base yields as the material's interior would.
        ``elastic=True`` makes them of the body's material made elastic (``yield_stress =
        inf``, otherwise the same; added to the model's materials after the body's and named
        in ``Body.floor_material``; a fit of every material or of the body's, and
        ``Model.set_material`` of the body's material, leave it as built): a floor the
        material sticks to. It holds the material within a support radius of it, about two
        layers at the default h = 2 dx: a strip three particles thick on a slope at 1.3 x
        its shear yield stress does not slide on it (on the plastic floor it flows), and a
        slumping cylinder rests higher than on the plastic floor, as a continuum pile does
        on a no-slip floor at a coarse grid (docs/physics.md, "The floor's plasticity").

        ``ghost=True`` makes it a no-slip wall on the plane halfway between the floor's top
        layer and the body's lowest layer, holding no layer of material: in the fits the
        floor's particles move as the odd continuation of the material's motion across
        that plane, and they carry no energy of their own (``warp_esph/sim/ghost_floor.py``;
        docs/physics.md, "The no-slip ghost floor"). With ``slip=True`` (ghost floors only) the
        ghosts continue the motion evenly along the plane and oddly across it: a frictionless
        wall that the material slides on without crossing (the SPH viscosity against the floor's
        particles still acts). The solver then runs the non-fused kernels, with the paper's
        linear fit and the variational elastic force only."""
        names = [b.name for b in self._bodies]
        k = self._body_index(body)
        bd = self._bodies[k]
        if k != len(self._bodies) - 1:
            raise ValueError(f"body = {checks.shorten(body)!r} is not allowed: a particle floor grows its body, so it must be the body "
                             f"added last ({names[-1]!r}); add the floor right after the body")
        if bd.name in self._floors:
            raise ValueError(f"body = {checks.shorten(body)!r} is not allowed: it has a particle floor already")
        dx = self.spacing
        if margin is None:  # a required keyword: its absence was a TypeError
            raise ValueError("margin is required: the floor's reach beyond the body's columns (m, horizontally), "
                             "e.g. margin=2 * spacing")
        m = checks.non_negative("margin", margin) / dx
        default_layers = layers is None
        if default_layers:
            layers = _floor_layers(self.support_radius, dx)
        layers = checks.positive_int("layers", layers, maximum=MAX_FLOOR_LAYERS)
        if where is not None and not callable(where):
            raise ValueError(f"where = {checks.shorten(where)!r} is not allowed: must be callable as where(floor_positions) -> bool array")
        if not isinstance(elastic, bool):
            raise ValueError(f"elastic = {checks.shorten(elastic)!r} is not allowed: must be True or False")
        if not isinstance(ghost, bool):
            raise ValueError(f"ghost = {checks.shorten(ghost)!r} is not allowed: must be True or False")
        if not isinstance(slip, bool):
            raise ValueError(f"slip = {checks.shorten(slip)!r} is not allowed: must be True or False")
        if slip and not ghost:
            raise ValueError("slip = True is not allowed without ghost = True: only a ghost floor can let the material slide")
        if ghost and elastic:
            raise ValueError("elastic = True is not allowed with ghost = True: a ghost floor carries no energy of its own, "
                             "so it has no material to make elastic")
        name = f"{bd.name}_floor" if name is None else name
        self._check_tool_name(name)
        pts = self._points[-1]
        ref = pts[np.argmin(pts[:, 1])]
        cols = np.round((pts[:, [0, 2]] - ref[[0, 2]]) / dx).astype(np.int64)
        # Sizes in floats first: a margin of 1e300 m must be refused, not overflow an integer.
        # A margin near the float range over a spacing below 1 m is inf spacings: math.floor(inf) raised OverflowError.
        reach_f = math.floor(m + 1e-9) * 1.0 if math.isfinite(m) else math.inf
        span = [float(c) + 1.0 + 2.0 * reach_f for c in cols.max(axis=0) - cols.min(axis=0)]
        if span[0] * span[1] * layers > MAX_PARTICLES_PER_BODY:
            raise ValueError(f"margin = {checks.shorten(margin)!r} is not allowed: at spacing {dx:g} the floor would need "
                             f"{span[0] * span[1] * layers:.3g} particles, more than {MAX_PARTICLES_PER_BODY:.3g}")
        work = (2.0 * reach_f + 1.0) * span[0] * span[1]
        if work > MAX_FLOOR_WORK:
            raise ValueError(f"margin = {checks.shorten(margin)!r} is not allowed: at spacing {dx:g} it reaches {reach_f:.0f} spacings beyond "
                             f"the body, and the footprint test would take {work:.3g} column operations, more than {MAX_FLOOR_WORK:.3g}")
        reach = int(reach_f)
        lo, hi = cols.min(axis=0) - reach, cols.max(axis=0) + reach
        size = hi - lo + 1
        foot = np.zeros(size, dtype=bool)
        foot[cols[:, 0] - lo[0], cols[:, 1] - lo[1]] = True
        # Dilation by a disc of radius m columns: per row offset a, a running window of
        # half-width sqrt(m^2 - a^2) along z (cumulative sums), so the cost is rows x grid.
        under = np.zeros_like(foot)
        for a in range(-reach, reach + 1):
            w = int(math.floor(math.sqrt(max(m * m - a * a, 0.0)) + 1e-9))
            row = np.zeros_like(foot)
            if a >= 0:
                row[a:] = foot[:size[0] - a]
            else:
                row[:a] = foot[-a:]
            cs = np.cumsum(np.pad(row, ((0, 0), (w + 1, w))), axis=1)
            under |= (cs[:, 2 * w + 1:] - cs[:, :size[1]]) > 0
        # Ordered as a lattice_points box: x slowest, then y (upwards), then z.
        ix, iz = np.nonzero(under)
        cx, cz = ref[0] + dx * (ix + lo[0]), ref[2] + dx * (iz + lo[1])
        ys = ref[1] - dx * np.arange(layers, 0, -1)
        nc = len(ix)
        order = np.lexsort((np.tile(np.arange(nc), layers), np.repeat(np.arange(layers), nc), np.tile(ix, layers)))
        floor = np.stack([np.tile(cx, layers), np.repeat(ys, nc), np.tile(cz, layers)], axis=1)[order]
        if where is not None:
            floor = floor[checks.selection("where", where, floor, "floor_positions")]
        if len(floor) == 0:
            raise ValueError(f"where = {checks.shorten(where)!r} is not allowed: it keeps none of the floor's positions")
        start = self._count
        own = self._materials[bd.material]
        floor_material = bd.material
        if elastic and own.yield_stress != math.inf:
            # A force left to its default stays so, as the body's (dataclasses.replace alone
            # marked the resolved 'variational' as given).
            floor_material = self._material_index(dataclasses.replace(own, **_following_force(own, {"yield_stress": math.inf})))
        self._points[-1] = np.vstack([pts, floor])
        self._velocities[-1] = np.vstack([self._velocities[-1], np.zeros_like(floor)])
        self._material_ids[-1] = np.concatenate([self._material_ids[-1], np.full(len(floor), floor_material, dtype=np.int32)])
        self._bodies[-1] = dataclasses.replace(bd, count=bd.count + len(floor),
                                               floor_material=floor_material if floor_material != bd.material else -1,
                                               ghost_floor=len(floor) if ghost else 0,
                                               ghost_plane=float(ref[1] - 0.5 * dx) if ghost else 0.0, ghost_slip=slip)
        self._count += len(floor)
        self._floors.add(bd.name)
        pin = self.pin(indices=np.arange(start, self._count), name=name)
        self.pins[-1] = dataclasses.replace(self.pins[-1], floor=True)
        if default_layers:
            self._default_floors[pin] = (layers, self.support_radius)
        return pin

    # -------------------------------------------------------------- colliders
    def _add_collider(self, lst: list, item, kind: str):
        if len(lst) >= MAX_PER_KIND:
            raise ValueError(f"{kind} colliders = {len(lst) + 1} is not allowed: at most {MAX_PER_KIND} per kind")
        lst.append(item)

    def add_ground(self, height: float = 0.0, friction: float = 0.5, *, images: bool = False, shear_cap: float | None = None):
        """The plane y = ``height``, solid below; Coulomb ``friction`` >= 0.

        ``images=True``: the ground is also a rough floor of the material's fits: each
        particle within the support radius of it has, in its incremental fit and in the
        elastic force (the variational energy, or the paper's pairs), the mirror images of its
        neighbours below the plane, carrying a stress (their own, below)
        (the incremental fit; docs/physics.md, "The ground
        collider's thin-layer strength"). Without it a layer's bottom particles are held on
        the plane with a one-sided fit, and a thin layer is 2.25 x too strong in shear.
        Each image has an elastic F and a hardening of its own (``State.F_image``,
        ``alpha_image``): its own fit over the particles near it updates the F, which flows
        plastically as theirs does and advances its own hardening, so the work
        its energy does is stored and an undamped layer on it keeps its energy
        (docs/physics.md, "The floor images' energy is not stored").

        With ``friction > 0`` the images are at rest over each step in the fits, so a bottom
        layer sliding over them is sheared as on a floor at rest, and its stress pulls the body
        back: a rough floor whatever the friction (an elastic box thrown sideways on it swings
        about where it was; ``friction`` itself acts only where a particle touches the plane,
        and a body resting on the images stays off it, so its value does not grade the floor).
        With ``friction = 0`` the images move with their particles over each step (the
        mirror of each particle's displacement in the fits, of its velocity in the SPH
        viscosity): a frictionless floor, on which a body slides on (docs/physics.md, "The
        imaged ground is rough whatever its friction"). Its elastic energy within the support
        radius of the plane is half the particle's and half its image's, each image's F its
        own fit's, and every image's reaction reaches its particle through the image's motion,
        so the force is minus the gradient of the energy stored also where the images, below
        half a spacing, are no mirrors: an undamped body resting there keeps its energy but for
        the step's own error (docs/physics.md, "The frictionless imaged ground below half a
        spacing").

        ``shear_cap=K`` (``K >= 0``; None or 0: off), with ``images=True`` and ``friction=0``
        only: the Tresca ground. It holds each base particle tangentially up to ``K`` times its
        shear yield stress ``tau_y = Y / sqrt(2)`` (``Material.shear_yield_stress``) over the
        area ``V^(2/3)`` it stands for, ``Y = yield_stress + hardening * alpha`` the yield stress
        the plastic flow reads for it, of its ``alpha`` at the step's start (a particle whose
        softening has taken ``Y`` to 0 is not held at all): a particle
        whose centre starts a step within 0.75 spacings of the plane loses up to ``K tau_y
        V^(2/3) dt / m`` of its tangential speed (sticking below it), the hold fading with zero
        slope to none at 1.25 spacings (``sim/colliders.py``, ``tresca_traction``). ``K = 1`` is
        the continuum's floor that grips as the material's own yield strength (docs/physics.md,
        "The Tresca ground (built)"). Its traction is in the ground's reaction row. Refused
        beside a material without a ``shear_yield_stress`` (another model, a deformation other
        than the incremental one, or an infinite ``yield_stress``), whether or not that body
        touches the ground."""
        if not isinstance(images, bool):
            raise ValueError(f"images = {checks.shorten(images)!r} is not allowed: must be True or False")
        if images and any(p.images for p in self.planes):
            raise ValueError("images = True is not allowed twice: one ground may be a rough floor of the fits")
        y0, friction = checks.number("height", height), checks.non_negative("friction", friction)
        cap = 0.0 if shear_cap is None else checks.non_negative("shear_cap", shear_cap)
        if cap > 0.0 and not images:
            raise ValueError(f"shear_cap = {checks.shorten(shear_cap)!r} is not allowed with images = False: the hold "
                             "is the frictionless imaged ground's (add_ground(friction=0, images=True, shear_cap=K)); "
                             "a plain ground's grip is its friction")
        if cap > 0.0 and friction != 0.0:
            raise ValueError(f"shear_cap = {checks.shorten(shear_cap)!r} is not allowed with friction = "
                             f"{checks.shorten(friction)!r}: with friction > 0 the images stand still over each step, "
                             "a rough floor that already holds the base whatever the cap; give friction = 0")
        plane = Plane((0.0, 1.0, 0.0), y0, friction, images, cap)
        self._refuse_coincident(plane, f"add_ground(height = {checks.shorten(height)!r})")
        self._add_collider(self.planes, plane, "plane")

    def add_plane(self, normal, offset: float, friction: float = 0.5):
        """The half-space dot(normal, x) < offset is solid. ``normal`` need not be of unit
        length: both sides are divided by its length, so the plane stands ``offset / |normal|``
        from the origin (stored as a unit normal and that distance; a distance that overflows, a
        normal of subnormal length, is refused naming both)."""
        n = checks.unit_vector("normal", normal)
        raw = np.array(checks.vector("normal", normal))
        big = float(np.abs(raw).max())  # scaled first, as unit_vector does: no overflow in the norm
        distance = checks.number("offset", offset) / big / float(np.linalg.norm(raw / big))
        if not math.isfinite(distance):
            # A normal of subnormal length made a finite offset an infinite distance, refused at
            # finalize as 'offset = -inf ... use a smaller value', a value the caller never gave.
            raise ValueError(f"offset = {checks.shorten(offset)!r} is not allowed with normal = {checks.shorten(normal)!r}: "
                             f"the plane's distance from the origin, offset / |normal|, is {distance}, so it must be a "
                             "finite number; give a normal of about unit length")
        plane = Plane(n, distance, checks.non_negative("friction", friction))
        self._refuse_coincident(plane, f"add_plane(normal = {checks.shorten(normal)!r}, offset = {checks.shorten(offset)!r})")
        self._add_collider(self.planes, plane, "plane")

    def _refuse_coincident(self, plane: Plane, call: str) -> None:
        # Each plane responds to a particle in turn (sim/colliders.py): a second ground on the
        # first took a share of the touchdown the first had left and a reaction row of its own
        # (a block dropped sliding at 0.5 m/s ended 400 steps at 0.0134 m/s, on one ground 0.0166).
        # Equal up to rounding, not to the bit: the same plane by another multiple of its normal
        # ((0.3, 0.1, 0) for (3, 1, 0)) or a height computed in another order came out a unit in
        # the last place away and was taken as a second plane; a float32 model holds planes
        # that close as one. Within a few float32 units (offsets on the spacing's scale at least).
        tol = 1e-6
        for k, p in enumerate(self.planes):
            if (max(abs(a - b) for a, b in zip(p.normal, plane.normal)) <= tol
                    and abs(p.offset - plane.offset) <= tol * max(abs(p.offset), abs(plane.offset), self.spacing)):
                axes = [i for i in range(3) if p.normal[i] != 0.0]
                lhs = "xyz"[axes[0]] if len(axes) == 1 and p.normal[axes[0]] == 1.0 else f"{tuple(p.normal)} . x"
                raise ValueError(f"{call} is not allowed: it is plane{k}, the plane {lhs} = {p.offset:g} (friction "
                                 f"{p.friction:g}), again: each plane responds to a particle in turn, so the second "
                                 "took a share of the touchdown again and a reaction row of its own; add each plane once")

    def add_sphere_collider(self, center, radius: float, friction: float = 0.5):
        """A fixed solid sphere; Coulomb ``friction`` >= 0 (its reaction row is ``sphere<k>``)."""
        self._add_collider(
            self.spheres,
            Sphere(checks.vector("center", center), checks.positive("radius", radius), checks.non_negative("friction", friction)),
            "sphere",
        )

    def add_box_collider(self, center, half_extents, friction: float = 0.5):
        """A fixed axis-aligned solid box of ``half_extents`` about ``center``; Coulomb
        ``friction`` >= 0 (its reaction row is ``box<k>``)."""
        self._add_collider(
            self.boxes,
            Box(checks.vector("center", center), checks.positive_vector("half_extents", half_extents), checks.non_negative("friction", friction)),
            "box",
        )

    def _check_tool_name(self, name):
        """A tool's or pinned set's name: new, non-empty, and not one the static colliders'
        reaction rows use (``plane<k>``, ``sphere<k>``, ``box<k>``, ``Solver.collider_reactions``:
        the force log and ``ReactionForceLoss`` look both up by name)."""
        import re  # noqa: PLC0415

        if not isinstance(name, str) or not name:
            raise ValueError(f"name = {checks.shorten(name)!r} is not allowed: must be a new non-empty string")
        for what, items in (("tool", self.tools), ("pinned set", self.pins)):
            if name in [t.name for t in items]:
                # Said only 'must be a new non-empty string': a scene file's tool named like a
                # body's floor ('<body>_floor') clashed with a set the file never named.
                raise ValueError(f"name = {checks.shorten(name)!r} is not allowed: a {what} of that name exists already; tools and "
                                 "pinned sets share one set of names (the force log's rows)")
        checks.one_line("name", name, "it names the tool or pinned set in messages, in the force log's rows and in the "
                        "USD file")
        if re.fullmatch(r"(plane|sphere|box)[0-9]+", name):
            raise ValueError(f"name = {checks.shorten(name)!r} is not allowed: plane<k>, sphere<k> and box<k> name the static colliders' "
                             f"reaction rows; choose another name")

    def add_tool(self, shape: str, *, motion=None, position=(0.0, 0.0, 0.0), orientation=tools.IDENTITY,
                 friction: float = 0.0, static_friction: float | None = None, name: str | None = None,
                 normal=None, half_extents=None, radius=None, half_height=None, mesh=None, scale: float = 1.0,
                 prim_path: str | None = None) -> str:
        """A moving rigid collider (``tools.py``); returns its name.

        ``shape``: ``"plane"`` (through the tool's origin, ``normal`` in its frame; solid
        below), ``"box"`` (``half_extents``), ``"sphere"`` (``radius``), ``"capsule"`` and
        ``"cylinder"`` (``radius``, ``half_height``, along the tool's y axis) or ``"mesh"``
        (``mesh``: a file meshio or USD reads, or ``(points, triangles)``, closed, in the
        tool's frame, times ``scale``, where the particles meet it near enough its origin that
        float32, which Warp's mesh queries use, resolves half the contact's margin there
        (``finalize`` judges it; in float32 the vertices of the faces they meet count;
        docs/tools.md);
        ``prim_path`` names a USD file's Mesh prim, as in ``add_mesh``). ``motion``: ``tools.Keyframes``, ``tools.Velocity``
        or ``tools.Scripted``; ``None``: held at ``position`` / ``orientation`` (x, y, z, w).
        ``friction``: kinetic Coulomb coefficient; ``static_friction`` (>= friction;
        default: ``friction``)."""
        kind = checks.choice("shape", shape, tools.KINDS)
        if len(self.tools) >= tools.MAX_TOOLS:
            raise ValueError(f"tools = {len(self.tools) + 1} is not allowed: at most {tools.MAX_TOOLS}")
        name = f"{kind}_tool{len(self.tools)}" if name is None else name
        self._check_tool_name(name)
        mu_k = checks.non_negative("friction", friction)
        mu_s = mu_k if static_friction is None else checks.non_negative("static_friction", static_friction)
        if mu_s < mu_k:
            raise ValueError(f"static_friction = {checks.shorten(static_friction)!r} is not allowed: must be >= friction = {mu_k:g}")
        # Options of another shape, and a place a motion of absolute poses overrides, were
        # ignored without a word.
        given = {"normal": normal, "half_extents": half_extents, "radius": radius, "half_height": half_height,
                 "mesh": mesh, "prim_path": prim_path}
        own = _TOOL_SHAPE_OPTIONS[kind]
        stray = [k for k, v in given.items() if v is not None and k not in own]
        # A mesh's alone: any other value given, an array (numpy's 'truth value ... is
        # ambiguous' at '!=') or True (== 1) as well.
        if kind != "mesh" and not (isinstance(scale, numbers.Real) and not isinstance(scale, (bool, np.bool_)) and scale == 1.0):
            stray.append("scale")
        if stray:
            raise ValueError(f"{stray[0]} = {checks.shorten(given.get(stray[0], scale))!r} is not allowed for shape "
                             f"{kind!r}: its options are {', '.join(own) or 'none'}")
        pos = checks.vector("position", position)
        ori = tools._quat("orientation", orientation)
        if isinstance(motion, (tools.Keyframes, tools.Scripted)):
            # Its poses are absolute: a place given beside them was ignored. The same as its
            # first pose says nothing new and is taken.
            identity = tools._quat("orientation", tools.IDENTITY)
            first = ((0.0, 0.0, 0.0), identity)
            if isinstance(motion, tools.Keyframes):
                first = (tuple(motion.positions[0]),
                         tuple(motion.orientations[0]) if motion.orientations is not None else identity)
            same = lambda a, b: np.allclose(a, b, rtol=0.0, atol=1e-12)  # noqa: E731
            # The value given, and the pose the motion starts at, so the caller sees which
            # of the two it meant (the message named neither).
            for label, given, default, start in (("position", position, (0.0, 0.0, 0.0), first[0]),
                                                 ("orientation", orientation, identity, first[1])):
                value = pos if label == "position" else ori
                if not (same(value, default) or same(value, start)):
                    starts = ("" if isinstance(motion, tools.Scripted) else
                              f"; its first keyframe's {label} is {checks.shorten(tuple(float(c) for c in start))!r}")
                    raise ValueError(f"{label} = {checks.shorten(given)!r} is not allowed with a {type(motion).__name__} "
                                     f"motion: its poses are absolute (give them in the motion{starts})")
        if motion is None:
            motion = tools.Velocity(position=pos, orientation=ori)
        elif isinstance(motion, tools.Velocity):
            # A start pose the motion gives overrode the one given beside it without a word.
            same = lambda a, b: np.allclose(a, b, rtol=0.0, atol=1e-12)  # noqa: E731
            for label, given, own, default in (("position", pos, motion.position, (0.0, 0.0, 0.0)),
                                               ("orientation", ori, motion.orientation, tools._quat("orientation", tools.IDENTITY))):
                if own is not None and not same(given, default) and not same(given, own):
                    raise ValueError(f"{label} = {checks.shorten(given)!r} is not allowed beside a Velocity motion with "
                                     f"{label} = {checks.shorten(own)!r}: give the start pose once (in the motion, or "
                                     f"as add_tool's {label} with the motion's left None)")
            if motion.position is None or motion.orientation is None:
                motion = tools.Velocity(motion.velocity, motion.angular_velocity,
                                        motion.position if motion.position is not None else pos,
                                        motion.orientation if motion.orientation is not None else ori)
        elif not isinstance(motion, tools.MOTIONS):
            raise ValueError(f"motion = {checks.shorten(motion)!r} is not allowed: must be tools.Keyframes, tools.Velocity, tools.Scripted or None")
        points = triangles = None
        if kind == "mesh":
            if mesh is None:
                raise ValueError("mesh = None is not allowed: a mesh tool needs a mesh file or (points, triangles)")
            points, triangles = meshes.load_mesh(mesh, prim_path=prim_path, name="mesh")
            s = checks.positive("scale", scale)
            with np.errstate(over="ignore", invalid="ignore"):
                points = points * s
            # Warp's mesh queries run in float32 whatever the model's precision, and square
            # distances: a bunny at scale 1e39 became a tool of inf points (a numpy warning
            # only), and the run went on as if it were not there.
            reach, far = float(np.abs(points).max()), math.sqrt(float(np.finfo(np.float32).max))
            # The queries' float32 must also resolve the contact's margin where the particles
            # meet the mesh (``_check_mesh_tool_reach``). Every point of a mesh whose bounds lie
            # that far out (modelled far from its origin) is: refused here, particles or not.
            lo, hi = points.min(axis=0), points.max(axis=0)
            near = float(np.maximum(np.maximum(lo, -hi), 0.0).max()) if len(points) else 0.0
            if not (reach <= far and _float32_resolves_margin(near, self.spacing)):
                label = repr(os.fsdecode(os.fspath(mesh))) if meshes._is_path(mesh) else "(points, triangles)"
                what = (f"scale = {checks.shorten(scale)!r} is not allowed for mesh {label}: it puts the mesh's points"
                        if s != 1.0 else f"mesh {label} is not allowed: its points (scale 1) lie")
                if not reach <= far:
                    raise ValueError(f"{what} up to {reach:.3g} m from the tool's origin; a mesh tool's points must be "
                                     f"within {far:.3g} m of it (Warp's mesh queries are float32); give a smaller scale")
                raise ValueError(f"{what} {near:.3g} m and more from the tool's origin, where float32 (Warp's mesh "
                                 f"queries) {_margin_unresolved(near, self.spacing)}; model the mesh about its origin (its "
                                 "points less their centre, the centre added to position) or use a larger spacing")
        param = tools.shape_param(kind, normal=normal, half_extents=half_extents, radius=radius, half_height=half_height)
        self._check_tool_size(name, kind, param, points, mesh, scale)
        self.tools.append(tools.Collider(name, kind, param, motion, mu_k, mu_s, points, triangles))
        return name

    def _check_tool_size(self, name, kind, param, points, mesh, scale) -> None:
        """Refuse a tool smaller in every direction than the contact's own margin (a particle
        that meets a tool is put ``tools.CONTACT_MARGIN`` spacings outside it): a bunny at
        scale 1e-9 was taken, and the run went on as if it were not there. A tool a tenth of
        a spacing across is taken: it still stops the particles in its path (a 2 mm sphere
        through a row at spacing 0.02, ``tests/test_tools.py``), as a plate thinner than the
        spacing does."""
        if kind == "plane":
            return
        if kind == "mesh":
            across = float((points.max(axis=0) - points.min(axis=0)).max()) if len(points) else 0.0
            label = repr(os.fsdecode(os.fspath(mesh))) if meshes._is_path(mesh) else "(points, triangles)"
            what = (f"scale = {checks.shorten(scale)!r} is not allowed for mesh tool {name!r} of {label}" if scale != 1.0
                    else f"mesh tool {name!r} of {label} is not allowed")
            fix = "a larger scale or a smaller spacing"
        else:
            across = {"box": 2.0 * max(param), "sphere": 2.0 * param[0], "capsule": 2.0 * max(param[0], param[1] + param[0]),
                      "cylinder": 2.0 * max(param[0], param[1])}[kind]
            key = {"box": "half_extents", "sphere": "radius"}.get(kind, "radius / half_height")
            given = {"box": param, "sphere": param[0]}.get(kind, param[:2])
            what = f"{key} = {checks.shorten(given)!r} is not allowed for {kind} tool {name!r}"
            fix = f"a larger {key} or a smaller spacing"
        least = tools.CONTACT_MARGIN * self.spacing
        if not across >= least:
            raise ValueError(f"{what}: the tool is {across:.3g} m across at most, less than {least:.3g} m, a thousandth of "
                             f"the spacing {self.spacing:g} (the contact's margin): the particles pass it by; give {fix}")

    def pin(self, indices=None, *, body: str | int | None = None, region=None, where=None, motion=None, name: str | None = None) -> str:
        """Hold a set of particles fixed, or move it rigidly (``tools.py``); returns its name.

        The set is the intersection of the given selections among the particles added so
        far: ``indices`` (integer indices or a boolean mask), ``body`` (a body's name or the
        index its ``add_*`` returned),
        ``region = (lo, hi)`` (an axis-aligned box of rest positions), ``where`` (a predicate
        on the rest positions, ``(N, 3) -> bool (N,)``). ``motion``: ``None`` (held fixed),
        ``tools.Velocity`` (from the set's rest centroid unless it gives a position),
        ``tools.Keyframes`` (poses of the set's frame, whose rest pose is its centroid with
        identity orientation) or ``tools.Scripted``. Pinned particles keep their place in
        every neighbour fit; only their x and v are prescribed."""
        name = f"pin{len(self.pins)}" if name is None else name
        self._check_tool_name(name)
        if motion is not None and not isinstance(motion, tools.MOTIONS):
            raise ValueError(f"motion = {checks.shorten(motion)!r} is not allowed: must be tools.Keyframes, tools.Velocity, tools.Scripted or None")
        idx = tools.select_particles(self, indices=indices, body=body, region=region, where=where, name=name)
        for p in self.pins:
            if np.intersect1d(p.indices, idx).size:
                raise ValueError(f"pin {name!r} is not allowed: it shares particles with pin {p.name!r}")
        self.pins.append(tools.PinSet(name, idx, tools.Velocity() if motion is None else motion))
        return name

    def add_compression_field(self, center, strength: float, t_on: float = 0.0, t_off: float = float("inf"),
                              body: str | int | None = None):
        """A horizontal compression ``a = -strength (x - center)`` (1/s^2) while ``t_on <= t < t_off``,
        on the particles of ``body`` (a name, or the index an ``add_*`` returned; ``None``: all).
        See ``fields.CompressionField``; ``Model.stable_dt`` bounds the step by its strength."""
        from .sim.fields import CompressionField  # noqa: PLC0415

        index = -1 if body is None else self._body_index(body)
        self.force_fields.append(CompressionField(center, strength, t_on, t_off, body=index))

    def _body_index(self, body) -> int:
        """The index of ``body``, a body's name or the index its ``add_*`` returned; refused by
        name otherwise (a bool is no index)."""
        names = [b.name for b in self._bodies]
        if not names:
            # Refused as "index (0..-1)" or "one of []".
            raise ValueError(f"body = {checks.shorten(body)!r} is not allowed: the builder has no body yet; add one (add_box, "
                             f"add_particles, ...) first")
        if isinstance(body, str):
            if body not in names:
                raise ValueError(f"body = {checks.shorten(body)!r} is not allowed: must be one of {names!r}")
            return names.index(body)
        if isinstance(body, (int, np.integer)) and not isinstance(body, bool) and 0 <= body < len(names):
            return int(body)
        raise ValueError(f"body = {checks.shorten(body)!r} is not allowed: must be a body name or index (0..{len(names) - 1})")

    # --------------------------------------------------------------- finalize
    # The scene-wide settings, checked as the constructor checks them when set afterwards
    # (the command line sets the solver's from its options, fit --support-radius the radius):
    # set by hand they were taken unchecked, and max_neighbors = 0 crashed the process in the
    # first step, gravity (0, nan, 0) ran to NaN and a support radius of 50 spacings ran.

    @property
    def spacing(self) -> float:
        """The lattice spacing dx (m); fixed once made: the bodies are sampled on its lattice (set to
        its own value, a no-op, it is taken)."""
        return self._spacing

    @spacing.setter
    def spacing(self, value):
        # Its own value is no change: a caller that sets every setting from a record (a scene's
        # settings copied onto a builder) was refused for the one it did not change.
        if checks.positive("SceneBuilder.spacing", value) == self._spacing:
            return
        raise ValueError(f"SceneBuilder.spacing = {checks.shorten(value)!r} is not allowed: the bodies are sampled on the lattice "
                         f"of spacing {self._spacing!r}, and their masses, the support radius and the neighbour rows follow "
                         f"it; make a SceneBuilder(spacing={checks.shorten(value)!r})")

    @property
    def support_radius(self) -> float:
        """The kernels' support radius h (m), in ``SUPPORT_RANGE`` spacings; None sets the
        default, 2 dx. The default ``max_neighbors`` follows it."""
        return self._support_radius

    @support_radius.setter
    def support_radius(self, value):
        h = 2.0 * self._spacing if value is None else checks.positive("support_radius", value)
        lo, hi = SUPPORT_RANGE
        if not lo * self._spacing <= h <= hi * self._spacing:
            raise ValueError(
                f"support_radius = {checks.shorten(value)!r} is not allowed: must be in "
                f"[{lo} * spacing, {hi} * spacing] = [{lo * self._spacing:g}, {hi * self._spacing:g}]"
            )
        thin = self.thin_floor(h)
        if thin is not None:
            raise ValueError(f"support_radius = {h:g} is not allowed {thin}; set the support radius before "
                             f"add_particle_floor (a scene file's support_radius), or give the floor its layers (layers=, a "
                             f"scene file's floor_layers)")
        self._support_radius = h
        if self._max_neighbors_given is None:
            # The default width for the new radius: rows of the old one's were cut.
            self._max_neighbors = default_max_neighbors(h / self._spacing)

    def thin_floor(self, support_radius: float) -> str | None:
        """Why a particle floor added with its default layers would be thinner than a support of
        ``support_radius`` (its top layer then without a full neighbourhood), or None: the
        ``support_radius`` setter's refusal, which ``fit --support-radius`` words as its own."""
        for pin, (layers, then) in self._default_floors.items():
            reach = _floor_layers(support_radius, self._spacing)
            if reach > layers:
                return (f"after the particle floor {pin!r}: it was added with the default {layers} layers, ceil(support_radius "
                        f"/ spacing) at the support radius it was added at, {then:g}, and a support of {support_radius:g} "
                        f"reaches {reach} spacings below the body, past the floor")
        return None

    @property
    def max_neighbors(self) -> int:
        """The width of a neighbour row (see the class's docstring): a positive integer, None
        (the default for the support radius) or "paper" (``PAPER_MAX_NEIGHBORS``)."""
        return self._max_neighbors

    @max_neighbors.setter
    def max_neighbors(self, value):
        given = value
        if value is None:
            value = default_max_neighbors(self._support_radius / self._spacing)
        elif isinstance(value, str):
            if value != "paper":
                raise ValueError(f"max_neighbors = {checks.shorten(value)!r} is not allowed: must be a positive integer, "
                                 f"None (the default width) or 'paper' ({PAPER_MAX_NEIGHBORS})")
            value = PAPER_MAX_NEIGHBORS
        self._max_neighbors = checks.positive_int("max_neighbors", value, maximum=MAX_NEIGHBORS)
        self._max_neighbors_given = given

    @property
    def gravity(self) -> tuple[float, float, float]:
        """The acceleration of gravity (m/s^2): three finite numbers."""
        return self._gravity

    @gravity.setter
    def gravity(self, value):
        self._gravity = checks.vector("gravity", value)

    @property
    def bodies_interact(self) -> bool:
        """Whether SPH pressure and viscosity act between bodies (contact between bodies).
        ``False`` makes every body a separate simulation that only shares colliders."""
        return self._bodies_interact

    @bodies_interact.setter
    def bodies_interact(self, value):
        if not isinstance(value, bool):
            raise ValueError(f"bodies_interact = {checks.shorten(value)!r} is not allowed: must be True or False")
        self._bodies_interact = value

    @property
    def fit(self) -> str | None:
        """``Model.fit`` of the model ``finalize`` makes (None: the model's default)."""
        return self._fit

    @fit.setter
    def fit(self, value):
        self._fit = None if value is None else checks.choice("fit", value, FITS)

    @property
    def fit_weight(self) -> str:
        """``Model.fit_weight`` of the model ``finalize`` makes."""
        return self._fit_weight

    @fit_weight.setter
    def fit_weight(self, value):
        self._fit_weight = checks.choice("fit_weight", value, FIT_WEIGHTS)

    @property
    def contact_ramp(self) -> float:
        """``Model.contact_ramp`` of the model ``finalize`` makes."""
        return self._contact_ramp

    @contact_ramp.setter
    def contact_ramp(self, value):
        self._contact_ramp = check_contact_ramp("contact_ramp", value)

    @property
    def hourglass(self) -> float | None:
        """``Model.hourglass`` of the model ``finalize`` makes (None: by the fit)."""
        return self._hourglass

    @hourglass.setter
    def hourglass(self, value):
        self._hourglass = None if value is None else checks.hourglass("hourglass", value)

    @property
    def particle_count(self) -> int:
        """The particles added so far (pinned floors included)."""
        return self._count

    def _check_overlap(self):
        """Bodies must not share space: overlapping particles would start under huge pressure.

        Particles are binned in cells of half the spacing; a body's own lattice puts at
        most one particle in a cell, so a shared cell means two bodies closer than ~0.9 dx.
        """
        if len(self._bodies) < 2 or not self.bodies_interact:
            return
        points = np.concatenate(self._points)
        body = np.concatenate([np.full(b.count, k) for k, b in enumerate(self._bodies)])
        cells = np.floor(points / (0.5 * self.spacing)).astype(np.int64)
        _, first, inverse = np.unique(cells, axis=0, return_index=True, return_inverse=True)
        owner = body[first][inverse.ravel()]
        clash = np.nonzero(owner != body)[0]
        if not clash.size:
            # Two bodies offset by less than half a spacing can fall in different cells
            # throughout (two boxes 0.1 dx apart passed): any two particles of different
            # bodies closer than half a spacing overlap as well.
            i, j = _closer_than(points, body, 0.5 * self.spacing)
            if i is not None:
                owner, clash = {j: body[i]}, np.array([j])
        if clash.size:
            a, b = self._bodies[owner[clash[0]]].name, self._bodies[body[clash[0]]].name
            why = (f"bodies {a!r} and {b!r} are not allowed to overlap: {clash.size} particles of one lie within "
                   f"the other (at {np.round(points[clash[0]], 4).tolist()}); move them at least one spacing apart")
            # A scene file's: the later body's table, which put it where the other was.
            self._refuse(("body", max(int(owner[clash[0]]), int(body[clash[0]]))), why, why)

    def _refuse(self, origin: tuple, api: str, key: str):
        """Raise the refusal ``api`` (worded for the Python API), or, for a builder read from a
        scene file, ``key`` (worded for the file's keys) after the file and the table ``origin``
        names (a float32 refusal of a file's mu = 1e39, or a body starting inside a file's tool,
        named neither)."""
        if self.source is None:
            raise ValueError(api)
        where = self.origins.get(origin)
        raise ValueError(f"{self.source}: {where}: {key}" if where is not None else f"{self.source}: {api}")

    def _body_at(self, i: int) -> tuple[int, str]:
        """``(body index, the file's key that places it)`` of particle ``i``."""
        for k, b in enumerate(self._bodies):
            if b.start <= i < b.start + b.count:
                return k, "translation" if b.kind == "mesh" else "center"
        return -1, "center"

    def _check_mesh_tool_reach(self, scalar) -> None:
        """Refuse a mesh tool whose contact float32 cannot resolve to half its margin where the
        particles can meet it (``_float32_resolves_margin``); it was judged at the mesh's
        farthest point, and a floor 20000 spacings wide about its origin was refused with the
        particles on its middle.

        Where they can meet it is bounded by the distance ``D`` from the tool's origin to the
        particles' box at the start, grown by its own diagonal on every side (they fall, flow
        and spread over a run), seen from each place the motion gives before the run: a held
        or ``Velocity`` tool's start, each key of ``Keyframes`` (a place between two keys is
        no farther from the box). A distance, so any turn of the tool is covered. A
        ``Scripted`` tool's places are known only as it runs: its whole mesh counts. The
        particles may go farther than this bound (thrown, carried on a conveyor, dragged by a
        pinned set): ``simulate`` stops the run where they meet such a mesh there
        (``simulate._far_mesh_contact``).

        Warp's float32 queries only pick the face and say inside or outside: in float64 what
        counts is how far out the particles meet it (up to ``D``, and no farther than the
        mesh's farthest point). A float32 model also computes the contact point on the face
        from its vertices, so there the vertices of every face within ``D`` count (measured:
        a block resting on the two triangles of a floor's top 400 m across bounced over the
        whole margin in float32, to 5e-15 m in float64)."""
        points = np.concatenate(self._points) if self._points else np.zeros((0, 3))
        if not len(points):
            return
        lo, hi = points.min(axis=0), points.max(axis=0)
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        grow = float(np.linalg.norm(hi - lo))
        f32 = scalar is wp.float32
        for t in self.tools:
            if t.kind != "mesh" or not len(t.mesh_points):
                continue
            pts = t.mesh_points
            reach = float(np.abs(pts).max())
            if not isinstance(t.motion, tools.Scripted):
                m = t.motion
                places = np.atleast_2d(np.asarray(m.positions if isinstance(m, tools.Keyframes) else m.position, dtype=np.float64))
                d = float(np.linalg.norm(corners[:, None, :] - places[None, :, :], axis=2).max()) + grow
                if f32:
                    tri = pts[t.mesh_triangles]  # (T, 3, 3)
                    near = (tri.min(axis=1) <= d).all(axis=1) & (tri.max(axis=1) >= -d).all(axis=1)
                    reach = float(np.abs(tri[near]).max()) if near.any() else 0.0
                else:
                    reach = min(reach, d)
            if not _float32_resolves_margin(reach, self.spacing):
                move = "model the mesh about where they touch it (its points less that place, the place added to position)"
                if f32:
                    why = (f"mesh tool {t.name!r} is not allowed in float32: the faces the particles can touch reach "
                           f"{reach:.3g} m from its origin, where float32 (the model's contact and Warp's mesh queries) "
                           f"{_margin_unresolved(reach, self.spacing)}; {move}, split its faces there into smaller ones, ")
                    self._refuse(("tool", t.name), why + "use dtype=float64, or a larger spacing",
                                 why + "use dtype=float64 (--dtype float64), or a larger spacing")
                why = (f"mesh tool {t.name!r} is not allowed: the particles can touch it up to {reach:.3g} m from its "
                       f"origin, where float32 (Warp's mesh queries) {_margin_unresolved(reach, self.spacing)}; {move} or "
                       "use a larger spacing")
                self._refuse(("tool", t.name), why, why)

    def _check_precision(self, scalar):
        """Every material parameter and position fits the precision: 1e300 Pa cast to float32
        became inf in the model without a word."""
        big = float(np.finfo(np.float32 if scalar is wp.float32 else np.float64).max)
        T = scalar.__name__
        hint = wider_precision(scalar, "a smaller value", cli=True)
        for k, m in enumerate(self._materials):
            problem = material_precision_problem(m, scalar)
            if problem is not None:
                name, v, why = problem
                # A scene file's is read by the command (--dtype) and by Python (dtype=): its
                # advice names both, as a sweep's sample refusal does (it named dtype=float64 only).
                self._refuse(("material", k), f"{name} = {v:g} (material {k}) is not allowed in {T}: {why}",
                             f"{name.removeprefix('Material.')} = {v:g} is not allowed in {T}: "
                             f"{material_precision_problem(m, scalar, cli=True)[2]}")
        points = np.concatenate(self._points) if self._points else np.zeros((0, 3))
        if len(points) and np.abs(points).max() > big:
            i = int(np.argmax(np.abs(points).max(axis=1)))
            k, key = self._body_at(i)
            self._refuse(("body", k), f"positions beyond {big:.3g} m are not allowed in {T}",
                         f"{key} puts particles beyond {big:.3g} m (one at {tuple(points[i].tolist())!r}), which is not "
                         f"allowed in {T}: {hint}")
        # The kernels' constants are powers of the support radius (poly6's 1 / h^9): below
        # h = 5.7e-5 m h^9 left float32's normal range and the first step wrote NaN positions.
        tiny = float(np.finfo(np.float32 if scalar is wp.float32 else np.float64).tiny)
        h = float(self.support_radius)
        if not tiny ** (1 / 9) <= h <= big ** (1 / 9):  # h itself: h ** 9 overflowed a float beyond 1e34
            why = (f"is not allowed in {T}: the kernels' constants (1 / h^9) must fit the precision, so it must be in "
                   f"[{tiny ** (1 / 9):.3g}, {big ** (1 / 9):.3g}] m")
            f32 = scalar is wp.float32
            self._refuse(("scene",), f"support_radius = {h!r} {why}; {'use dtype=float64 (or larger units)' if f32 else 'use other units'}",
                         f"support_radius = {h!r} (given, or 2 x spacing) {why}; "
                         f"{'use dtype=float64 (--dtype float64) or larger units' if f32 else 'use other units'}")
        # The static colliders' sizes and places enter the contact squared: 1e300 m (or 1e40 m
        # in float32) turned every particle's position into NaN in the first step.
        far = math.sqrt(big)
        kinds = (("plane", "add_ground", self.planes, (("height (add_plane offset)", "offset", "offset"),)),
                 ("sphere", "add_sphere_collider", self.spheres, (("center", "center", "center"), ("radius", "radius", "radius"))),
                 ("box", "add_box_collider", self.boxes, (("center", "center", "center"),
                                                         ("half_extents", "half_extents", "half_extents"))))
        for kind, call, items, fields in kinds:
            for j, item in enumerate(items):
                for label, key, field in fields:
                    if kind == "plane" and "(type 'ground')" in self.origins.get((kind, j), ""):
                        key = "height"  # a ground is the plane y = height
                    v = getattr(item, field)
                    if np.abs(np.asarray(v, dtype=np.float64)).max() > far:
                        why = f"is not allowed in {T}: must be at most {far:.3g} in size; {hint}"
                        self._refuse((kind, j), f"{call} {label} = {v!r} {why}", f"{key} = {v!r} {why}")
                if item.friction > big:
                    why = f"is not allowed in {T}: must be at most {big:.3g}"
                    self._refuse((kind, j), f"{call} friction = {item.friction!r} {why}", f"friction = {item.friction!r} {why}")
        # Positions must also resolve the spacing: at 1e7 m a float32 lattice 5 cm apart fell
        # onto 16 points and every fit was ill-conditioned, without a word.
        if len(points):
            i = int(np.argmax(np.abs(points).max(axis=1)))
            reach = float(np.abs(points[i]).max())
            eps = float(np.finfo(np.float32 if scalar is wp.float32 else np.float64).eps)
            if reach * eps > 1e-2 * self.spacing:
                why = (f"{T} resolves {reach * eps:.2g} m there, more than a hundredth of the spacing {self.spacing:g}; "
                       f"move the scene nearer the origin{' or use dtype=float64 (--dtype float64)' if scalar is wp.float32 else ''}")
                k, key = self._body_at(i)
                self._refuse(("body", k), f"positions {reach:.3g} m from the origin are not allowed in {T}: it resolves "
                             f"{reach * eps:.2g} m there, more than a hundredth of the spacing {self.spacing:g}; move "
                             f"the scene nearer the origin{' or use dtype=float64' if scalar is wp.float32 else ''}",
                             f"{key} puts particles {reach:.3g} m from the origin, which is not allowed in {T}: {why}")
        # Gravity, the bodies' velocities and the tools' poses, sizes and motions are numbers of
        # this precision in the step too (gravity 1e39 in float32 was inf in the first kernel, a
        # tool at 1e39 m wrote NaN poses and the run exited 0).
        if np.abs(self.gravity).max() > big:
            why = f"is not allowed in {T}: must be at most {big:.3g}"
            self._refuse(("scene",), f"gravity = {self.gravity!r} {why}", f"gravity = {list(self.gravity)!r} {why}")
        for fld in self.force_fields:
            problem = field_precision_problem(fld, scalar)
            if problem is not None:
                raise ValueError(problem)
        velocities = np.concatenate(self._velocities) if self._velocities else np.zeros((0, 3))
        if len(velocities) and np.abs(velocities).max() > big:
            k, _ = self._body_at(int(np.argmax(np.abs(velocities).max(axis=1))))
            self._refuse(("body", k), f"body velocities beyond {big:.3g} m/s are not allowed in {T}",
                         f"velocity (with angular_velocity) gives speeds beyond {big:.3g} m/s, which is not allowed in "
                         f"{T}: {hint}")
        keys = {"velocity": "velocity", "angular_velocity": "angular_velocity", "position": "position",
                "positions": "keyframe_positions", "times": "keyframe_times"}
        for t in [*self.tools, *self.pins]:
            m = t.motion
            kind = "tool" if t in self.tools else "pinned set"
            origin = ("tool" if t in self.tools else "pin", t.name)
            for field in ("velocity", "angular_velocity", "position", "positions", "times"):
                v = getattr(m, field, None)
                if v is not None and np.abs(np.asarray(v, dtype=np.float64)).max() > far:
                    why = f"is not allowed in {T}: must be at most {far:.3g} in size; {hint}"
                    self._refuse(origin, f"{kind} {t.name!r}: {type(m).__name__} {field} = {v!r} {why}",
                                 f"{keys[field]} = {checks.shorten(np.asarray(v).tolist())!r} {why}")
            if isinstance(m, tools.Keyframes):
                why = tools.keyframe_times_problem(m.times, np.float32 if scalar is wp.float32 else np.float64)
                if why is not None:
                    shown = checks.shorten(list(m.times))
                    why = f"is not allowed in {T}: {why}; "
                    self._refuse(origin, f"{kind} {t.name!r}: Keyframes times = {shown!r} {why}"
                                 f"{wider_precision(scalar, 'times further apart')}",
                                 f"keyframe_times = {shown!r} {why}{wider_precision(scalar, 'times further apart', cli=True)}")
            param = getattr(t, "param", None)
            if param is not None and np.abs(np.asarray(param, dtype=np.float64)).max() > far:
                size = np.abs(np.asarray(param)).max()
                why = f"is not allowed in {T}: must be at most {far:.3g}"
                self._refuse(origin, f"tool {t.name!r}: a size of {size:.3g} m {why}",
                             f"a size (radius, half_extents, half_height or scale) of {size:.3g} m {why}")
            for label in ("friction", "static_friction"):
                mu = getattr(t, label, None)
                if mu is not None and mu > big:
                    why = f"is not allowed in {T}: must be at most {big:.3g}"
                    self._refuse(origin, f"tool {t.name!r}: {label} = {mu!r} {why}", f"{label} = {mu!r} {why}")

    def finalize(self, device="cpu", dtype=wp.float32, requires_grad: bool = False, worlds: int = 1) -> Model:
        """Builds the ``Model`` on ``device`` in precision ``dtype`` (float32 or float64).

        ``worlds=W`` puts ``W`` copies of the scene in one model (``finalize_worlds``):
        each with its own materials (``model.set_material(i, material, world=w)``), none
        seeing another (they may overlap in space), all sharing the colliders and tools
        (each world reports its own tool reactions, ``tools.ToolSet``).

        A body's particles that start inside a static collider, or a tool at its first pose,
        are placed on its surface, as their initial and rest positions both (a ``UserWarning``
        names the body, the collider, how many and how deep); more than half a spacing deep is
        refused (docs/errors.md)."""
        if isinstance(worlds, bool) or not isinstance(worlds, (int, np.integer)) or worlds < 1:
            raise ValueError(f"worlds = {checks.shorten(worlds)!r} is not allowed: must be an integer >= 1")
        if worlds > MAX_WORLDS:  # 1e12 ended in a MemoryError building the list of copies
            raise ValueError(f"worlds = {checks.shorten(worlds)!r} is not allowed: must be at most {MAX_WORLDS}")
        try:
            dev = wp.get_device(device)
        except Exception:  # noqa: BLE001 (a bad device: finalize_worlds names it)
            dev = None
        if dev is not None and worlds > 1:  # (one world: finalize_worlds checks it)
            _check_memory(self.particle_count * int(worlds), self.max_neighbors, dev, worlds=int(worlds))
        return finalize_worlds([self] * int(worlds), device=device, dtype=dtype, requires_grad=requires_grad)


#: What every world of a model must share (``finalize_worlds``).
_SHARED = ("spacing", "support_radius", "gravity", "max_neighbors", "bodies_interact", "planes", "spheres", "boxes",
           "fit", "contact_ramp", "hourglass", "fit_weight")


def _tool_signature(b: SceneBuilder) -> tuple:
    """What must be equal in every world's tools and pins (``finalize_worlds``)."""
    cols = tuple(
        (c.name, c.kind, c.param, repr(c.motion), c.friction, c.static_friction,
         None if c.mesh_points is None else np.asarray(c.mesh_points).tobytes(),
         None if c.mesh_triangles is None else np.asarray(c.mesh_triangles).tobytes())
        for c in b.tools
    )
    return cols, tuple((p.name, repr(p.motion), len(p.indices)) for p in b.pins)


#: The most copies of a scene ``finalize(worlds=)`` makes.
MAX_WORLDS = 100_000
#: What a particle takes in a model, two states and a step, besides its neighbour rows, and
#: what each entry of its rows takes (measured on the CPU: 3.2-3.4 kB a particle at 96).
BYTES_PER_PARTICLE = 1000
BYTES_PER_NEIGHBOR = 24


#: Where the memory limit of this process's control group is read (``_cgroup_memory_free``).
_PROC_CGROUP = "/proc/self/cgroup"
_CGROUP_ROOT = "/sys/fs/cgroup"


def _cgroup_memory_free() -> int | None:
    """The least memory, in bytes, left under a limit of this process's control group or an
    ancestor's (cgroup v2 ``memory.max`` less ``memory.current``, v1 ``memory.limit_in_bytes``
    less ``memory.usage_in_bytes``, each use less the group's file cache, which the
    kernel drops before it fails an allocation; the limit itself where the use cannot be
    read), or None where none is set or none can be read."""
    try:
        # A group's name may be any bytes: kept as the file system's own (os.path maps them back).
        with open(_PROC_CGROUP, errors="surrogateescape") as f:
            lines = f.read().splitlines()
    except OSError:
        return None
    found = []
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        if parts[1] == "":
            base, name, used, cache = _CGROUP_ROOT, "memory.max", "memory.current", ("inactive_file", "active_file")
        elif "memory" in parts[1].split(","):
            base, name, used, cache = (os.path.join(_CGROUP_ROOT, "memory"), "memory.limit_in_bytes", "memory.usage_in_bytes",
                                       ("total_inactive_file", "total_active_file"))
        else:
            continue
        steps = [p for p in parts[2].split("/") if p]
        # The ancestors too: a limit set on a parent holds for its children, and a container
        # sees its own group at the mount's root whatever path the process's record names.
        for k in range(len(steps) + 1):
            try:
                with open(os.path.join(base, *steps[:k], name)) as f:
                    text = f.read().strip()
            except (OSError, ValueError):
                continue
            # v2 writes "max" for no limit, v1 a number near 2**63.
            if text.isdigit() and 0 < int(text) < 2**62:
                # The group's other processes' memory (a CI job's other workers) is not this model's.
                found.append(max(int(text) - _cgroup_memory_used(os.path.join(base, *steps[:k]), used, cache), 0))
    return min(found) if found else None


def _cgroup_memory_used(group: str, used: str, cache: tuple) -> int:
    """The memory a control group holds, in bytes (``used``, its file), less its file cache
    (``cache``, the keys of its ``memory.stat``: the inactive and the active lists, both of
    which the kernel reclaims before it fails an allocation under the limit; with the
    inactive list alone, as ``docker stats`` counts, a group whose cache is mostly active
    read as full and every model, however small, was refused); 0 where it cannot be read."""
    try:
        with open(os.path.join(group, used)) as f:
            taken = int(f.read().strip())
    except (OSError, ValueError):
        return 0
    try:
        with open(os.path.join(group, "memory.stat")) as f:
            for line in f:
                key, _, value = line.partition(" ")
                if key in cache:
                    taken -= int(value)
    except (OSError, ValueError):
        pass
    return max(taken, 0)


def _process_memory_limit() -> int | None:
    """The lowest soft limit, in bytes, of this process's address space and data segment
    (``ulimit -v``, ``ulimit -d``: ``RLIMIT_AS``, ``RLIMIT_DATA``), or None where neither is
    set or none can be read (no ``resource`` module off POSIX)."""
    try:
        import resource  # noqa: PLC0415 (POSIX only)
    except ImportError:
        return None
    found = []
    for name in ("RLIMIT_AS", "RLIMIT_DATA"):
        try:
            soft, _ = resource.getrlimit(getattr(resource, name))
        except (AttributeError, OSError, ValueError):
            continue
        if soft != resource.RLIM_INFINITY and soft > 0:
            found.append(int(soft))
    return min(found) if found else None


#: Where the machine's available memory is read (``_machine_memory_free``).
_PROC_MEMINFO = "/proc/meminfo"


def _machine_memory_free() -> int | None:
    """The machine's memory a new allocation can take, in bytes: Linux's ``MemAvailable``
    (free memory and the caches it can drop, less what the kernel keeps), else all of it
    (``SC_PHYS_PAGES``) where that cannot be read; None where neither can."""
    try:
        with open(_PROC_MEMINFO) as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, OSError, ValueError, TypeError):
        return None


def _host_memory() -> int | None:
    """The host's memory available to what is about to be allocated, in bytes, or None where
    not known: the machine's available memory (``_machine_memory_free``: its total let a run
    be taken on a shared machine whose other processes held most of it, and it filled it),
    or what the process's control group has left under its limit where lower (a container's:
    the machine's took what the container could not hold, and the container killed the run),
    or the process's own limit of its address space or data (``ulimit -v`` or ``-d``) where
    lower still (a model of 2.3 GB a field under ``ulimit -v 6000000`` failed in Warp's
    allocator with a traceback)."""
    machine = _machine_memory_free()
    if machine is None:
        return None
    limits = [x for x in (_cgroup_memory_free(), _process_memory_limit()) if x is not None]
    return min([machine, *limits])


def _device_memory(dev) -> int | None:
    """The memory of ``dev`` available to what is about to be allocated, in bytes, or None
    where not known: for the CPU the host's (``_host_memory``), for a GPU its free memory."""
    if getattr(dev, "is_cpu", False):
        return _host_memory()
    try:
        return int(dev.free_memory)
    except (AttributeError, OSError, ValueError, TypeError):
        return None


def _check_memory(count: int, max_neighbors: int, dev, worlds: int | None = None) -> None:
    """Refuse a model that could not fit in the device's memory before allocating it: a body
    under the lattice cap (2e7 particles of 3 kB) exhausted the machine and was killed.
    ``worlds``: the copies asked for, which the refusal names (their particles are ``count``)."""
    have = _device_memory(dev)
    need = count * (BYTES_PER_PARTICLE + BYTES_PER_NEIGHBOR * max_neighbors)
    if have is not None and need > have:
        # The worlds' own refusal: wrapped in one, this said 'is not allowed' twice ('worlds = 2
        # is not allowed: particles = 128 is not allowed on cpu: ...').
        what, them, fewer = ((f"particles = {count}", "them", "") if worlds is None else
                             (f"worlds = {worlds}", f"their {count} particles", "fewer worlds, "))
        raise ValueError(f"{what} is not allowed on {dev}: a model and two states of {them} need about "
                         f"{need / 2**30:.3g} GiB ({need // count} B a particle at max_neighbors = {max_neighbors}), more "
                         f"than the {have / 2**30:.3g} GiB available; use {fewer}a larger spacing or smaller bodies")


def _check_outside_colliders(builder) -> None:
    """Refuse a body that starts more than half a spacing inside a static collider (pinned
    particles aside: a particle floor may lie under the ground): the contact pushed it out
    within a step, at a speed the run reported as a divergence (exit 3 after the kernels
    ran) or, inside a box or sphere, left it there."""
    if not builder._points or not (builder.planes or builder.spheres or builder.boxes):
        return
    x = np.concatenate(builder._points)
    free = np.ones(len(x), dtype=bool)
    for p in builder.pins:
        free[np.asarray(p.indices, dtype=np.int64)] = False
    starts = np.cumsum([0] + [b.count for b in builder._bodies])
    tol = 0.5 * builder.spacing
    for name, origin, depth, _ in _static_surfaces(builder):
        d = np.where(free, depth(x), -np.inf)
        inside = d > tol
        if inside.any():
            i = int(np.argmax(d))
            body = builder._bodies[int(np.searchsorted(starts, i, side="right")) - 1]
            why = (f"body {body.name!r} is not allowed where it is: {int(inside[body.start:body.start + body.count].sum())} "
                   f"of its particles start inside {name}, up to {d[i]:.3g} m deep (at {np.round(x[i], 4).tolist()})"
                   f"{_allowed_inside('collider', tol)}: move it out, or the collider")
            # A scene file's: the collider's table, which plane0, sphere0, box0 do not name.
            builder._refuse(origin, why, why)


def _static_surfaces(builder):
    """``(name, origin, depth, surface)`` of each static collider, named as the reaction rows
    name them (plane0, sphere0, box0): ``depth(x)`` how deep each point lies inside it
    (``_tool_depth``, in its own frame), ``surface(x)`` the nearest point of its surface from
    inside, where the contact kernels move a particle found inside (``sim/colliders.py``)."""
    out = []
    for k, p in enumerate(builder.planes):
        n, o = np.asarray(p.normal, dtype=np.float64), float(p.offset)
        out.append((f"plane{k}", ("plane", k), lambda x, n=n, o=o: _tool_depth("plane", n, x - o * n),
                    lambda x, n=n, o=o: x + np.outer(o - x @ n, n)))
    for k, s in enumerate(builder.spheres):
        c, r = np.asarray(s.center, dtype=np.float64), float(s.radius)

        def sphere_surface(x, c=c, r=r):
            d = x - c
            length = np.linalg.norm(d, axis=1, keepdims=True)
            # At the centre itself no direction is nearer: straight up, as any would do.
            d = np.where(length > 0.0, d / np.where(length > 0.0, length, 1.0), np.array([0.0, 1.0, 0.0]))
            return c + r * d
        out.append((f"sphere{k}", ("sphere", k), lambda x, c=c, r=r: _tool_depth("sphere", (r, 0.0, 0.0), x - c),
                    sphere_surface))
    for k, b in enumerate(builder.boxes):
        c, h = np.asarray(b.center, dtype=np.float64), np.asarray(b.half_extents, dtype=np.float64)

        def box_surface(x, c=c, h=h):
            # Through the nearest face, the one collide_box moves it to (ties: the lower axis).
            d = x - c
            axis = np.argmax(np.abs(d) - h, axis=1)
            rows = np.arange(len(x))
            out_ = x.copy()
            out_[rows, axis] = c[axis] + np.where(d[rows, axis] < 0.0, -1.0, 1.0) * h[axis]
            return out_
        out.append((f"box{k}", ("box", k), lambda x, c=c, h=h: _tool_depth("box", h, x - c), box_surface))
    return out


#: Most passes over the static colliders that placing a start inside makes (``_place_on_colliders``):
#: in a trough of angle a a corner particle's depth falls by cos(a)^2 a pass (60 degrees: a quarter),
#: to round-off in some 25 passes; a narrower trough may end a little inside, for the contact.
PLACING_PASSES = 64


def _place_on_colliders(builder, warn: bool = True) -> np.ndarray:
    """The builder's points with each free particle that starts inside a static collider
    (no deeper than half a spacing: ``_check_outside_colliders`` refuses deeper) moved onto
    its surface, as the model's initial and rest positions both, and a ``UserWarning`` for
    each body and collider naming how many and how deep. Left inside, the first step moved
    them there while the rest of the body stayed, a strain the material sent out at its wave
    speed: a two-layer rubber star 0.1 / 0.4 spacings inside the ground reached 3.1 / 12 m/s
    (exit 3 as diverged at 0.4; docs/errors.md). Placed with their rest positions they start
    unstrained, the body a little thinner where it met the collider. ``warn=False``: placed
    without a word (the resolution check's build, ``scenes.unresolved_bodies``)."""
    x = np.concatenate(builder._points).astype(np.float64, copy=True)
    if not (builder.planes or builder.spheres or builder.boxes):
        return x
    free = np.ones(len(x), dtype=bool)
    for p in builder.pins:
        free[np.asarray(p.indices, dtype=np.int64)] = False
    starts = np.cumsum([0] + [b.count for b in builder._bodies])
    # Deeper than the round-off of the coordinates is a start inside: a body built on the
    # ground from sums of spacings may come out a unit in the last place below it, and is
    # left there, as the contact takes it.
    sizes = [abs(p.offset) for p in builder.planes] + [np.abs(s.center).max() + s.radius for s in builder.spheres]
    sizes += [np.abs(b.center).max() + np.abs(b.half_extents).max() for b in builder.boxes]
    round_off = 8.0 * float(np.finfo(np.float64).eps) * (float(np.abs(x).max()) + max(sizes))
    surfaces = _static_surfaces(builder)
    placed = [np.zeros(len(x), dtype=bool) for _ in surfaces]
    deep = [np.zeros(len(x)) for _ in surfaces]
    # Pass after pass: a particle in a corner of two colliders, placed on one, may lie inside
    # the other, and placed on that, inside the first again (a 60-degree trough left 0.075
    # spacings of 0.1 inside the first, for the first step's contact to move).
    for _ in range(PLACING_PASSES):
        again = False
        for j, (name, origin, depth, surface) in enumerate(surfaces):
            d = depth(x)
            inside = free & (d > round_off)
            if not inside.any():
                continue
            again = True
            x[inside] = surface(x[inside])
            placed[j] |= inside
            deep[j] = np.where(inside, np.maximum(deep[j], d), deep[j])
            for k, body in enumerate(builder._bodies):
                _refuse_stacked(builder, origin, name, body.name, x[starts[k]:starts[k + 1]],
                                inside[starts[k]:starts[k + 1]])
        if not again:
            break
    for (name, origin, _, _), inside, d in zip(surfaces, placed, deep):
        for k, body in enumerate(builder._bodies if warn else ()):
            mine = inside[starts[k]:starts[k + 1]]
            if mine.any():
                deepest = float(d[starts[k]:starts[k + 1]][mine].max())
                # A scene file's: the file and the collider's table, as its refusals name them.
                table = builder.origins.get(origin)
                where = "" if builder.source is None else f"{builder.source}: {table}: " if table else f"{builder.source}: "
                warnings.warn(f"{where}body {body.name!r}: {int(mine.sum())} of its particles start inside {name}, up to "
                              f"{deepest:.3g} m deep ({deepest / builder.spacing:.3g} spacings); they are placed on its "
                              "surface, their rest positions with them, so the body starts unstrained (left inside, the "
                              "first step moved them out and the strain flung the body); start bodies on the surface",
                              UserWarning, stacklevel=4)
    return x


def _refuse_stacked(builder, origin, name: str, body: str, x: np.ndarray, placed: np.ndarray) -> None:
    """Refuse a body whose particles ``placed`` on collider ``name``'s surface put two of its
    particles ``x`` at one place (``checks.coincident_points``, as ``add_particles`` refuses
    them: they never separate). Two given 0.1 and 0.3 spacings under the ground on one normal
    were both placed on the same surface point, and the model built."""
    if not placed.any():
        return
    count, i = checks.coincident_points(x, builder.spacing)
    if count:
        why = (f"body {body!r} is not allowed where it is: its particles that start inside {name} (no deeper than half a "
               f"spacing), placed on its surface, put {count} of them on one place with another (first at "
               f"{np.round(x[i], 6).tolist()}); move the body out, or give its particles a spacing apart")
        builder._refuse(origin, why, why)


def _tool_depth(kind: str, param, xl: np.ndarray) -> np.ndarray:
    """How deep each local point ``xl`` lies inside a tool of ``kind`` (negative: outside),
    as the contact tests of ``tools.py`` see the shapes; a mesh is measured by ``ToolSet.mesh_depth`` (0 here)."""
    a, b, _ = (float(v) for v in param)
    if kind == "plane":
        return -(xl @ np.asarray(param, dtype=np.float64))
    if kind == "box":
        return (np.asarray(param, dtype=np.float64) - np.abs(xl)).min(axis=1)
    if kind == "sphere":
        return a - np.linalg.norm(xl, axis=1)
    if kind == "capsule":
        axis = np.zeros_like(xl)
        axis[:, 1] = np.clip(xl[:, 1], -b, b)
        return a - np.linalg.norm(xl - axis, axis=1)
    if kind == "cylinder":
        return np.minimum(a - np.hypot(xl[:, 0], xl[:, 2]), b - np.abs(xl[:, 1]))
    return np.zeros(len(xl))


def _allowed_inside(what: str, depth: float) -> str:
    """What a refusal of a body started inside a ``what`` (tool, collider) says is allowed."""
    return f"; a body may start at most half a spacing ({depth:.3g} m) inside a {what} (placed on its surface)"


def _check_outside_tools(model, builders) -> None:
    """Refuse a body that starts more than half a spacing inside a tool at the tool's first
    pose (pinned particles aside), as ``_check_outside_colliders`` does for the static
    ones: the first step moved the particles inside onto the tool's surface and reported a
    force (a sphere tool of 1000 m radius flung them 1 km, reported as a divergence; a box
    mesh tool in the middle of a block, which was not measured, pushed its particles out
    and read 69 N in five steps). ``builders``: the worlds'; the body is named as its
    builder names it (the model's 'w0/block' is a name the scene never gave), with its
    world where the worlds' builders differ, and the first one read from a scene file names
    the file and the tool's table."""
    builder = builders[0]
    one_scene = all(b is builder for b in builders)
    ts = model.tools
    x = np.asarray(model.particle_x0, dtype=np.float64)
    free = ts.pin.numpy() < 0
    tol = 0.5 * model.spacing
    for k, tool in enumerate(ts.colliders):
        p, q = ts.pose_at(k, 0.0)
        xl = (x - np.asarray(p, dtype=np.float64)) @ tools.quat_to_matrix(np.asarray(q, dtype=np.float64))
        depth = ts.mesh_depth(k, xl) if tool.kind == "mesh" else _tool_depth(tool.kind, tool.param, xl)
        d = np.where(free, depth, -np.inf)
        inside = d > tol
        if inside.any():
            i = int(np.argmax(d))
            k = int(model.particle_body_np[i])
            body = model.bodies[k]
            own = builders[body.world]._bodies[k - sum(len(b._bodies) for b in builders[:body.world])]
            name = repr(own.name) if one_scene else f"{own.name!r} of world {body.world}"
            why = (f"body {name} is not allowed where it is: {int(inside[body.start:body.start + body.count].sum())} of its "
                   f"particles start inside tool {tool.name!r} at its first pose, up to {d[i]:.3g} m deep (at "
                   f"{np.round(x[i], 4).tolist()}){_allowed_inside('tool', tol)}: move the body or the tool out")
            builder._refuse(("tool", tool.name), why, why)


def _tool_surface(kind: str, param, xl: np.ndarray, margin: float) -> np.ndarray:
    """Where the contact of a tool of ``kind`` (``tools.py``, ``shape_*``) puts each local
    point ``xl`` found inside it: the nearest point of its surface, ``margin`` outward of it
    (a plane's without one); a mesh's is ``_place_on_tools``'s."""
    a, b, _ = (float(v) for v in param)

    def outward(d, side):
        length = np.linalg.norm(d, axis=1, keepdims=True)
        # At the centre (or on the axis) no direction is nearer: any does for a sphere, any
        # across the axis (local y) for a capsule. Along it (the sphere's "up", once taken for
        # both), a rod thinner than a spacing through a row of particles left them inside it.
        return np.where(length > 0.0, d / np.where(length > 0.0, length, 1.0), side)
    across = np.array([1.0, 0.0, 0.0])
    if kind == "plane":
        n = np.asarray(param, dtype=np.float64)
        return xl - np.outer(xl @ n, n)
    if kind == "sphere":
        return (a + margin) * outward(xl, np.array([0.0, 1.0, 0.0]))
    if kind == "capsule":
        axis = np.zeros_like(xl)
        axis[:, 1] = np.clip(xl[:, 1], -b, b)
        return axis + (a + margin) * outward(xl - axis, across)
    out = xl.copy()
    rows = np.arange(len(xl))
    if kind == "box":
        half = np.asarray(param, dtype=np.float64)
        k = np.argmax(np.abs(xl) - half, axis=1)
        out[rows, k] = np.where(xl[rows, k] < 0.0, -1.0, 1.0) * (half[k] + margin)
        return out
    # A cylinder: through its side where that is nearer than its ends (shape_cylinder), on
    # the axis across it as the capsule's. The contact sends a point on the axis to an end
    # (it has no direction across): placed there, the axis' row of particles of a rod thinner
    # than a spacing went 5 spacings out of the body, onto one point at each end.
    rho = np.hypot(xl[:, 0], xl[:, 2])
    side = a - rho < b - np.abs(xl[:, 1])
    axial = side & (rho == 0.0)
    scale = (a + margin) / np.where(side & ~axial, rho, 1.0)
    out[side, 0] *= scale[side]
    out[side, 2] *= scale[side]
    out[axial, 0] = a + margin
    out[~side, 1] = np.where(xl[~side, 1] < 0.0, -1.0, 1.0) * (b + margin)
    return out


def _tool_shapes(model, x: np.ndarray) -> list:
    """``(name, origin, depth, place, round_off)`` of each tool at its first pose, as
    ``_static_surfaces`` gives the static colliders': ``depth(x)`` how deep each point lies
    inside it, ``place(x)`` where its contact puts a point found inside (the nearest point of
    its surface, the contact's margin outward; ``_tool_surface``), ``round_off`` the depth
    below which a point of ``x`` counts as on it."""
    ts = model.tools
    out = []
    for k, tool in enumerate(ts.colliders):
        p, q = ts.pose_at(k, 0.0)
        p = np.asarray(p, dtype=np.float64)
        R = tools.quat_to_matrix(np.asarray(q, dtype=np.float64))

        def depth(y, k=k, tool=tool, p=p, R=R):
            yl = (y - p) @ R
            return ts.mesh_depth(k, yl) if tool.kind == "mesh" else _tool_depth(tool.kind, tool.param, yl)

        def place(y, k=k, tool=tool, p=p, R=R):
            yl = (y - p) @ R
            if tool.kind == "mesh":
                _, near = ts.mesh_depth(k, yl, closest=True)
                d = near - yl
                placed = near + ts.margin * d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-30)
            else:
                placed = _tool_surface(tool.kind, tool.param, yl, ts.margin)
            return p + placed @ R.T
        # The model's positions are in its precision, the mesh's queries in float32. Deeper
        # than round-off: a tool put on a body's outer particles (the lab scenes') meets them
        # within it, and the contact takes them as they are.
        eps = float(np.finfo(np.float32 if tool.kind == "mesh" else model.types.np_dtype).eps)
        round_off = 8.0 * eps * (float(np.abs((x - p) @ R).max()) + ts.reach(k))
        out.append((f"tool {tool.name!r}", ("tool", tool.name), depth, place, round_off))
    return out


def _deepest(shapes: list, x: np.ndarray, among: np.ndarray) -> np.ndarray:
    """How deep each point of ``x`` lies inside the deepest of ``shapes`` (``_tool_shapes``'
    tuples), ``-inf`` outside ``among``."""
    return np.where(among, np.max([depth(x) for _, _, depth, _, _ in shapes], axis=0), -np.inf)


def _named(names: list) -> str:
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]


def _place_on_tools(model, builder, x: np.ndarray, free: np.ndarray, bodies, warn: bool = True) -> np.ndarray:
    """Place each free particle of ``x`` (one world's positions, placed out of the static
    colliders already) that starts inside a tool at the tool's first pose (no deeper than
    half a spacing: ``_check_outside_tools`` refuses deeper) where the tool's contact would
    put it, and warn for each of ``bodies`` (``(name, start, count)``) and tool, as
    ``_place_on_colliders`` does for the static ones: left inside, the first step moved them
    out while the rest of the body stayed, and the strain flung it. Those placed are then
    placed out of the static colliders and the tools again, pass after pass, until they are
    inside none: a plate tool's underside a twentieth of its margin above the ground put
    them 9.5e-4 spacings into the ground. One still inside after ``PLACING_PASSES`` (a tool
    into a collider, the particle between) is refused. ``x`` is placed in place; returns
    which moved. ``warn``: as theirs."""
    eps = float(np.finfo(model.types.np_dtype).eps)
    shapes = _tool_shapes(model, x)
    statics = []
    if builder.planes or builder.spheres or builder.boxes:
        sizes = [abs(p.offset) for p in builder.planes] + [np.abs(s.center).max() + s.radius for s in builder.spheres]
        sizes += [np.abs(b.center).max() + np.abs(b.half_extents).max() for b in builder.boxes]
        round_off = 8.0 * eps * (float(np.abs(x).max()) + max(sizes))
        statics = [(name, origin, depth, surface, round_off) for name, origin, depth, surface in _static_surfaces(builder)]
    everything = shapes + statics
    moved = np.zeros(len(x), dtype=bool)
    kept = np.zeros(len(x))  # how deep the passes left one they were still getting out
    started = [(np.zeros(len(x), dtype=bool), np.zeros(len(x))) for _ in shapes]
    again = [np.zeros(len(x), dtype=bool) for _ in everything]
    # The first pass places the starts inside a tool; the next ones, what that placing put
    # inside a static collider or another tool (a particle between a plate tool and the
    # ground, placed on one, lay in the other).
    for pass_ in range(PLACING_PASSES):
        busy = False
        if pass_ == 1:
            # How deep the first placing left each particle in another: what the passes take
            # out. One between a tool and a collider crossing at a narrow angle gets out at
            # cos(a)^2 a pass (10 degrees: 0.97), and 64 passes left 0.0065 spacings of 0.05.
            begun = _deepest(everything, x, moved)
        for j, (name, origin, depth, place, round_off) in enumerate(shapes if pass_ == 0 else everything):
            d = depth(x)
            inside = (free if pass_ == 0 else moved) & (d > round_off)
            if not inside.any():
                continue
            busy = True
            x[inside] = place(x[inside])
            moved |= inside
            if pass_ == 0:
                started[j] = (inside, d)
            else:
                again[j] |= inside
            for body, start, count in bodies:
                _refuse_stacked(builder, origin, name, body, x[start:start + count], inside[start:start + count])
        if not busy:
            break
    else:
        depths = np.stack([np.where(moved, depth(x) - round_off, -np.inf) for _, _, depth, _, round_off in everything])
        # Refused where the passes did not take out half of it, each placing putting it out
        # of one into the other as deep (a tool into a collider, the particle between); one
        # still getting out is left a little inside, for the contact, as _place_on_colliders
        # leaves one in a narrow trough (one 0.3 spacings before a tool's underside crosses the
        # ground at 10 degrees, 0.0065 of 0.05 spacings left, was refused, the wedge that near).
        deep, inside = _deepest(everything, x, moved), depths.max(axis=0) > 0.0
        left = inside & (deep > 0.5 * begun)
        kept = np.where(inside & ~left, deep, 0.0)
        if left.any():
            i = int(np.argmax(np.where(left, depths.max(axis=0), -np.inf)))
            body, start, count = next(b for b in bodies if b[1] <= i < b[1] + b[2])
            j = next(j for j, (mask, _) in enumerate(started) if mask[i])
            others = [everything[k][0] for k in range(len(everything)) if k != j and again[k][i]]
            deepest = int(np.argmax(depths[:, i]))
            why = (f"body {body!r} is not allowed where it is: {int(left[start:start + count].sum())} of its particles start "
                   f"inside {shapes[j][0]} at its first pose, and no place outside both it and {_named(others)} was found "
                   f"(one at {np.round(x[i], 6).tolist()} still {depths[deepest, i] / model.spacing:.2g} spacings inside "
                   f"{everything[deepest][0]} after {PLACING_PASSES} passes, each placing it out of one into the other); "
                   "move the body, the tool or the collider apart")
            builder._refuse(shapes[j][1], why, why)
    for j, ((name, origin, _, _, _), (inside, depth)) in enumerate(zip(shapes, started)):
        for body, start, count in bodies if warn else ():
            mine = inside[start:start + count]
            if mine.any():
                deepest = float(depth[start:start + count][mine].max())
                # Those it put them in, not itself (it was named among them, 'which that put
                # inside tool 'wedge' and plane0', where plane0's placing put them back in it).
                later = [everything[k][0] for k in range(len(everything))
                         if k != j and (again[k][start:start + count] & mine).any()]
                then = int((np.any(again, axis=0)[start:start + count] & mine).sum()) if later else 0
                still = kept[start:start + count][mine]
                left = (f"; {int((still > 0.0).sum())} left up to {still.max() / model.spacing:.2g} spacings inside, for the "
                        "contact, where the passes were still getting them out" if (still > 0.0).any() else "")
                table = builder.origins.get(origin)
                where = "" if builder.source is None else f"{builder.source}: {table}: " if table else f"{builder.source}: "
                warnings.warn(f"{where}body {body!r}: {int(mine.sum())} of its particles start inside {name} "
                              f"at its first pose, up to {deepest:.3g} m deep ({deepest / model.spacing:.3g} spacings); they "
                              "are placed on its surface, their rest positions with them"
                              + (f" ({then} of them, which that put inside {_named(later)}, then out of "
                                 f"{'it' if len(later) == 1 else 'each'} in turn{left})" if then else "")
                              + ", so the body starts unstrained (left inside, the first step moved them out and the strain "
                              "flung the body); start bodies outside the tools", UserWarning, stacklevel=4)
    return moved


def _check_pins_at_rest(model, builder) -> None:
    """Refuse a pinned set whose motion does not start at the set's rest pose (its rest
    centroid, identity orientation): a pinned particle is placed at ``p(t) + R(t) (X - c)``,
    so a first keyframe (or a ``Velocity`` position, or a scripted pose at t = 0) elsewhere
    moved the whole set there in the first step. A clamp keyed from the origin jumped 0.1 m
    off its beam, which then fell free of it, and the run reported nothing. ``builder``
    (the first world's): one read from a scene file names the file and the set's table."""
    ts = model.tools
    x = np.asarray(model.particle_x0, dtype=np.float64)
    pin_of = ts.pin.numpy()
    for j, ps in enumerate(ts.pins):
        k = len(ts.colliders) + j
        p, q = ts.pose_at(k, 0.0)
        p, q = np.asarray(p, dtype=np.float64), np.asarray(q, dtype=np.float64)
        c = x[np.asarray(ps.indices)].mean(axis=0)  # in float64: the model's copy is in its precision
        # A thousandth of a spacing, and the pose's own rounding in the model's precision (a
        # held set 1 km out: a float32 centroid is 6e-5 m from the float64 one).
        tol = 1e-3 * model.spacing + 2.0 * float(np.spacing(model.types.np_dtype(np.abs(c).max())))
        xs = x[pin_of == k]
        moved = np.linalg.norm(p + (xs - c) @ tools.quat_to_matrix(q / np.linalg.norm(q)).T - xs, axis=1)
        if moved.max() > tol:
            why = (f"pinned set {ts.names[k]!r} is not allowed to start away from its rest pose: its "
                   f"{type(ts.motions[k]).__name__} motion puts its frame at position {np.round(p, 9).tolist()}, orientation "
                   f"{np.round(q, 9).tolist()} at t = 0, which moves its particles up to {moved.max():.3g} m from where they "
                   f"were built; its rest pose is its centroid {np.round(c, 9).tolist()} with orientation (0, 0, 0, 1) (a "
                   f"pinned set's frame moves it as x = p(t) + R(t) (X - centroid)): start the motion there")
            builder._refuse(("pin", ps.name), why, _pin_rest_key(ts.names[k], ts.motions[k], p, q, c, moved.max(), tol) or why)


def _pin_rest_key(name: str, motion, p, q, c, moved: float, tol: float) -> str | None:
    """``_check_pins_at_rest``'s refusal worded for a scene file's keys (the file's other
    refusals name the key, ``keyframe_times = [...]``; this one repeated the Python API's
    text): the keyframe the set starts at and what to give it, or ``None`` where no
    keyframe is the pose at t = 0 (a file's velocity motion always starts at rest)."""
    if not isinstance(motion, tools.Keyframes):
        return None
    a, b, w = tools.sample_times(motion.times, 0.0)
    # The centroid to as many decimals as the check resolves: [-0.090000004, 0.099999999] read
    # as a value to copy digit by digit, where [-0.09, 0.1] is accepted.
    c = np.round(c, max(0, math.ceil(-math.log10(tol / 10.0)))) + 0.0
    rest = f"its rest pose, its centroid {c.tolist()} with orientation [0, 0, 0, 1]"
    tail = (f"which moves its particles up to {moved:.3g} m from where they were built; a pinned set must start at {rest} "
            "(its frame moves it as x = p(t) + R(t) (X - centroid))")
    if w != 0.0:  # t = 0 falls between two keyframes
        return (f"keyframe_times = {checks.shorten(list(motion.times))!r} is not allowed here: keyframes {a} and {b} put the "
                f"frame of pinned set {name!r} at position {np.round(p, 9).tolist()}, orientation {np.round(q, 9).tolist()} at t = 0, "
                f"{tail}: start the keyframes there")
    kp = np.asarray(motion.positions[a], dtype=np.float64)
    kq = np.asarray(motion.orientations[a], dtype=np.float64)
    off, fix = [], []
    if np.linalg.norm(kp - c) > tol or abs(kq[3]) / np.linalg.norm(kq) >= 1.0 - 1e-12:
        off.append(f"keyframe_positions[{a}] = {np.round(kp, 9).tolist()}")
        fix.append(f"keyframe_positions[{a}] = {c.tolist()}")
    if abs(kq[3]) / np.linalg.norm(kq) < 1.0 - 1e-12:
        off.append(f"keyframe_orientations[{a}] = {np.round(kq, 9).tolist()}")
        fix.append(f"keyframe_orientations[{a}] = [0, 0, 0, 1]")
    return (f"{' and '.join(off)} {'is' if len(off) == 1 else 'are'} not allowed: pinned set {name!r} starts there "
            f"(keyframe_times[{a}] = {motion.times[a]:g}, its pose at t = 0), {tail}: give {' and '.join(fix)}")


def _closer_than(points: np.ndarray, body: np.ndarray, r: float):
    """``(i, j)``, two particles of different bodies closer than ``r``, or ``(None, None)``:
    points binned in cells of ``r``, each compared with those of its 27 neighbouring cells."""
    cells = np.floor(points / r).astype(np.int64)
    cells -= cells.min(axis=0) - 1
    dims = cells.max(axis=0) + 2
    if float(dims[0]) * float(dims[1]) * float(dims[2]) > 2.0**62:  # a scene too wide to key its cells
        return None, None
    key = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                near = key + (dx * dims[1] + dy) * dims[2] + dz
                lo = np.searchsorted(sorted_key, near, "left")
                hi = np.searchsorted(sorted_key, near, "right")
                for k in range(int((hi - lo).max(initial=0))):
                    has = lo + k < hi
                    i = np.flatnonzero(has)
                    j = order[lo[has] + k]
                    d = points[i] - points[j]
                    hit = np.flatnonzero((body[i] != body[j]) & ((d * d).sum(axis=1) < r * r))
                    if hit.size:
                        return int(i[hit[0]]), int(j[hit[0]])
    return None, None


def finalize_worlds(builders: Sequence[SceneBuilder], device="cpu", dtype=wp.float32, requires_grad: bool = False,
                    _guards_only: bool = False) -> Model:
    """One ``Model`` of ``len(builders)`` worlds: world ``w`` is ``builders[w]``'s scene.

    Worlds are independent simulations in one set of arrays: particles, bodies and
    materials world after world (``model.world_particles(w)``, ``model.world_materials(w)``),
    neighbour lists (so SPH) never crossing worlds, every step advancing all of them in
    the same launches. The builders must agree on spacing, support radius, gravity,
    ``max_neighbors``, ``bodies_interact``, colliders, tools and pinned sets (a world is a
    scene at the same place, colliders and tools are shared; tool reactions are per world). Bodies keep their names with one world; with several,
    body ``name`` of world ``w`` is ``"w<w>/name"``.
    """
    requires_grad = checks.boolean("requires_grad", requires_grad)
    if isinstance(builders, SceneBuilder) or not isinstance(builders, Sequence) or len(builders) < 1:
        raise ValueError(f"builders = {checks.shorten(builders)!r} is not allowed: must be a non-empty list of SceneBuilder")
    for k, b in enumerate(builders):
        if not isinstance(b, SceneBuilder):
            raise ValueError(f"builders[{k}] = {checks.shorten(b)!r} is not allowed: must be a SceneBuilder")
        if not b._bodies:
            raise ValueError("the scene has no bodies: add one with add_box, add_sphere, ... before finalize()")
    first = builders[0]
    for k, b in enumerate(builders[1:], start=1):
        for name in _SHARED:
            if getattr(b, name) != getattr(first, name):
                raise ValueError(
                    f"builders[{k}].{name} = {checks.shorten(getattr(b, name))!r} is not allowed: every world must have the "
                    f"{name} of builders[0] ({getattr(first, name)!r})"
                )
    for k, b in enumerate(builders[1:], start=1):
        # Tools are shared by the worlds like the static colliders (one motion, one set of
        # differentiable parameters); each world reports its own reaction.
        if _tool_signature(b) != _tool_signature(first):
            raise ValueError(
                f"builders[{k}] tools and pinned sets are not allowed to differ from builders[0]'s: every world "
                "meets the same tools (same names, shapes, motions, friction; pinned sets of the same name, "
                "motion and particle count)"
            )
    # Overlap is checked within each world only: worlds overlap in space by design.
    for b in {id(b): b for b in builders}.values():
        if not _guards_only:
            b._check_overlap()
    scalar = scalar_type(dtype)
    for b in {id(b): b for b in builders}.values():
        b._check_precision(scalar)
        b._check_mesh_tool_reach(scalar)
    try:
        dev = wp.get_device(device)
    except Exception as e:  # noqa: BLE001 (Warp raises several kinds)
        raise ValueError(f"device = {checks.shorten(device)!r} is not allowed: {checks.shorten_text(e)}") from None
    several = len(builders) > 1
    velocities, mat_ids, body_ids, world_ids = [], [], [], []
    materials: list[Material] = []
    bodies: list[Body] = []
    fields = []
    mat_start = [0]
    count = 0
    same_fields = all(b.force_fields == first.force_fields for b in builders)
    for w, b in enumerate(builders):
        m0, b0 = len(materials), len(bodies)
        velocities += b._velocities
        mat_ids += [ids + m0 for ids in b._material_ids]
        for k, body in enumerate(b._bodies):
            name = f"w{w}/{body.name}" if several else body.name
            bodies.append(Body(name=name, start=count, count=body.count, material=body.material + m0, kind=body.kind, world=w,
                               floor_material=body.floor_material + m0 if body.floor_material >= 0 else -1,
                               ghost_floor=body.ghost_floor, ghost_plane=body.ghost_plane, ghost_slip=body.ghost_slip))
            body_ids.append(np.full(body.count, b0 + k, dtype=np.int32))
            world_ids.append(np.full(body.count, w, dtype=np.int32))
            count += body.count
        materials += list(b._materials)
        mat_start.append(len(materials))
        for fld in b.force_fields:
            if fld.body >= 0:
                fields.append(dataclasses.replace(fld, body=fld.body + b0))
            elif not (same_fields and w > 0):
                # A field on every particle acts on all worlds once when the worlds share
                # it; a world's own such field acts on each of its bodies.
                fields += [fld] if same_fields else [dataclasses.replace(fld, body=b0 + k) for k in range(len(b._bodies))]
    try:
        _check_memory(count, first.max_neighbors, dev)
    except ValueError as e:
        first._refuse(("scene",), str(e), str(e))  # a scene file's: its spacing and bodies
    placed = {}
    for b in {id(b): b for b in builders}.values():  # finalize(worlds=W) repeats one builder W times
        _check_outside_colliders(b)
        # The resolution check's build (_guards_only) places as finalize does, silently: the
        # scene's own finalize warns, and a load_scene warned twice, once from inside the check.
        placed[id(b)] = _place_on_colliders(b, warn=not _guards_only)
    model = Model(
        positions=np.concatenate([placed[id(b)] for b in builders]),
        velocities=np.concatenate(velocities),
        particle_material=np.concatenate(mat_ids),
        particle_body=np.concatenate(body_ids),
        materials=materials,
        bodies=bodies,
        spacing=first.spacing,
        support_radius=first.support_radius,
        gravity=first.gravity,
        planes=first.planes,
        spheres=first.spheres,
        boxes=first.boxes,
        max_neighbors=first.max_neighbors,
        bodies_interact=first.bodies_interact,
        device=dev,
        scalar=scalar,
        requires_grad=requires_grad,
        particle_world=np.concatenate(world_ids),
        world_material_start=mat_start,
        fit_weight=first.fit_weight,
    )
    model.force_fields = fields
    model.fit, model.contact_ramp, model.hourglass = first.fit, first.contact_ramp, first.hourglass
    if first.tools or first.pins:
        model.tools = tools.ToolSet(model, first.tools, first.pins, world_pins=[[p.indices for p in b.pins] for b in builders])
        _check_outside_tools(model, builders)
        # Once per scene, as the static colliders' placing: finalize(worlds=W) repeats one
        # builder W times, and each copy warned by its own name ('w0/plate', 'w1/plate').
        free = model.tools.pin.numpy() < 0
        done = {}
        for w, b in enumerate(builders):
            at = model.world_particles(w)
            if id(b) not in done:
                x = np.asarray(model.particle_x0[at], dtype=np.float64).copy()
                starts = np.cumsum([0] + [body.count for body in b._bodies])
                bodies = [(body.name, int(start), body.count) for body, start in zip(b._bodies, starts)]
                done[id(b)] = x, _place_on_tools(model, b, x, free[at], bodies, warn=not _guards_only)
            x, moved = done[id(b)]
            model.particle_x0[at][moved] = x[moved]
        _check_pins_at_rest(model, first)
    if not _guards_only:
        # _guards_only: scenes.unresolved_bodies, which reads the rest neighbourhoods' guards
        # alone (a search of their own), and checks the overlap only where it would refuse:
        # the rest density's search and the overlap check were 60 % of its cost.
        model.compute_rest_density()
    return model


def replicate_worlds(model: Model, worlds: int, requires_grad: bool | None = None) -> Model:
    """A ``Model`` of ``worlds`` copies of the one-world ``model``, as it is now: its
    initial positions and velocities (``particle_x0``, ``particle_v0``, jitter included),
    rest densities, masses and volumes, current parameter values (``parameter_values()``, which a fit may have
    changed) and force fields. World ``w``'s copy of material ``k`` is material
    ``w * len(model.materials) + k`` (``model.world_materials(w)``). For the multi-start fit
    (``fit(..., starts=K, worlds=True)``), which has a model rather than its builder."""
    if not isinstance(model, Model):
        raise ValueError(f"model = {checks.shorten(model)!r} is not allowed: must be a warp_esph.Model")
    if isinstance(worlds, bool) or not isinstance(worlds, (int, np.integer)) or worlds < 1:
        raise ValueError(f"worlds = {checks.shorten(worlds)!r} is not allowed: must be an integer >= 1")
    if worlds > MAX_WORLDS:
        # As finalize(worlds=): 1e9 spent minutes building the list of bodies before any memory was asked for.
        raise ValueError(f"worlds = {checks.shorten(worlds)!r} is not allowed: must be at most {MAX_WORLDS}")
    if model.world_count != 1:
        raise ValueError(f"model is not allowed: it already has {model.world_count} worlds; replicate a one-world model")
    if model.tools is not None:
        raise ValueError("model is not allowed: it has moving tools or pinned sets, which act on one world; "
                         "build one model per scene with tools")
    W, n, M, B = int(worlds), model.particle_count, len(model.materials), len(model.bodies)
    _check_memory(n * W, model.max_neighbors, model.device, worlds=W)
    several = W > 1
    bodies = []
    for w in range(W):
        for b in model.bodies:
            bodies.append(dataclasses.replace(b, name=f"w{w}/{b.name}" if several else b.name, start=b.start + w * n,
                                              material=b.material + w * M, world=w,
                                              floor_material=b.floor_material + w * M if b.floor_material >= 0 else -1))
    out = Model(
        positions=np.tile(model.particle_x0, (W, 1)),
        velocities=np.tile(model.particle_v0, (W, 1)),
        particle_material=np.concatenate([model.particle_material_np + w * M for w in range(W)]),
        particle_body=np.concatenate([model.particle_body_np + w * B for w in range(W)]),
        materials=list(model.materials) * W,
        bodies=bodies,
        **model.settings(),
        requires_grad=model.requires_grad if requires_grad is None else checks.boolean("requires_grad", requires_grad),
        particle_world=np.repeat(np.arange(W, dtype=np.int32), n),
        world_material_start=[w * M for w in range(W + 1)],
    )
    out._fit, out.contact_ramp, out.hourglass = model._fit, model.contact_ramp, model.hourglass
    # A field on every particle acts once on all worlds; one on a body acts on each copy.
    out.force_fields = [f for f in model.force_fields if f.body < 0]
    out.force_fields += [dataclasses.replace(f, body=f.body + w * B) for w in range(W) for f in model.force_fields if f.body >= 0]
    for name, values in model.parameter_values().items():
        getattr(out, name).assign(np.tile(values, W).astype(model.types.np_dtype))
    # The per-particle arrays as they are now, as the parameters: a mass written after the build
    # (in place, or set) ran in the model and not in its worlds.
    for name in ("particle_rest_density", "particle_mass", "particle_volume"):
        getattr(out, name).assign(np.tile(getattr(model, name).numpy(), W))
    return out
