"""Property-based bad input: whatever values or scene files are given, the answer is a
finished object or a ValueError that names the field — never another exception, a
hang or a crash."""

import math
import string

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import warp_esph as we
from warp_esph.scenes import load_scene_file

# Values of every wrong kind: wrong types, NaN, inf, negative, zero, huge, empty.
ANY_VALUE = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(min_value=-(10**30), max_value=10**30),
    st.text(max_size=5),
    st.booleans(),
    st.none(),
    st.lists(st.floats(allow_nan=True), max_size=4),
    st.just(float("nan")),
    st.just(float("inf")),
    st.just(-1.0),
    st.just(0.0),
    st.just(1e300),
)

MATERIAL_FIELDS = ["mu", "lam", "yield_stress", "flow_rate", "hardening", "density", "pressure_stiffness", "viscosity", "model", "clamp_pressure"]


@settings(max_examples=150, deadline=None)
@given(field=st.sampled_from(MATERIAL_FIELDS), value=ANY_VALUE)
def test_material_field_is_valid_or_named(field, value):
    kwargs = {"mu": 1.0e4, "lam": 1.0e4, field: value}
    try:
        m = we.Material(**kwargs)
    except ValueError as e:
        assert f"Material.{field} = " in str(e), str(e)
        return
    # Accepted: the stored value is a usable one.
    stored = getattr(m, field)
    if isinstance(stored, float):
        assert not math.isnan(stored)
        assert math.isfinite(stored) or field == "yield_stress"


BUILDER_CALLS = {
    "add_box": (("center", (0.0, 0.0, 0.0)), ("size", (0.1, 0.1, 0.1))),
    "add_sphere": (("center", (0.0, 0.0, 0.0)), ("radius", 0.05)),
    "add_cylinder": (("center", (0.0, 0.0, 0.0)), ("radius", 0.05), ("height", 0.1)),
    "add_star": (("center", (0.0, 0.0, 0.0)), ("outer_radius", 0.1), ("inner_radius", 0.05), ("thickness", 0.04)),
    "add_sphere_collider": (("center", (0.0, 0.0, 0.0)), ("radius", 0.05), ("friction", 0.5)),
    "add_box_collider": (("center", (0.0, 0.0, 0.0)), ("half_extents", (0.1, 0.1, 0.1)), ("friction", 0.5)),
    "add_ground": (("height", 0.0), ("friction", 0.5)),
}
DOUGH = we.Material.preset("dough")


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(call=st.sampled_from(sorted(BUILDER_CALLS)), arg=st.integers(0, 3), value=ANY_VALUE)
def test_builder_argument_is_valid_or_named(call, arg, value):
    params = dict(BUILDER_CALLS[call])
    names = list(params)
    name = names[arg % len(names)]
    params[name] = value
    b = we.SceneBuilder(spacing=0.02)
    fn = getattr(b, call)
    try:
        if call.startswith("add_") and "collider" not in call and call != "add_ground":
            fn(material=DOUGH, **params)
        else:
            fn(**params)
    except ValueError as e:
        assert name in str(e) or "has no particles" in str(e) or "inner_radius" in str(e), str(e)


def _toml_value(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v == math.inf else ("-inf" if v == -math.inf else repr(v)))
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return '""'


TOML_VALUES = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True), st.integers(-(10**9), 10**9), st.text(string.ascii_letters, max_size=6),
    st.booleans(), st.lists(st.floats(-10, 10), max_size=4),
)
SCENE_KEYS = ["spacing", "gravity", "frames", "fps", "dt", "support_radius", "max_neighbors", "name", "sapcing", "fsp"]
BODY_KEYS = ["shape", "center", "size", "radius", "material", "velocity", "name", "colour"]


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(
    table=st.sampled_from(["scene", "body"]),
    key=st.sampled_from(SCENE_KEYS + BODY_KEYS),
    value=TOML_VALUES,
)
def test_scene_file_is_valid_or_names_the_key(tmp_path_factory, table, key, value):
    scene = {"spacing": 0.05, "frames": 1, "fps": 30}
    body = {"shape": "box", "center": [0.0, 0.2, 0.0], "size": [0.2, 0.2, 0.2], "material": "dough"}
    (scene if table == "scene" else body)[key] = value
    text = "[scene]\n" + "".join(f"{k} = {_toml_value(v)}\n" for k, v in scene.items())
    text += "\n[[bodies]]\n" + "".join(f"{k} = {_toml_value(v)}\n" for k, v in body.items())
    path = tmp_path_factory.mktemp("scene") / "s.toml"
    path.write_text(text)
    try:
        sc = load_scene_file(path)
    except ValueError as e:
        msg = str(e)
        assert "s.toml" in msg, msg
        assert key in msg or "invalid TOML" in msg or "has no particles" in msg or "support_radius" in msg, msg
        return
    model = sc.builder.finalize()
    assert model.particle_count > 0


@pytest.mark.parametrize("content", [b"", b"\x00\xff\xfe", b"[scene\n", b"[[bodies]]\nshape = 1\n", "[scene]\nspacing = 0.05\n".encode()])
def test_broken_scene_files(tmp_path, content):
    path = tmp_path / "broken.toml"
    path.write_bytes(content)
    with pytest.raises(ValueError, match="broken.toml"):
        load_scene_file(path)
