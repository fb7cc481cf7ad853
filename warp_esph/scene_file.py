"""Scene files: the TOML schema (every key each table may hold, its type, whether it is
required) and the loader that checks a file against it and builds its ``Scene``.

The format is described for users in ``docs/scene_format.md``. ``warp_esph.scenes`` holds
the built-in scenes and re-exports ``Scene`` and ``load_scene_file`` from here.
"""

from __future__ import annotations

import codecs
import dataclasses
import difflib
import json
import math
import os
import re
import sys

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: the same parser as the tomli package
    try:
        import tomli as tomllib
    except ModuleNotFoundError:
        tomllib = None

from . import checks
from .builder import MAX_FLOOR_LAYERS, MAX_NEIGHBORS, SceneBuilder
from .material import (LAB_QUANTITIES, PRESETS, Material, _following_force, _from_young, _lame, from_lab, lab_flow_rate,
                       lab_yield_stress)
from .meshes import check_mesh_file
from .model import CONTACTS, FITS
from .sim.neighbors import MIN_NEIGHBORS
from .sim.smoothing import DEFAULT_FIT_WEIGHT, FIT_WEIGHTS

__all__ = [
    "Scene", "load_scene_file", "SCENE_KEYS", "MATERIAL_KEYS", "BODY_COMMON", "BODY_SHAPES", "COLLIDER_TYPES", "TOP_KEYS",
    "SOLVER_KEYS", "TOOL_COMMON", "TOOL_SHAPES",
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
    ``inputs``: ``(what, path)`` of each file the scene was read from (a scene file and the
    mesh files of its bodies and tools, absolute): a command refuses to write over them.
    ``material_names``: a scene file's name of each material, by index (its table's, or the
    preset's a body names; ``""`` where it has none, as a particle floor's).
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
    inputs: tuple[tuple[str, str], ...] = ()
    material_names: tuple[str, ...] = ()

    def material_index(self, name: str) -> int | None:
        """The index of the material a scene file names ``name`` (``material_names``: its
        ``[materials.NAME]`` table, or the preset a body names), where no body has that name (a
        body's name selects its material first); else None."""
        if name in [body.name for body in self.builder._bodies] or name not in self.material_names:
            return None
        return self.material_names.index(name)

    def __post_init__(self):
        # As a scene file's [scene] name and description: one made in Python took any, and
        # 'evil\u202etxt' went into a sweep's record and a fit's folder and messages.
        check_name("Scene.name", self.name)
        check_description("Scene.description", self.description)


def check_name(param: str, name) -> str:
    """A scene's ``name`` (``param``: ``Scene.name``, a file's ``[scene] name``), refused
    where it is no file name or not one line of visible text (``checks.one_line``)."""
    if not isinstance(name, str) or not name.strip() or name in (".", "..") or any(c in name for c in "/\\\0"):
        # The name makes the default output <name>.usdc: '../../x' wrote two folders up.
        raise ValueError(f"{param} = {checks.shorten(name)!r} is not allowed: it names the default output file, so it "
                         "must be a file name (a string, not empty, no '/', '\\' or '..')")
    # A newline went into the default output's name ('ti\nny.usdc') and split every one-line
    # message naming the scene; a tab or an escape sequence read as terminal control.
    return checks.one_line(param, name, "it names the default output file and the scene in one-line messages")


def check_description(param: str, text) -> str:
    """A scene's ``description`` (``param`` as ``check_name``'s): free text, not a name, so a
    format character that only joins (an emoji sequence's, a Persian word's) is its text;
    one that reorders what follows it is not (``checks.one_line_text``)."""
    role = "it is the scene's one-line description (Scene.description)"
    if not isinstance(text, str):
        raise ValueError(f"{param} = {checks.shorten(text)!r} is not allowed: {role}, so it must be a string")
    return checks.one_line_text(param, text, role)


# ------------------------------------------------------------------ schema
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


class _Hourglass(_Num):
    """Schema type: a finite number in [0, ``checks.MAX_HOURGLASS``] (``[solver] hourglass``; 0: off)."""

    def check(self, value) -> bool:
        return super().check(value) and 0 <= value <= checks.MAX_HOURGLASS

    def describe(self) -> str:
        return f"a number >= 0 and <= {checks.MAX_HOURGLASS:g} (0: off)"


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


