"""Closed triangle meshes: loading (meshio or USD), checking, and filling with lattice points.

``load_mesh`` returns a cleaned, outward-oriented closed mesh or raises a ``ValueError``
that names the mesh and says what is wrong with it; ``sample_inside`` keeps the lattice
points whose winding number says they are inside.
"""

import contextlib
import io
import os
import pathlib
import re
import warnings

import numpy as np
import warp as wp

from . import checks

USD_EXTENSIONS = (".usd", ".usda", ".usdc", ".usdz")
# No body is 1e30 units across; beyond this the volume and area tests overflow a float.
MAX_SPAN = 1e30


def _meshio_extensions() -> tuple[str, ...]:
    import meshio  # noqa: PLC0415 (meshio is slow to import and only needed for files)

    return tuple(meshio.extension_to_filetypes)


# ----------------------------------------------------------------------------- errors
def _reject(label: str, reason: str):
    raise ValueError(f"mesh {label} is not allowed: {reason}")


# ---------------------------------------------------------------------------- loading
def _is_path(source) -> bool:
    return isinstance(source, (str, bytes)) or hasattr(source, "__fspath__")


def _extension(name: str, known) -> str | None:
    """The longest known extension ``name`` ends with (so ``.vol.gz`` beats ``.gz``)."""
    lower = name.lower()
    matches = [e for e in known if lower.endswith(e)]
    return max(matches, key=len) if matches else None


def mesh_name(source) -> str:
    """A body name from a mesh file's name without its extension ('bunny' for 'bunny.usd')."""
    name = pathlib.Path(os.fsdecode(os.fspath(source))).name
    ext = _extension(name, USD_EXTENSIONS + _meshio_extensions())
    stem = name[: -len(ext)] if ext else pathlib.Path(name).stem
    return stem or name


def check_mesh_file(path: str, name: str = "source", typed: str | None = None) -> bool:
    """Refuses ``path`` where no file is there, it is a folder, or no reader here knows its
    extension, naming it as the caller's parameter ``name`` (add_mesh's ``source``, a tool's
    ``mesh``, a scene file's ``file``) and ``typed``, the path as written (default ``path``).
    True for a USD file, False for one meshio reads."""
    # Named as the caller's parameter: 'mesh' had been named to add_mesh("x"), whose is source,
    # and 'source' to a scene file, whose key is file.
    said = f"{name} = {checks.shown_path(path if typed is None else typed)}"
    if not os.path.exists(path):
        raise ValueError(f"{said} is not allowed: file not found")
    if not os.path.isfile(path):
        raise ValueError(f"{said} is not allowed: it is not a file")
    if _extension(path, USD_EXTENSIONS):
        return True
    meshio_ext = _meshio_extensions()
    if not _extension(path, meshio_ext):
        suffix = pathlib.Path(path).suffix or "(none)"
        allowed = ", ".join(USD_EXTENSIONS + meshio_ext)
        raise ValueError(f"{said} is not allowed: unsupported extension {suffix!r}; must be one of {allowed}")
    return False