class _List:
    """Schema type: an array whose items all pass ``item`` (``length``: exact item count)."""

    def __init__(self, item, what: str, length: int | None = None):
        self.item, self.what, self.length = item, what, length

    def check(self, value) -> bool:
        return isinstance(value, list) and (self.length is None or len(value) == self.length) and all(self.item.check(v) for v in value)

    def describe(self) -> str:
        return self.what


QUAT = _List(NUM, "an array of 4 numbers (x, y, z, w)", 4)
NUMS, INTS = _List(NUM, "an array of numbers"), _List(INT, "an array of integers")
VEC3S, QUATS = _List(VEC3, "an array of 3-number arrays"), _List(QUAT, "an array of 4-number arrays (x, y, z, w)")
REGION = _List(VEC3, "an array of two 3-number arrays [lo, hi]", 2)

#: Every key a scene file may hold, per table: name -> (type, required).
SCENE_KEYS = {
    "name": (STR, False), "description": (STR, False), "spacing": (NUM, False), "support_radius": (NUM, False),
    "gravity": (VEC3, False), "max_neighbors": (INT, False), "frames": (INT, False), "fps": (NUM, False), "dt": (NUM, False),
}
MATERIAL_KEYS = {
    "preset": (STR, False), "E": (NUM, False), "nu": (NUM, False), "mu": (NUM, False), "lam": (NUM, False),
    "yield_stress": (NUM_INF, False), "flow_rate": (NUM, False), "hardening": (NUM, False), "density": (NUM, False),
    "pressure_stiffness": (NUM, False), "viscosity": (NUM, False), "model": (STR, False), "clamp_pressure": (BOOL, False),
    "deformation": (STR, False), "elastic_force": (STR, False), "pressure_force": (STR, False),
    "pair_repulsion": (NUM, False), "shear_yield_stress": (NUM, False), "uniaxial_yield_stress": (NUM, False), "plastic_viscosity": (NUM_INF, False),
}
#: A lab's values, which set ``yield_stress`` and ``flow_rate`` as ``Material.from_rheology``
#: does, from the table's final ``mu`` (a preset's where the table gives no moduli).
RHEOLOGY_KEYS = ("shear_yield_stress", "uniaxial_yield_stress", "plastic_viscosity")
#: ``floor_margin`` puts a particle floor under the body (``SceneBuilder.add_particle_floor``;
#: ``floor_layers`` its layers, default ceil(support_radius / spacing); ``floor_elastic`` its
#: ``elastic``, default false; ``floor_ghost`` its ``ghost`` and ``floor_slip`` its ``slip``,
#: default false).
BODY_COMMON = {"shape": (STR, True), "material": (STR, True), "name": (STR, False), "velocity": (VEC3, False),
               "angular_velocity": (VEC3, False), "floor_margin": (NUM, False), "floor_layers": (INT, False),
               "floor_elastic": (BOOL, False), "floor_ghost": (BOOL, False), "floor_slip": (BOOL, False)}