def load_mesh(source, prim_path: str | None = None, *, name: str = "source") -> tuple[np.ndarray, np.ndarray]:
    """A closed triangle mesh as ``(points (N, 3) float64, triangles (M, 3) int32)``.

    ``source`` is a file meshio reads, a USD file, or a tuple ``(points, triangles)``.
    Polygons are fan-triangulated and tetrahedral meshes reduced to their surface.
    Coincident and unused vertices are merged or dropped, and the triangles are turned to
    face outward.

    Of a USD file, ``prim_path`` names the Mesh prim to read. Without it the stage's only
    (active) Mesh prim is read, or else the only one the stage shows: those invisible or of
    purpose guide or proxy are left out, and several shown are refused, naming them. The
    prim's local-to-world transform and the stage's metres per unit are applied and the up
    axis is kept; a stage that does not author ``metersPerUnit`` is read in USD's fallback
    unit, centimetres, with a ``UserWarning``.

    ``name``: how a refusal of ``source`` itself (no such file, no known extension, not a path
    or tuple) names it, as the caller's parameter (``add_mesh``'s ``source``, a tool's ``mesh``).
    """
    if prim_path is not None and not isinstance(prim_path, str):
        raise ValueError(f"prim_path = {checks.shorten(prim_path)!r} is not allowed: must be a string such as '/root/bunny' or None")
    if isinstance(source, tuple):
        if prim_path is not None:
            raise ValueError(f"prim_path = {checks.shorten(prim_path)!r} is not allowed: it is only for USD files, not (points, triangles)")
        if len(source) != 2:
            raise ValueError(f"{name} with {len(source)} items is not allowed: a tuple must be (points, triangles)")
        label = "(points, triangles)"
        points, triangles = source
    elif _is_path(source):
        path = os.fsdecode(os.fspath(source))
        label = repr(path)
        if check_mesh_file(path, name):
            points, triangles, prim = _read_usd(label, path, prim_path)
            label = f"{label} (prim {prim!r})"
        else:
            if prim_path is not None:
                raise ValueError(f"prim_path = {checks.shorten(prim_path)!r} is not allowed: it is only for USD files, not {label}")
            points, triangles = _read_meshio(label, path)
    else:
        raise ValueError(
            f"{name} = {checks.shorten(source)!r} is not allowed: must be a mesh file path or a (points, triangles) tuple"
        )
    return _clean(label, points, triangles)


def _as_arrays(label: str, points, triangles) -> tuple[np.ndarray, np.ndarray]:
    try:
        if np.asarray(points).dtype.kind not in "iuf":  # complex lost its imaginary part, strings were parsed
            raise TypeError
        pts = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError):
        _reject(label, "points must be an (N, 3) array of numbers")
    try:
        tri = np.asarray(triangles)
    except (TypeError, ValueError):
        _reject(label, "triangles must be an (M, 3) array of integers")
    if pts.size == 0 or tri.size == 0:
        _reject(label, f"it is empty ({len(pts)} points, {len(tri)} triangles)")
    if pts.ndim != 2 or pts.shape[1] != 3:
        _reject(label, f"points with shape {pts.shape} are not allowed; must be (N, 3)")
    if tri.ndim != 2 or tri.shape[1] != 3:
        _reject(label, f"triangles with shape {tri.shape} are not allowed; must be (M, 3)")
    if tri.dtype.kind not in "iu":
        # Integral floats (from some readers or user code) are accepted, fractions are not.
        if tri.dtype.kind != "f" or not np.all(np.isfinite(tri)) or np.any(tri != np.round(tri)):
            _reject(label, f"triangles of dtype {tri.dtype} are not allowed; must be integer vertex indices")
    return pts, tri.astype(np.int64)


def _fan(counts: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Fan triangulation (v0, vk, vk+1) of polygons given as USD faceVertexCounts/Indices."""
    ntri = counts - 2
    first = np.cumsum(counts) - counts
    face = np.repeat(np.arange(len(counts)), ntri)
    k = np.arange(int(ntri.sum())) - np.repeat(np.cumsum(ntri) - ntri, ntri) + 1
    base = first[face]
    return np.stack([indices[base], indices[base + k], indices[base + k + 1]], axis=1)


def _read_usd(label: str, path: str, prim_path: str | None):
    from pxr import Sdf, Usd, UsdGeom  # noqa: PLC0415 (USD only when a USD file is given)

    full = checks.not_utf8_path(path)
    if full is not None:
        # pxr's refusal was the codec's ("'utf-8' codec can't encode ..."), naming nothing allowed.
        _reject(label, f"USD names its files in UTF-8 text, and {full!r} is not; give a path of UTF-8 text (rename the "
                       "file or its folder)")
    try:
        stage = Usd.Stage.Open(path)
    except Exception as e:  # noqa: BLE001 (pxr raises Tf.ErrorException and others)
        _reject(label, f"pxr cannot open it ({checks.read_reason(e)})")
    if stage is None:
        _reject(label, "pxr cannot open it")
    # EarliestTime reads the default value, or the first sample of animated points.
    time = Usd.TimeCode.EarliestTime()
    if prim_path is None:
        prim = _only_mesh(label, stage, time)
    else:
        if not Sdf.Path.IsValidPathString(prim_path) or not Sdf.Path(prim_path).IsAbsolutePath():
            raise ValueError(f"prim_path = {checks.shorten(prim_path)!r} is not allowed: must be an absolute prim path such as '/root/bunny'")
        prim = stage.GetPrimAtPath(prim_path)
        if not prim.IsValid():
            raise ValueError(f"prim_path = {checks.shorten(prim_path)!r} is not allowed: {label} has no prim there")
        if not prim.IsA(UsdGeom.Mesh):
            raise ValueError(
                f"prim_path = {checks.shorten(prim_path)!r} is not allowed: it is a {prim.GetTypeName() or 'typeless'} prim, not a Mesh"
            )
    mesh = UsdGeom.Mesh(prim)
    where = f"{label} (prim {str(prim.GetPath())!r})"
    try:
        pts = np.array(mesh.GetPointsAttr().Get(time) or [], dtype=np.float64).reshape(-1, 3)
        counts = np.array(mesh.GetFaceVertexCountsAttr().Get(time) or [], dtype=np.int64)
        idx = np.array(mesh.GetFaceVertexIndicesAttr().Get(time) or [], dtype=np.int64)
        xform = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(time), dtype=np.float64)
        meters = float(UsdGeom.GetStageMetersPerUnit(stage))
        meters_authored = UsdGeom.StageHasAuthoredMetersPerUnit(stage)
    except Exception as e:  # noqa: BLE001
        _reject(where, f"pxr cannot read it ({checks.read_reason(e)})")
    if len(pts) == 0 or len(counts) == 0:
        _reject(where, f"it is empty ({len(pts)} points, {len(counts)} faces)")
    if np.any(counts < 3):
        _reject(where, f"{int(np.sum(counts < 3))} faces have fewer than 3 vertices")
    if counts.sum() != len(idx):
        _reject(where, f"faceVertexCounts sum to {int(counts.sum())} but there are {len(idx)} faceVertexIndices")
    if not meters_authored:
        # USD's rule, kept: without the metadata the stage is in centimetres. Most tools author
        # it, so a file without it was often modelled in metres and came in 100 x too small.
        warnings.warn(
            f"mesh {label}: its stage does not author metersPerUnit, so USD's fallback of {meters:g} m per unit "
            f"(centimetres) is assumed (USD's rule); if the mesh is in metres, author metersPerUnit = 1 in the file "
            f"(UsdGeom.SetStageMetersPerUnit)",
            UserWarning, stacklevel=3)
    # USD matrices act on row vectors: p_world = [p, 1] @ M.
    pts = (np.hstack([pts, np.ones((len(pts), 1))]) @ xform)[:, :3] * meters
    return pts, _fan(counts, idx), str(prim.GetPath())


def _only_mesh(label: str, stage, time):
    """The Mesh prim a stage shows, when no prim_path names one.

    The traversal skips inactive prims. A stage's only Mesh prim is taken as it is; of several,
    those the stage does not show (invisible, or of purpose guide or proxy: helpers and
    stand-ins) are left out, and one must remain: taking the first in file order read a hidden
    stand-in, or one part of a model of several, without a word."""
    from pxr import Usd, UsdGeom  # noqa: PLC0415

    found = [p for p in stage.Traverse(Usd.TraverseInstanceProxies()) if p.IsA(UsdGeom.Mesh)]
    if not found:
        _reject(label, "it has no UsdGeom.Mesh prim, so it is not a closed triangle mesh")
    if len(found) == 1:
        return found[0]

    def shown(prim) -> bool:
        img = UsdGeom.Imageable(prim)
        return img.ComputeVisibility(time) != UsdGeom.Tokens.invisible and \
            img.ComputePurpose() not in (UsdGeom.Tokens.guide, UsdGeom.Tokens.proxy)

    visible = [p for p in found if shown(p)]
    if len(visible) == 1:
        return visible[0]

    def paths(prims) -> str:
        named = ", ".join(repr(str(p.GetPath())) for p in prims[:6])
        return named + (f", ... {len(prims) - 6} more" if len(prims) > 6 else "")

    if visible:
        raise ValueError(f"prim_path = None is not allowed: {label} has {len(visible)} visible Mesh prims "
                         f"({paths(visible)}); pass prim_path= the one to read (or make the others invisible)")
    raise ValueError(f"prim_path = None is not allowed: {label} has {len(found)} Mesh prims and none is visible "
                     f"(each is invisible or of purpose guide or proxy: {paths(found)}); pass prim_path= the one to read")


# ------------------------------------------------------------- bounded reading (meshio)
# meshio's readers trust the file: its PLY and OFF readers loop for ever on a header cut
# short (they skip blank lines until a non-blank one comes, and at the end of the file
# none does), and its binary PLY reader walks as many faces as the header declares even
# past the end of the data (400 million faces took longer than 10 minutes). The formats
# read here in-process are the ones whose reader is linear in the file's size once the
# header has been checked against the size; every other format is read in a child
# process with a time limit, so no damaged file can hang the caller.
_CHECKED_FORMATS = (".obj", ".stl", ".ply", ".off")
_PLY_SIZES = {
    "char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
    "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4,
    "int64": 8, "uint64": 8, "double": 8, "float64": 8,
}
_HEADER_LIMIT = 1 << 20  # a PLY header longer than 1 MiB is not one meshio wrote or reads


def _check_ply(label: str, path: str) -> None:
    """Refuses a PLY file whose header is cut short or declares more than the file holds."""
    size = os.path.getsize(path)
    with open(path, "rb") as f:
        head = f.read(min(size, _HEADER_LIMIT))
    end = re.search(rb"^end_header[ \t]*\r?\n", head, re.MULTILINE)
    if not head.startswith(b"ply") or end is None:
        _reject(label, "it is not a PLY file: no 'ply' first line and 'end_header' line in its first 1 MiB")
    lines = [ln.strip() for ln in head[: end.start()].decode("latin-1").splitlines()]
    fmt = next((ln.split()[1] for ln in lines if ln.startswith("format") and len(ln.split()) > 1), None)
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        _reject(label, f"its PLY header has format {fmt!r}; must be ascii, binary_little_endian or binary_big_endian")
    elements = []  # [name, count, smallest bytes per element]
    for ln in lines:
        words = ln.split()
        if words[:1] == ["element"]:
            if len(words) != 3 or not words[2].isdigit():
                _reject(label, f"its PLY header line {ln[:60]!r} is not 'element <name> <count>'")
            elements.append([words[1], int(words[2]), 0])
        elif words[:1] == ["property"]:
            if not elements:
                _reject(label, f"its PLY header has {ln[:60]!r} before any element line")
            # A list may be empty, so it takes at least its count; ASCII needs a digit and a space.
            kinds = words[2:4] if words[1:2] == ["list"] else words[1:2]
            if len(words) < (5 if words[1:2] == ["list"] else 3) or any(k not in _PLY_SIZES for k in kinds):
                _reject(label, f"its PLY header line {ln[:60]!r} is not a property of a known type")
            elements[-1][2] += 2 if fmt == "ascii" else _PLY_SIZES[kinds[0]]
    body = size - end.end()
    needed = sum(count * max(each, 1) for _, count, each in elements)
    if needed > body:
        declared = ", ".join(f"{count} {name}" for name, count, _ in elements)
        _reject(label, f"its PLY header declares {declared}, which need at least {needed} bytes, but {body} follow it")


def _check_off(label: str, path: str) -> None:
    """Refuses an OFF file without its counts line, or with more items than it has bytes."""
    size = os.path.getsize(path)
    with open(path, "rb") as f:
        text = f.read(min(size, _HEADER_LIMIT)).decode("latin-1")
    lines = [ln.strip() for ln in text.splitlines()]
    counts = next((ln.split() for ln in lines[1:] if ln and not ln.startswith("#")), None)
    if not lines or lines[0] != "OFF" or counts is None or len(counts) != 3 or not all(c.isdigit() for c in counts):
        _reject(label, "it is not an OFF file: it must start with 'OFF' and a line '<vertices> <faces> <edges>'")
    if 6 * int(counts[0]) + 8 * int(counts[1]) > size:  # 'x y z' and '3 i j k', a digit and a space each
        _reject(label, f"it declares {counts[0]} vertices and {counts[1]} faces, more than its {size} bytes can hold")


# Generous for a legitimate file (meshio reads tens of MB per second), short for a loop.
_CHILD_SECONDS = 30.0
# The child reads the file and hands back points and cells as arrays: nothing but numpy.
_CHILD = """
import contextlib, io, sys
import numpy as np
import meshio
printed = io.StringIO()
try:
    with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(printed), np.errstate(over="ignore"):
        m = meshio.read(sys.argv[1])
except BaseException as e:
    said = " ".join(printed.getvalue().split())
    # Its words, not its class's name, as checks.read_reason says a reader's exception (this
    # child imports no warp_esph).
    text = " ".join(str(e).split())
    text = said if isinstance(e, SystemExit) and said else (f"no {text}" if isinstance(e, KeyError) and text
                                                            else text or "its reader gave no reason")
    sys.stderr.write(text[:300])
    sys.exit(3)
arrays = {"points": np.asarray(m.points)}
for i, b in enumerate(m.cells):
    if not b.type.startswith("polyhedron"):
        arrays[f"cell{i:06d}_{b.type}"] = np.asarray(b.data)
np.savez(sys.argv[2], **arrays)
"""


def _read_in_child(label: str, path: str):
    import subprocess  # noqa: PLC0415
    import sys  # noqa: PLC0415
    import tempfile  # noqa: PLC0415
    import types  # noqa: PLC0415

    limit = _CHILD_SECONDS + 2.0 * os.path.getsize(path) / 1e6
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "mesh.npz")
        try:
            done = subprocess.run([sys.executable, "-c", _CHILD, path, out], capture_output=True, timeout=limit, check=False)
        except subprocess.TimeoutExpired:
            _reject(label, f"meshio did not finish reading it within {limit:.3g} s (a damaged header declaring more than the file holds?)")
        if done.returncode != 0 or not os.path.exists(out):
            reason = done.stderr.decode("utf-8", "replace").strip().splitlines()
            _reject(label, f"meshio cannot read it ({reason[-1][:300] if reason else f'exit status {done.returncode}'})")
        with np.load(out) as data:
            cells = [types.SimpleNamespace(type=k.split("_", 1)[1], data=data[k]) for k in sorted(data.files) if k != "points"]
            return types.SimpleNamespace(points=data["points"], cells=cells)


def read_meshio(label: str, path: str):
    """A meshio mesh (``points``, ``cells`` with ``type`` and ``data``) read so that no file can hang.

    A file that cannot be read raises ``ValueError`` naming ``label`` and the reason."""
    ext = _extension(path, _CHECKED_FORMATS)
    if ext is None:
        return _read_in_child(label, path)
    if ext == ".ply":
        _check_ply(label, path)
    elif ext == ".off":
        _check_off(label, path)
    import meshio  # noqa: PLC0415

    printed = io.StringIO()
    try:
        # On a ReadError meshio.read prints the reason, then calls sys.exit(1).
        # Its STL reader overflows a uint32 while guessing ASCII vs binary; that is harmless.
        with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(printed), np.errstate(over="ignore"):
            m = meshio.read(path)
    except (Exception, SystemExit) as e:  # noqa: BLE001 (meshio raises ReadError, KeyError, ValueError, ...)
        said = re.sub(r"\s+", " ", printed.getvalue()).strip()
        reason = said if isinstance(e, SystemExit) and said else checks.read_reason(e)
        _reject(label, f"meshio cannot read it ({reason})")
    said = printed.getvalue().strip()
    if said:
        warnings.warn(f"meshio, reading {label}: {said}", stacklevel=4)
    return m


def _read_meshio(label: str, path: str):
    m = read_meshio(label, path)
    tris, tets = [], []
    for block in m.cells:
        kind = block.type
        if kind.startswith("polyhedron"):
            continue  # ragged lists of faces, not a surface
        # Higher-order cells (triangle6, quad8, tetra10) list their corners first.
        data = np.asarray(block.data)
        corners = data.shape[1] if data.ndim == 2 else 0
        if kind.startswith("tetra") and corners >= 4:
            tets.append(data[:, :4])
        elif kind.startswith("triangle") and corners >= 3:
            tris.append(data[:, :3])
        elif kind.startswith("quad") and corners >= 4:
            tris.append(_fan(np.full(len(data), 4), data[:, :4].ravel()))
        elif kind.startswith("polygon") and corners >= 3:
            tris.append(_fan(np.full(len(data), corners), data.ravel()))
    points = np.asarray(m.points, dtype=np.float64)
    if tets:
        tris.append(_tet_surface(points, np.concatenate(tets).astype(np.int64)))
    if not tris:
        kinds = ", ".join(sorted({b.type for b in m.cells})) or "none"
        _reject(label, f"it has no triangles, polygons or tetrahedra (cell types: {kinds})")
    return points, np.concatenate(tris).astype(np.int64)


def _tet_surface(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """The faces used by one tetrahedron only, each facing away from its tetrahedron."""
    if points.shape[1:] == (3,) and len(tets) and 0 <= tets.min() and tets.max() < len(points):
        p = points[tets]
        negative = np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0])) < 0.0
        tets = np.where(negative[:, None], tets[:, [0, 2, 1, 3]], tets)
    faces = np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 3, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 1]]])
    _, first, counts = np.unique(np.sort(faces, axis=1), axis=0, return_index=True, return_counts=True)
    return faces[first[counts == 1]]


# --------------------------------------------------------------------------- checking
def _checked_arrays(label: str, points, triangles) -> tuple[np.ndarray, np.ndarray]:
    pts, tri = _as_arrays(label, points, triangles)
    n = len(pts)
    lo, hi = int(tri.min()), int(tri.max())
    if lo < 0 or hi >= n:
        _reject(label, f"triangle indices must be in [0, {n - 1}] for {n} points, found [{lo}, {hi}]")
    return pts, tri


def _clean(label: str, points, triangles) -> tuple[np.ndarray, np.ndarray]:
    pts, tri = _checked_arrays(label, points, triangles)
    n = len(pts)
    bad = int(np.sum(~np.isfinite(pts).all(axis=1)))
    if bad:
        _reject(label, f"{bad} of its {n} points are not finite")

    # Merge coincident vertices (STL and seam-split meshes repeat them) so that edges
    # shared by two triangles are recognised, and drop unused ones (they would widen the
    # bounding box that is filled with lattice points).
    used = np.unique(tri)
    merged, inverse = np.unique(pts[used], axis=0, return_inverse=True)
    remap = np.zeros(n, dtype=np.int64)
    remap[used] = inverse.reshape(-1)
    tri = remap[tri]
    # A triangle that lost a corner to merging has no area and would break edge counting.
    tri = tri[(tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2])]
    span = float(np.max(merged.max(axis=0) - merged.min(axis=0)))
    if not span <= MAX_SPAN:  # also inf: the difference of two huge finite coordinates
        _reject(label, f"its points span {span:.3g} (file units); must be at most {MAX_SPAN:g} (the volume test cubes it)")
    diag = float(np.linalg.norm(merged.max(axis=0) - merged.min(axis=0)))
    if len(tri) == 0 or diag == 0.0:
        _reject(label, "it is degenerate: all its triangles have zero area")
    a, b, c = merged[tri[:, 0]], merged[tri[:, 1]], merged[tri[:, 2]]
    cross = np.cross(b - a, c - a)
    if np.all(np.linalg.norm(cross, axis=1) <= 1e-12 * diag * diag):
        _reject(label, "it is degenerate: all its triangles have zero area")

    edges = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    _, uses = np.unique(np.sort(edges, axis=1), axis=0, return_counts=True)
    open_edges = int(np.sum(uses != 2))
    if open_edges:
        _reject(label, f"it is not closed ({open_edges} edges are not shared by exactly two triangles)")
    # In a consistently oriented closed mesh each directed edge occurs once; otherwise
    # the winding number is not +-1 inside and the inside test is meaningless.
    _, directed = np.unique(edges, axis=0, return_counts=True)
    flipped = int(np.sum(directed > 1))
    if flipped:
        _reject(label, f"it is not consistently oriented ({flipped} edges run the same way in both their triangles)")

    volumes = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0
    volume = float(np.sum(volumes))
    if abs(volume) <= 1e-9 * diag**3:
        _reject(label, f"it is degenerate: it encloses no volume ({volume:g})")
    if volume < 0.0:
        tri = tri[:, ::-1]  # inward-facing (or mirrored by a transform): turn outward
        volumes = -volumes
    return merged, np.ascontiguousarray(_orient_parts(merged, tri, volumes), dtype=np.int32)


def _orient_parts(points: np.ndarray, tri: np.ndarray, volumes: np.ndarray) -> np.ndarray:
    """``tri`` with every separate part that faces inward turned outward, unless it lies inside
    an outward part (a cavity). The whole mesh's orientation (by its total volume) left a part
    wound the other way facing inward, and the inside test left it empty without a word."""
    part = _parts(len(points), tri)
    labels, per = np.unique(part[tri[:, 0]], return_inverse=True)
    signed = np.bincount(per.reshape(-1), weights=volumes, minlength=len(labels))
    outward = signed > 0.0
    if outward.all():
        return tri
    shell = tri[outward[per.reshape(-1)]]
    out = tri.copy()
    for k in np.flatnonzero(~outward):
        mine = per.reshape(-1) == k
        if _winding_number(points, shell, points[tri[mine][0, 0]]) < 0.5:
            out[mine] = tri[mine][:, ::-1]
    return out


def _parts(n: int, tri: np.ndarray) -> np.ndarray:
    """A label per vertex, equal within each connected part of the triangles (the smallest
    vertex index of the part: min-label propagation with pointer jumping)."""
    label = np.arange(n)
    while True:
        new = label.copy()
        np.minimum.at(new, tri.reshape(-1), np.repeat(label[tri].min(axis=1), 3))
        jumped = new[new]
        while not np.array_equal(jumped, new):
            new, jumped = jumped, jumped[jumped]
        if np.array_equal(new, label):
            return label
        label = new


def _winding_number(points: np.ndarray, tri: np.ndarray, q: np.ndarray) -> float:
    """The winding number of the closed triangles ``tri`` about ``q`` (solid angles, Van
    Oosterom and Strackee): 1 inside an outward surface, 0 outside."""
    a, b, c = (points[tri[:, k]] - q for k in range(3))
    la, lb, lc = (np.linalg.norm(v, axis=1) for v in (a, b, c))
    num = np.einsum("ij,ij->i", a, np.cross(b, c))
    den = la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", b, c) * la + np.einsum("ij,ij->i", c, a) * lb
    return float(np.sum(2.0 * np.arctan2(num, den)) / (4.0 * np.pi))


def signed_volume(points, triangles) -> float:
    """Volume enclosed by a closed triangle mesh (divergence theorem); > 0 if outward."""
    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(triangles)
    a, b, c = p[t[:, 0]], p[t[:, 1]], p[t[:, 2]]
    return float(np.sum(np.einsum("ij,ij->i", a, np.cross(b, c)))) / 6.0


def write_mesh(path, points, triangles) -> None:
    """Writes a triangle mesh with meshio (format from the extension)."""
    import meshio  # noqa: PLC0415

    points, triangles = checks.host_values("points", points), checks.host_values("triangles", triangles)
    # PLY has no 64-bit integers: meshio casts them down itself, printing a warning on stdout.
    index = np.int32 if os.fsdecode(os.fspath(path)).lower().endswith(".ply") else np.int64
    meshio.write_points_cells(
        os.fspath(path), np.asarray(points, dtype=np.float64), [("triangle", np.asarray(triangles, dtype=index))]
    )


# --------------------------------------------------------------------------- sampling
#: How many float64 roundings at a coordinate's magnitude a lattice's count, and a pin region's
#: face written at a layer's value (``tools.select_particles``), allow beside their 1e-9
#: spacings: far from the origin one rounding passes those (at |x| = 1e5 it is 1.5e-11 m, 1.5e-9
#: of a 0.01 spacing), and a box 0.1 m across there had 9 layers in a third of its places.
COORDINATE_ROUNDINGS = 4


def coordinate_round_off(magnitude):
    """How far (m) a float64 coordinate of size ``magnitude`` (m, or an array of them) may lie
    from the value a user writes for it by round-off alone (``COORDINATE_ROUNDINGS``)."""
    return COORDINATE_ROUNDINGS * float(np.finfo(np.float64).eps) * np.abs(magnitude)


def lattice_counts(lo: np.ndarray, hi: np.ndarray, dx: float, reach=None) -> np.ndarray:
    """How many whole dx cells fit in [lo, hi] per axis (floats: inf past the float range).
    An extent a whole number of cells by round-off counts them all: 1e-9 cells near the origin
    (0.1 - 0.04 is 0.06000000000000001), ``coordinate_round_off`` of the faces farther out.
    ``reach``: the magnitude of the coordinates whose round-off the faces carry, where they
    were moved near the origin after it (``sample_inside``); None: the faces' own."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    if reach is None:
        reach = np.maximum(np.abs(lo), np.abs(hi))
    slack = 1e-9 + coordinate_round_off(reach) / dx
    return np.floor((hi - lo) / dx + slack)


def lattice_points(lo: np.ndarray, hi: np.ndarray, dx: float, reach=None) -> np.ndarray:
    """Lattice points centred in the box [lo, hi], one per whole dx^3 cell that fits
    (``lattice_counts``, ``reach`` as there).

    Every body is sampled this way: each particle stands for one cell of material, so a
    shape thinner than one cell along an axis gets no particles.
    """
    extent = hi - lo
    counts = np.maximum(lattice_counts(lo, hi, dx, reach).astype(int), 0)
    start = lo + 0.5 * (extent - (counts - 1) * dx)
    axes = [start[k] + dx * np.arange(counts[k]) for k in range(3)]
    g = np.meshgrid(*axes, indexing="ij")
    return np.stack([a.ravel() for a in g], axis=1)


@wp.kernel(enable_backward=False, module="unique")
def _inside_kernel(
    mesh: wp.uint64,
    queries: wp.array(dtype=wp.vec3f),
    max_dist: wp.float32,
    inside: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    q = wp.mesh_query_point_sign_winding_number(mesh, queries[i], max_dist)
    inside[i] = wp.where(q.result and q.sign < 0.0, 1, 0)


def sample_inside(points, triangles, spacing: float, device=None) -> np.ndarray:
    """Lattice points of ``spacing`` (cell-centred over the bounding box) inside the mesh.

    Expects an outward-oriented closed mesh such as ``load_mesh`` returns. The inside test
    is Warp's fast winding number, run on ``device`` (Warp's default when None).
    """
    dx = checks.positive("spacing", spacing)
    # wp.Mesh does not check its input and an index out of range crashes the process.
    pts, tri = _checked_arrays("(points, triangles)", points, triangles)
    if not np.isfinite(pts).all():
        _reject("(points, triangles)", "its points must be finite")
    tri = tri.astype(np.int32)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    # Work relative to the box centre: float32 keeps ~7 digits of the offset, not of the
    # absolute position, so a mesh far from the origin is classified as accurately. Its box
    # is counted with the round-off of where it lies: relative to the centre it carries it
    # still (a box mesh 5 spacings across 1e5 m out had 4 layers in 20 places of 20).
    centre = 0.5 * (lo + hi)
    grid = lattice_points(lo - centre, hi - centre, dx, reach=np.maximum(np.abs(lo), np.abs(hi)))
    dev = wp.get_device(device)
    mesh = wp.Mesh(
        points=wp.array((pts - centre).astype(np.float32), dtype=wp.vec3f, device=dev),
        indices=wp.array(tri.reshape(-1), dtype=wp.int32, device=dev),
        support_winding_number=True,
    )
    queries = wp.array(grid.astype(np.float32), dtype=wp.vec3f, device=dev)
    inside = wp.zeros(len(grid), dtype=wp.int32, device=dev)
    # Every query lies in the box, so the diagonal bounds its distance to the surface.
    max_dist = 2.0 * float(np.linalg.norm(hi - lo)) + dx
    wp.launch(_inside_kernel, dim=len(grid), inputs=[mesh.id, queries, max_dist], outputs=[inside], device=dev)
    keep = inside.numpy().astype(bool)  # synchronises, so ``mesh`` outlives the launch
    if not keep.any():
        size = ", ".join(f"{s:g}" for s in hi - lo)
        raise ValueError(
            f"spacing = {checks.shorten(spacing)!r} is not allowed for this mesh: no lattice point falls inside it "
            f"(its bounding box is {size}); use a smaller spacing or a larger scale"
        )
    return grid[keep] + centre