FLOOR_KEYS = ("floor_margin", "floor_layers", "floor_elastic", "floor_ghost", "floor_slip")
BODY_SHAPES = {
    "box": {"center": (VEC3, True), "size": (VEC3, True)},
    "sphere": {"center": (VEC3, True), "radius": (NUM, True)},
    "cylinder": {"center": (VEC3, True), "radius": (NUM, True), "height": (NUM, True), "axis": (STR, False)},
    "star": {"center": (VEC3, True), "outer_radius": (NUM, True), "inner_radius": (NUM, True), "thickness": (NUM, True), "points": (INT, False)},
    "mesh": {"file": (STR, True), "scale": (NUM, False), "translation": (VEC3, False), "prim_path": (STR, False)},
}
COLLIDER_TYPES = {
    "ground": {"height": (NUM, False), "friction": (NUM, False), "images": (BOOL, False), "shear_cap": (NUM, False)},
    "plane": {"normal": (VEC3, True), "offset": (NUM, True), "friction": (NUM, False)},
    "sphere": {"center": (VEC3, True), "radius": (NUM, True), "friction": (NUM, False)},
    "box": {"center": (VEC3, True), "half_extents": (VEC3, True), "friction": (NUM, False)},
}
#: Keys of a tool's or pinned set's rigid motion (tools.py): a constant velocity, or keyframes.
MOTION_KEYS = {
    "velocity": (VEC3, False), "angular_velocity": (VEC3, False), "keyframe_times": (NUMS, False),
    "keyframe_positions": (VEC3S, False), "keyframe_orientations": (QUATS, False),
}
#: Keys of every tool, whatever its shape.
TOOL_COMMON = {
    "shape": (STR, True), "name": (STR, False), "position": (VEC3, False), "orientation": (QUAT, False),
    "friction": (NUM, False), "static_friction": (NUM, False), **MOTION_KEYS,
}
#: Keys of each tool shape (``tools.KINDS``; ``SceneBuilder.add_tool``): a key of another
#: shape is refused, not ignored (a box given a radius was built without a word about it).
TOOL_SHAPES = {
    "plane": {"normal": (VEC3, False)},
    "box": {"half_extents": (VEC3, True)},
    "sphere": {"radius": (NUM, True)},
    "capsule": {"radius": (NUM, True), "half_height": (NUM, True)},
    "cylinder": {"radius": (NUM, True), "half_height": (NUM, True)},
    "mesh": {"file": (STR, True), "scale": (NUM, False), "prim_path": (STR, False)},
}
#: Every key a tool of some shape may hold.
TOOL_KEYS = {**TOOL_COMMON, **{key: kind for keys in TOOL_SHAPES.values() for key, kind in keys.items()}}
#: The keys of a keyframed motion, in the order of ``tools.check_keyframes``' arguments
#: (passed as its ``names``, so that its messages name the file's keys).
KEYFRAME_KEYS = ("keyframe_times", "keyframe_positions", "keyframe_orientations")
PIN_KEYS = {"name": (STR, False), "body": (STR, False), "region": (REGION, False), "indices": (INTS, False), **MOTION_KEYS}
#: ``[solver]``: the numerical options of ``Model`` a scene may choose (``Model.fit``, the
#: contact law ``Model.contact_ramp`` by name: ``model.CONTACTS``, ``Model.hourglass``,
#: ``Model.fit_weight``).
SOLVER_KEYS = {"fit": (STR, False), "contact": (STR, False), "hourglass": (_Hourglass(), False),
               "fit_weight": (STR, False)}
TOP_KEYS = ("scene", "solver", "materials", "bodies", "colliders", "tools", "pins")


def _did_you_mean(key: str, allowed) -> str:
    close = difflib.get_close_matches(key, list(allowed), n=1, cutoff=0.6)
    if not close:
        close = [a for a in allowed if a.lower() == key.lower()]
    return f"; did you mean {close[0]!r}?" if close else ""


def _unheld_in(value):
    """The first number in ``value`` (a key's value: a number, an array, an inline table) that
    no float holds as written (``checks.unheld``), else None."""
    if checks.unheld(value):
        return value
    items = value.values() if isinstance(value, dict) else value if isinstance(value, list) else ()
    return next((found for found in map(_unheld_in, items) if found is not None), None)


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
        typed = _unheld_in(value)
        if typed is not None:
            # 1e-400 was read as 0.0 (hourglass 0: off), 1e400 as inf (an inf-allowed key's "never").
            why = checks.unheld_refusal(typed, key, inf="write inf where inf is meant" if getattr(kind, "allow_inf", False) else "")
            raise ValueError(f"{file}: key {key!r} in {where}: {checks.shorten(typed)} is not allowed: {why}")
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


def _table_key(name: str) -> str:
    """``name`` as a TOML key: bare where TOML allows, else quoted with TOML's escapes (JSON's
    are TOML's), so a table named in a message is the one the file holds, on one line."""
    # Escaped, as repr does, where a name is refused for holding them (a bidirectional control
    # reordered the message around it).
    return name if re.fullmatch(r"[A-Za-z0-9_-]+", name) else checks.escaped(json.dumps(name, ensure_ascii=False))


def _material(file: str, name: str, table: dict) -> Material:
    where = f"[materials.{_table_key(name)}]"
    if checks.breaks_line(name) or checks.hides_text(name):
        # Every message about the material names its table: a newline split them in two.
        raise ValueError(f"{file}: {where} is not allowed: the name {name!r} names the material in one-line messages "
                         f"and in the bodies' material keys, so it must be {checks.ONE_LINE}")
    _check_table(file, where, table, MATERIAL_KEYS)
    fields = {k: v for k, v in table.items() if k not in ("preset", "E", "nu", *RHEOLOGY_KEYS)}
    for a, b in (("yield_stress", "shear_yield_stress"), ("yield_stress", "uniaxial_yield_stress"),
                 ("shear_yield_stress", "uniaxial_yield_stress"), ("flow_rate", "plastic_viscosity")):
        if a in table and b in table:
            raise ValueError(f"{file}: {where} gives {a} and {b}: give one")
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
    try:
        if "E" in table:
            fields["mu"], fields["lam"] = _lame(E, nu)
        if "preset" in table:
            preset = _choice(file, where, "preset", table["preset"], tuple(PRESETS))
            if "pressure_stiffness" not in fields:
                # Recomputed from the (possibly changed) bulk modulus, as for a new material.
                fields["pressure_stiffness"] = None
            # The deformation model's default force, as for a new material (the presets hold
            # the incremental model's, which "additive" refuses), and left defaulted as a preset's.
            made = dataclasses.replace(PRESETS[preset], **_following_force(PRESETS[preset], fields))
        elif "mu" not in fields or "lam" not in fields:
            raise ValueError(f"{file}: {where} needs a preset, E and nu, or mu and lam")
        else:
            made = Material(**fields)
        made = _with_rheology(made, table)
        return _from_young(made, E, nu) if "E" in table else made
    except ValueError as e:
        msg = str(e)
        if msg.startswith(file):
            raise
        # The table's keys are Material's fields: named as the file writes them ('model = ...',
        # not 'Material.model = ...'), as every other table's refusals name their keys.
        msg = msg.removeprefix("Material.")
        raise ValueError(f"{file}: {where}: {msg}") from None


def _with_rheology(material: Material, table: dict) -> Material:
    """``material`` with the yield stress and flow rate of a table's ``RHEOLOGY_KEYS``."""
    given = [key for key in RHEOLOGY_KEYS if key in table]
    if not given:
        return material
    # The Bingham relation holds for these models alone (Material.from_rheology).
    material._check_bingham(given[0])
    # The advice in the file's terms: Material.from_young had been advised to a scene file.
    # plastic_viscosity named only where given: it was advised out of tables without it.
    changes = {"yield_stress": lab_yield_stress(key, table[key], f"leave {key}"
                                                + (" and plastic_viscosity" if "plastic_viscosity" in table else "")
                                                + " out of the table"
                                                + (" and give yield_stress = inf" if "preset" in table else ""))
               for key in ("shear_yield_stress", "uniaxial_yield_stress") if key in table}
    if "plastic_viscosity" in table:
        moduli = (f"E = {table['E']!r}, nu = {table['nu']!r}" if "E" in table else f"mu = {material.mu:g}" if "mu" in table
                  else f"preset {table['preset']!r} (mu = {material.mu:g})")
        changes["flow_rate"] = lab_flow_rate(table["plastic_viscosity"], material.mu, moduli)
    elif "flow_rate" not in table and material.flow_rate == 0.0 and "yield_stress" in changes:
        # An elastic material, the yield stress given without effect: from_rheology refuses
        # this (plastic_viscosity is its required keyword).
        key = given[0]
        raise ValueError(f"{key} = {checks.shorten(table[key])!r} is not allowed without plastic_viscosity or flow_rate: the "
                         f"{'preset' + chr(39) + 's' if 'preset' in table else 'default'} flow_rate is 0, so the material "
                         "never flows and the yield stress has no effect; give plastic_viscosity (Pa s), or "
                         "plastic_viscosity = inf for a material that never flows")
    return from_lab(material.replace(**changes), {field: (key, table[key]) for key in given
                                                  for field in [LAB_QUANTITIES[key][0]]})


def _tagged(file: str, where: str, table, tag: str, kinds: dict) -> tuple[str, str]:
    """Check the key ``tag`` that selects the schema of an array-of-tables entry (a body's
    shape, a collider's type); returns the entry's description for messages and the kind."""
    if not isinstance(table, dict):
        raise ValueError(f"{file}: {where} must be a table, not {table!r}")
    kind = table.get(tag)
    if kind is None:
        raise ValueError(f"{file}: missing key {tag!r} in {where} (one of {', '.join(kinds)})")
    if not isinstance(kind, str):
        raise ValueError(f"{file}: key {tag!r} in {where} must be a string, not {type(kind).__name__} {kind!r}")
    _choice(file, where, tag, kind, tuple(kinds))
    return f"{where} ({tag} {kind!r})", kind


def _body(file: str, k: int, table: dict, builder: SceneBuilder, materials: dict, base_dir: str):
    where, shape = _tagged(file, f"[[bodies]] #{k + 1}", table, "shape", BODY_SHAPES)
    _check_table(file, where, table, {**BODY_COMMON, **BODY_SHAPES[shape]})
    mat_name = table["material"]
    if mat_name in materials:
        material = materials[mat_name]
    elif mat_name in PRESETS:
        material = materials.setdefault(mat_name, Material.preset(mat_name))
    else:
        known = list(materials) + [p for p in PRESETS if p not in materials]
        raise ValueError(
            f"{file}: material = {mat_name!r} in {where} is not allowed: no [materials.{_table_key(mat_name)}] table and no preset "
            f"of that name{_did_you_mean(mat_name, known)} (known: {', '.join(known)})"
        )
    args = {k: v for k, v in table.items() if k not in ("shape", "material") + FLOOR_KEYS}
    try:
        for key in FLOOR_KEYS[1:]:
            if key in table and "floor_margin" not in table:
                raise ValueError(f"{key} = {checks.shorten(table[key])!r} is not allowed without floor_margin: "
                                 f"give floor_margin (m) to put a particle floor under the body")
        if shape == "box":
            index = builder.add_box(material=material, **args)
        elif shape == "sphere":
            index = builder.add_sphere(material=material, **args)
        elif shape == "cylinder":
            index = builder.add_cylinder(material=material, **args)
        elif shape == "star":
            index = builder.add_star(material=material, **args)
        else:
            index = builder.add_mesh(_mesh_file(args.pop("file"), base_dir), material, **args)
        if "floor_margin" in table:
            # Checked here so that the message names the file's keys, not the method's arguments.
            margin = checks.non_negative("floor_margin", table["floor_margin"])
            layers = table.get("floor_layers")
            if layers is not None:
                layers = checks.positive_int("floor_layers", layers, maximum=MAX_FLOOR_LAYERS)
            try:
                builder.add_particle_floor(index, margin=margin, layers=layers, elastic=table.get("floor_elastic", False),
                                           ghost=table.get("floor_ghost", False), slip=table.get("floor_slip", False))
            except ValueError as e:
                # The method names its arguments; the file's keys are floor_<argument>.
                msg = str(e)
                # Every argument it names, not only the first: 'floor_elastic = True is not allowed with
                # ghost = True' named a key the file has not.
                raise ValueError(re.sub(r"\b(margin|layers|elastic|ghost|slip) = ", r"floor_\1 = ", msg)) from None
    except ValueError as e:
        raise ValueError(f"{file}: {where}: {e}") from None
    builder.origins[("body", index)] = where


def _collider(file: str, k: int, table: dict, builder: SceneBuilder):
    where, kind = _tagged(file, f"[[colliders]] #{k + 1}", table, "type", COLLIDER_TYPES)
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
        msg = str(e)
        again = re.match(r"add_(?:ground|plane)\(.*\) is not allowed: it is plane(\d+), ", msg)
        if again:
            # The file's reader wrote no call: the table it repeats.
            msg = f"it is {builder.origins.get(('plane', int(again[1])), 'plane' + again[1])}, {msg[again.end():]}"
        raise ValueError(f"{file}: {where}: {msg}") from None
    kind = {"ground": "plane"}.get(kind, kind)
    builder.origins[(kind, len({"plane": builder.planes, "sphere": builder.spheres, "box": builder.boxes}[kind]) - 1)] = where


def _motion(args: dict):
    """A ``tools`` motion from the motion keys in ``args`` (removed from it); None: static."""
    from . import tools  # noqa: PLC0415

    kf = {k: args.pop(k) for k in KEYFRAME_KEYS if k in args}
    vel = {k: args.pop(k) for k in ("velocity", "angular_velocity") if k in args}
    if kf and vel:
        raise ValueError("velocity/angular_velocity and keyframe_* are not allowed together: give one motion")
    if kf:
        if "keyframe_times" not in kf or "keyframe_positions" not in kf:
            raise ValueError("keyframe_times and keyframe_positions are both needed for a keyframed motion")
        # Checked under the file's names first: tools.Keyframes names its own arguments.
        tools.check_keyframes(kf["keyframe_times"], kf["keyframe_positions"], kf.get("keyframe_orientations"), KEYFRAME_KEYS)
        return tools.Keyframes(kf["keyframe_times"], kf["keyframe_positions"], kf.get("keyframe_orientations"))
    if vel:
        return tools.Velocity(vel.get("velocity", (0.0, 0.0, 0.0)), vel.get("angular_velocity", (0.0, 0.0, 0.0)))
    return None


def _tool(file: str, k: int, table: dict, builder: SceneBuilder, base_dir: str):
    where, shape = _tagged(file, f"[[tools]] #{k + 1}", table, "shape", TOOL_SHAPES)
    schema = {**TOOL_COMMON, **TOOL_SHAPES[shape]}
    for key in table:
        if key in TOOL_KEYS and key not in schema:
            takes = ", ".join(TOOL_SHAPES[shape]) or "no shape keys"
            owners = [s for s, keys in TOOL_SHAPES.items() if key in keys]
            owners = f"a {owners[0]} tool" if len(owners) == 1 else f"{', '.join(owners[:-1])} and {owners[-1]} tools"
            raise ValueError(f"{file}: key {key!r} in {where} is not allowed: a {shape} tool takes {takes} "
                             f"({key} is a key of {owners})")
    if any(key in table for key in KEYFRAME_KEYS):
        for key in ("position", "orientation"):
            if key in table:
                # Keyframes are absolute poses: a tool's position would be dropped.
                raise ValueError(f"{file}: key {key!r} in {where} is not allowed with keyframe_*: the keyframes give "
                                 "the tool's pose at every time; put it in the first keyframe")
    _check_table(file, where, table, schema)
    args = dict(table)
    shape = args.pop("shape")
    try:
        motion = _motion(args)
        if "file" in args:
            args["mesh"] = _mesh_file(args.pop("file"), base_dir)
        if "orientation" in args:
            args["orientation"] = tuple(args["orientation"])
        builder.add_tool(shape, motion=motion, **args)
    except ValueError as e:
        raise ValueError(f"{file}: {where}: {e}") from None
    builder.origins[("tool", builder.tools[-1].name)] = where


def _in_folder(source: str, base_dir: str) -> str:
    """A mesh file's path: one relative to the scene file is in the scene file's folder."""
    return source if os.path.isabs(source) else os.path.join(base_dir, source)


def _mesh_file(source: str, base_dir: str) -> str:
    """``_in_folder``, refused by the file's key where a relative path names no file there: the
    mesh's refusal named the joined path alone, and did not say it is read from the scene
    file's folder, not the working folder. A folder, an unknown extension or an absolute path
    to nothing likewise, as written: it was named by add_mesh's ``source`` or add_tool's ``mesh``."""
    path = _in_folder(source, base_dir)
    if not os.path.isabs(source) and not os.path.lexists(path):
        # (The message names the scene file first, and so its folder: the folder's path again,
        # and the joined one, made three long paths of one line.)
        raise ValueError(f"file = {checks.shown_path(source)} is not allowed: there is no such file; a relative path is "
                         f"read from the scene file's folder, not the working folder (give an absolute path for another)"
                         f"{checks.tilde_note(source)}")
    check_mesh_file(path, "file", source)
    return path


def _pin(file: str, k: int, table: dict, builder: SceneBuilder):
    where = f"[[pins]] #{k + 1}"
    _check_table(file, where, table, PIN_KEYS)
    args = dict(table)
    try:
        motion = _motion(args)
        builder.pin(args.pop("indices", None), motion=motion, **args)
    except ValueError as e:
        raise ValueError(f"{file}: {where}: {e}") from None
    builder.origins[("pin", builder.pins[-1].name)] = where


def _what_it_is(path) -> str:
    """What a file that is no TOML is, by its name, and the command that reads it: a run's
    output or a checkpoint given where the scene goes was only 'not UTF-8 text (byte 16)'."""
    suffix = os.path.splitext(path)[1].lower()
    if suffix in (".usd", ".usda", ".usdc", ".usdz"):
        return ("; it is a USD file, a run's output: 'warp-esph render' draws it, 'warp-esph export' exports it, "
                "'warp-esph fit SCENE --target' fits to it; a scene file is TOML (docs/scene_format.md)")
    if suffix == ".npz":
        return ("; it is a .npz file, a checkpoint's or a fit target's: 'warp-esph run --resume' resumes a checkpoint; "
                "a scene file is TOML (docs/scene_format.md)")
    return ""


def load_scene_file(path, scale: float = 1.0) -> Scene:
    """Read a TOML scene file (format: ``docs/scene_format.md``).

    ``scale`` divides the spacing (and an explicit support radius) as for built-in
    scenes. Any problem — unreadable file, TOML syntax, unknown or misspelt key, wrong
    type, bad value — raises a ``ValueError`` that names the file, the table and the key.
    """
    scale = checks.positive("scale", scale)
    path = os.fspath(path)
    # The file as every message names it: a long path cut to its ends (a 5000-character one
    # wrote a 5 kB line).
    file = str(checks.shown_path(path, quote=False))
    if tomllib is None:
        raise ValueError(f"cannot read scene file {checks.shown_path(path)}: reading TOML needs Python >= 3.11 or the tomli package")
    mark, utf16 = 0, False
    try:
        with open(path, "rb") as fh:
            raw = fh.read()
        # Notepad's UTF-8 starts with a byte-order mark, which TOML does not take: it was
        # 'invalid TOML: Invalid statement (at line 1, column 1)', of a first line that reads right.
        mark = len(codecs.BOM_UTF8) if raw.startswith(codecs.BOM_UTF8) else 0
        # UTF-16 (Excel's 'Unicode Text', PowerShell 5's '>') was 'not UTF-8 text (byte 0)',
        # and without its mark 'Invalid initial character for a key part'.
        codec = checks.text_codec(raw)
        utf16 = codec != "utf-8-sig"
        # A number no float holds (1e-400, 1e400) read as a TypedNumber, refused in _check_table.
        data = tomllib.loads(raw.decode(codec) if utf16 else raw[mark:].decode("utf-8"), parse_float=checks.read_number)
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"{file}: invalid TOML: {e}{_what_it_is(path)}") from None
    except UnicodeDecodeError as e:
        raise ValueError(f"{file}: invalid TOML: not {'UTF-16' if utf16 else 'UTF-8'} text (byte {mark + e.start})"
                         f"{_what_it_is(path)}") from None
    except RecursionError:
        raise ValueError(f"{file}: invalid scene file: arrays or tables nested too deeply to read") from None
    except OSError as e:
        raise ValueError(f"cannot read scene file {checks.shown_path(path)}: {e.strerror or e}{checks.tilde_note(path)}") from None
    for key in data:
        if key not in TOP_KEYS:
            raise ValueError(f"{file}: unknown key {key!r} at the top level{_did_you_mean(key, TOP_KEYS)} (allowed: {', '.join(TOP_KEYS)})")
    scene = _check_table(file, "[scene]", data.get("scene", {}), SCENE_KEYS)
    solver = _check_table(file, "[solver]", data.get("solver", {}), SOLVER_KEYS)
    fit = solver.get("fit")
    if fit is not None:
        _choice(file, "[solver]", "fit", fit, FITS)
    contact = solver.get("contact")
    if contact is not None:
        _choice(file, "[solver]", "contact", contact, tuple(CONTACTS))
    hourglass = solver.get("hourglass")
    fit_weight = solver.get("fit_weight", DEFAULT_FIT_WEIGHT)
    _choice(file, "[solver]", "fit_weight", fit_weight, FIT_WEIGHTS)
    materials_table = data.get("materials", {})
    if not isinstance(materials_table, dict):
        raise ValueError(f"{file}: 'materials' must be a table of [materials.NAME] tables, not {materials_table!r}")
    bodies = data.get("bodies", [])
    colliders = data.get("colliders", [])
    tool_tables, pin_tables = data.get("tools", []), data.get("pins", [])
    for key, value in (("bodies", bodies), ("colliders", colliders), ("tools", tool_tables), ("pins", pin_tables)):
        if not isinstance(value, list):
            raise ValueError(f"{file}: '{key}' must be an array of tables ([[{key}]]), not {type(value).__name__}")
    if not bodies:
        raise ValueError(f"{file}: the scene has no bodies: add at least one [[bodies]] table")

    try:
        spacing = checks.positive("spacing", scene.get("spacing", 0.02)) / scale
        support = scene.get("support_radius")
        wide = scene.get("max_neighbors")
        if wide is not None and not 1 <= wide <= MAX_NEIGHBORS:
            # The builder would say [1, 1024] (or '>= 1' below it), but a file cannot go below the
            # Solver's min_neighbors; 1-5 get the min_neighbors reason below.
            raise ValueError(f"max_neighbors = {wide} is not allowed: must be an integer in [{MIN_NEIGHBORS}, {MAX_NEIGHBORS}]")
        builder = SceneBuilder(
            spacing=spacing,
            gravity=scene.get("gravity", (0.0, -9.81, 0.0)),
            support_radius=None if support is None else checks.positive("support_radius", support) / scale,
            max_neighbors=scene.get("max_neighbors"),
            fit=fit,
            contact=contact,
            hourglass=hourglass,
            fit_weight=fit_weight,
        )
        if builder.max_neighbors < MIN_NEIGHBORS:
            # The Solver refuses it (a file cannot lower its min_neighbors), naming neither the
            # file nor the table: checked here against the Solver's own constant.
            raise ValueError(f"max_neighbors = {builder.max_neighbors} is not allowed: must be at least {MIN_NEIGHBORS}, the "
                             "fewest neighbours the solver keeps a deformation update with (its min_neighbors, which a "
                             "scene file does not set): a row that narrow drops every update")
        frames = checks.positive_int("frames", scene.get("frames", 60))
        fps = checks.positive("fps", scene.get("fps", 30.0))
        dt = scene.get("dt")
        if dt is not None:
            dt = checks.positive("dt", dt)
    except ValueError as e:
        raise ValueError(f"{file}: [scene]: {e}") from None
    # finalize checks the numbers against the model's precision; its refusals name the file too.
    builder.source = file  # (for messages: the path as they show it)
    builder.origins[("scene",)] = "[scene]"

    materials = {name: _material(file, name, table) for name, table in materials_table.items()}
    base_dir = os.path.dirname(os.path.abspath(path))
    for k, table in enumerate(bodies):
        _body(file, k, table, builder, materials, base_dir)
    for k, table in enumerate(colliders):
        _collider(file, k, table, builder)
    for k, table in enumerate(tool_tables):
        _tool(file, k, table, builder, base_dir)
    for k, table in enumerate(pin_tables):
        _pin(file, k, table, builder)
    material_names = [""] * len(builder._materials)
    for name, material in materials.items():
        for k, used in enumerate(builder._materials):
            if used is material:
                material_names[k] = name
                builder.origins[("material", k)] = f"[materials.{_table_key(name)}]" if name in materials_table else f"material {name!r}"
    name = scene.get("name")
    try:
        if name is not None:
            check_name("[scene] name", name)
        if "description" in scene:
            check_description("[scene] description", scene["description"])
    except ValueError as e:
        raise ValueError(f"{file}: {e}") from None
    # Named by its file, the name only labels, as a mesh file's default: cleaned, not refused
    # ('ev\u202eil.toml' was printed as it was in 'run's one-line report, reordering it).
    # So are what Scene refuses in a name, which a file's name may hold ('a\\b.toml', '  .toml').
    if name is None:
        name = checks.one_line_label(os.path.splitext(os.path.basename(path))[0]).replace("\\", "_")
        name = name if name.strip() else "_" * len(name)
    # Of the file's path, which only labels, cleaned as the name (Scene refuses a line break).
    description = scene.get("description") or f"scene file {checks.one_line_label(path)}"
    # The default output is <name>.usdc in the working folder: a bunny.toml beside its mesh
    # bunny.usdc had its mesh replaced by the run, and could not be run again.
    inputs = [("the scene file", os.path.abspath(path))]
    inputs += [(f"the mesh of [[{kind}]] #{k + 1}", os.path.abspath(_in_folder(table["file"], base_dir)))
               for kind, tables in (("bodies", bodies), ("tools", tool_tables))
               for k, table in enumerate(tables) if table.get("shape") == "mesh"]
    return Scene(name, description, builder, frames=frames, fps=fps, dt=dt, inputs=tuple(inputs),
                 material_names=tuple(material_names))
