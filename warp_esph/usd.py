"""Crash-safe USD output (``UsdWriter``): one ``UsdGeom.Points`` per body, one time sample
per frame; and its reader (``UsdFrames``, ``parse_frames``: particles, surfaces, colliders),
which the renderer and the exporter use, so the layout below is spelled out in this module
only (``surface_prim_path`` names a body's surface prim).

Layout of the written stage (Y up, metres, time code = frame index)::

    /World                      Xform, the default prim
    /World/<body>               Points: points, velocities, widths, extent (time-sampled);
                                primvars singular_values (float3, vertex: F's signed
                                singular values, the smallest < 0 where det F < 0), alpha (float,
                                vertex) per frame, double3 and double in a float64 run;
                                material_id (int, constant) and displayColor (constant) once;
                                custom data warp_esph:material:<field>, each field of its
                                Material (a file written before some were recorded lacks them)
    /World/Colliders/plane_<k>  Mesh: a large quad on the plane (solid below it)
    /World/Colliders/sphere_<k> Sphere
    /World/Colliders/box_<k>    Cube scaled to the box's half extents
    /World/Surfaces/<body>      Mesh (only with ``surface=True``): the body's triangle surface
                                per frame (time-sampled points, faceVertexCounts,
                                faceVertexIndices, extent; see ``warp_esph.surface``)

The root layer's custom data holds ``warp_esph:*`` facts about the run (particle count,
spacing, ..., and from ``simulate`` what its solver ran, ``UsdWriter.record_solver``) and, where the scene suggests one, ``warp_esph:view`` = (azimuth,
elevation) in degrees, which ``warp_esph.render`` uses as its default camera direction.

``.usd``/``.usdc`` are written as binary crate files, ``.usda`` as text.

Crash safety
------------
After every ``write_frame`` the file at ``path`` is a complete, valid stage that holds
every finished frame; a process killed at any moment leaves it so. USD's own in-place
crate save is incremental (it appends the new samples, O(frame)) but it rewrites the
structural sections at the end of the file before it rewrites the header, so a kill
during a save would corrupt the file. Re-exporting the whole stage to a temporary file
and renaming it over ``path`` is safe but costs O(all frames) per frame. This writer
gets both: it keeps two working copies (``.<name>.wa.<ext>`` and ``.<name>.wb.<ext>``
beside ``path``) that receive the same edits, saves them alternately with USD's cheap
incremental save, and publishes the copy just saved by hard-linking it to a temporary
name and ``os.replace``-ing that over ``path`` (atomic). The copy that ``path`` links
to is never written to: the next save goes to the other one. ``close()`` deletes the
working copies; ``path`` keeps the last one's data. Where hard links are not supported
the published copy is copied instead (still atomic, O(file) per frame). After a crash
the working copies stay behind; ``append=True`` and the next run replace them.
"""

from __future__ import annotations

import bisect
import contextlib
import dataclasses
import functools
import io
import math
import os
import re
import shutil
import sys
import tempfile
import time
import warnings
import weakref

import numpy as np
from pxr import Gf, Sdf, Tf, Usd, UsdGeom, Vt

from . import checks, tools
from .model import Model

__all__ = ["UsdWriter", "UsdFrames", "Collider", "Tool", "USD_EXTENSIONS", "body_prim_names", "parse_frames", "surface_prim_path"]

#: Output extensions and the layer format each is written in.
USD_EXTENSIONS = {".usd": "usdc", ".usdc": "usdc", ".usda": "usda"}

_ROOT = "/World"
_COLLIDERS = f"{_ROOT}/Colliders"
_SURFACES = f"{_ROOT}/Surfaces"
_KEY = "warp_esph"
_VIEW = f"{_KEY}:view"
_RUN_ID = f"{_KEY}:run_id"  # the run that wrote the file (UsdWriter's run_id; the CLI's run record)
# Per-particle primvars of a body's Points prim (the writer creates them, the reader reads them).
_SINGULAR_VALUES, _ALPHA, _MATERIAL_ID = "singular_values", "alpha", "material_id"
_PRIMVAR_SINGULAR_VALUES = f"primvars:{_SINGULAR_VALUES}"
_PRIMVAR_ALPHA = f"primvars:{_ALPHA}"
#: A float64 run's positions and velocities to the last bit, beside the schema's float
#: ``points`` and ``velocities`` (which round them to float32: 2e-9 m, measured), read back by
#: ``UsdFrames.arrays`` (fit targets, export).
_POINTS64, _VELOCITIES64 = f"{_KEY}:points_float64", f"{_KEY}:velocities_float64"
_PRIMVAR_MATERIAL_ID = f"primvars:{_MATERIAL_ID}"

# One display colour per material (cycled), so bodies are told apart in a viewer.
_PALETTE = [
    (0.90, 0.75, 0.50), (0.75, 0.35, 0.25), (0.25, 0.45, 0.80), (0.40, 0.70, 0.35),
    (0.80, 0.55, 0.80), (0.95, 0.85, 0.30), (0.50, 0.50, 0.50),
]


#: The largest elevation (degrees, up or down) of a view: at 90 the camera looks along its up axis.
VIEW_ELEVATION = 89.0


def _read_view(path: str, view) -> tuple[float, float] | None:
    """The ``(azimuth, elevation)`` a file suggests. A hint only, so it never makes a file
    unreadable: a value that is no pair of finite degrees (NaN failed in the renderer as 'cannot
    convert float NaN to integer', naming no file) is left out with a ``UserWarning`` naming the
    file, and an elevation beyond +-89 degrees (older writers took 90, which looks along the up
    axis) is brought to the bound."""
    try:
        if isinstance(view, (str, bytes)):
            raise TypeError  # text: '12' read as (1, 2)
        az, el = (float(v) for v in view)
        shown = [az, el]
    except (TypeError, ValueError):
        az = el = math.nan
        shown = view
    if not (math.isfinite(az) and math.isfinite(el)):
        warnings.warn(f"{checks.shown_path(path, False)}: its {_VIEW} = {checks.shorten(shown)!r} is no (azimuth, elevation) in finite degrees; "
                      "the suggested view is left out", UserWarning, stacklevel=3)
        return None
    return az, min(max(el, -VIEW_ELEVATION), VIEW_ELEVATION)


def open_layer_checked(path, action: str = "read") -> Sdf.Layer:
    """``Sdf.Layer.OpenAsAnonymous(path)`` (read afresh, not from pxr's layer cache), or a
    ``ValueError`` naming the file and pxr's reason: a truncated, garbled or foreign file
    makes pxr raise ``Tf.ErrorException`` with a C++ location, or return ``None``."""
    path = os.fspath(path)
    checks.usd_input(path, action)
    try:
        with _native_stderr() as notes:
            layer = Sdf.Layer.OpenAsAnonymous(path)
    except Exception as e:  # noqa: BLE001 (Tf.ErrorException, RuntimeError)
        raise checks.file_error(path, e, action) from None
    if layer is None:
        raise ValueError(f"cannot {action} {checks.shown_path(path, False)}: pxr cannot open it as a USD file")
    # A file this package wrote opens without a word; pxr's warnings (invalid prim names,
    # properties without a prim) mean damaged tokens, and the data read would be garbage.
    said = [n.split(" -- ", 1)[-1].strip() for n in notes if n.strip()]
    if said:
        raise ValueError(f"cannot {action} {checks.shown_path(path)}: pxr reads it as damaged ({checks.shorten(said[0]).text}"
                         + (f", and {len(said) - 1} more warnings)" if len(said) > 1 else ")"))
    return layer


@contextlib.contextmanager
def _native_stderr():
    """Collect what native code prints on file descriptor 2 (pxr's diagnostics go there
    directly, not through Python) into the yielded list, instead of the terminal."""
    notes: list[str] = []
    try:
        if sys.stderr is not None:  # None where the process started with descriptor 2 closed (2>&-)
            sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no descriptor 2: nothing to keep off the terminal
        yield notes
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield notes
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            notes.extend(tmp.read().decode(errors="replace").splitlines())


def body_prim_names(model: Model) -> list[str]:
    """The prim name of each body: a valid, unique USD identifier made from its name."""
    names: list[str] = []
    taken = {"Colliders", "Surfaces", "Tools"}  # scopes of usd.py and tools.py
    for body in model.bodies:
        base = Tf.MakeValidIdentifier(body.name) or "body"
        name, k = base, 1
        while name in taken:
            name = f"{base}_{k}"
            k += 1
        taken.add(name)
        names.append(name)
    return names


def surface_prim_path(body_prim: str) -> str:
    """The path of the surface Mesh prim of the body whose Points prim is ``/World/<body_prim>``."""
    return f"{_SURFACES}/{body_prim}"


def _singular_values(F: np.ndarray) -> np.ndarray:
    """The signed singular values of each 3x3 matrix in ``F`` (N, 3, 3), in ``F``'s precision
    (float32 or float64): those of the rotation-variant SVD the solver runs (docs/method.md
    §3), ``s1 >= s2 >= |s3|`` with ``s3`` of the sign of ``det F``. numpy's are all >= 0, and an
    inverted particle (det F < 0) was written as one of the mirrored shape, not told from a
    sound one."""
    F64 = np.asarray(F, dtype=np.float64)
    finite = np.isfinite(F64).all(axis=(1, 2))
    out = np.full((len(F64), 3), np.nan)
    if finite.any():
        out[finite] = np.linalg.svd(F64[finite], compute_uv=False)
        inverted = np.flatnonzero(finite)[np.linalg.det(F64[finite]) < 0.0]
        out[inverted, 2] = -out[inverted, 2]
    return out.astype(np.float64 if np.asarray(F).dtype == np.float64 else np.float32)


def _set_primvar(attr, values: np.ndarray, t) -> None:
    """Set a per-particle primvar at ``t`` in the precision the attribute was authored in:
    a file appended to keeps the type its first run gave it (a float64 run resumed into a
    file from before the double primvars, or another program's file naming no precision),
    where USD would refuse a value of the other type. A model of the other precision than a
    file names is refused at ``append`` (``_check_compatible``)."""
    double = attr.GetTypeName() in (Sdf.ValueTypeNames.DoubleArray, Sdf.ValueTypeNames.Double3Array)
    values = np.ascontiguousarray(values, dtype=np.float64 if double else np.float32)
    vec = values.ndim == 2
    cls = (Vt.Vec3dArray if vec else Vt.DoubleArray) if double else (Vt.Vec3fArray if vec else Vt.FloatArray)
    attr.Set(cls.FromNumpy(values), t)


class OutputInUse(checks.Rebuilt, ValueError):
    """A file another ``UsdWriter`` (of this or another process) is writing now: ``reason``
    says so, for a caller that names the file by its own option (the CLI's ``--output``)."""

    def __init__(self, path: str, reason: str):
        super().__init__(f"path = {checks.shown_path(path)} is not allowed: {reason}")
        self.reason = reason


class UsdWriter:
    """Writes simulation frames to a USD file; use as a context manager.

    ``path``: ``.usd``/``.usdc`` (binary) or ``.usda`` (text). ``fps``: frames per
    second; the time code of frame ``k`` is ``k``. ``append=True`` reopens an existing
    file written for the same scene and continues it: the first frame written then
    replaces that frame and every later one already in the file (resume from a
    checkpoint); a model without one of the file's bodies, or with another particle count
    in one, is refused, naming the body. ``plane_size``: edge length of the quads that show plane colliders
    (default: 10x the scene size, at least 4 m). ``surface=True`` also writes a triangle
    surface per body and frame under ``/World/Surfaces`` (marching cubes of a Zhu-Bridson
    field, ``warp_esph.surface``; costs about 0.15 s per frame per 50k particles on one CPU
    core). ``view``: a suggested camera direction (azimuth, elevation) in degrees for
    renderers, stored in the layer's custom data. ``run_id``: a text naming the run, stored
    in the layer's custom data by a new file; appending with one refuses a file that names
    another run (a checkpoint of one run resumed onto the frames of another). A file keeps
    one precision: appending with a model of the other precision than the file's
    (``warp_esph:dtype`` in its custom data) is refused, naming both, rather than writing
    the later frames in the other precision. While a writer is open no other may write
    ``path`` (``OutputInUse``, a ``ValueError``): it holds a lock on ``.<name>.lock`` beside
    it, removed by ``close()``, also when its clean-up fails (a later ``close()`` finishes
    that clean-up unless another writer has taken the file since). A ``path`` that is a
    symbolic link (or a device, a named pipe, a socket) is refused, as every command refuses
    it: each frame is renamed over ``path``, which would replace the link with a file.
    """

    def __init__(self, path, model: Model, fps: float = 30.0, *, append: bool = False, plane_size: float | None = None,
                 surface: bool = False, view=None, run_id: str | None = None):
        if not isinstance(model, Model):
            raise ValueError(f"model = {checks.shorten(model)!r} is not allowed: must be a warp_esph.Model")
        try:
            self.path = os.path.abspath(os.fspath(path))
        except TypeError:
            raise ValueError(f"path = {checks.shown_path(path)} is not allowed: must be a file path") from None
        folder, name = os.path.split(self.path)
        ext = os.path.splitext(name)[1].lower()
        if ext not in USD_EXTENSIONS:
            raise ValueError(f"path = {os.fspath(path)!r} is not allowed: the extension must be one of {', '.join(USD_EXTENSIONS)}")
        if not os.path.isdir(folder):
            raise FileNotFoundError(f"cannot write {checks.shown_path(self.path, False)}: the folder {checks.shown_path(folder, False)} does not exist")
        if os.path.isdir(self.path):  # a folder of that name met an IsADirectoryError at the first frame
            raise ValueError(f"path = {os.fspath(path)!r} is not allowed: it is a folder; a file is written there")
        # Every frame is renamed over path: a symbolic link there became a regular file and
        # the file it linked to was left as it was, where every command refuses the link.
        checks.refuse_special("path", os.fspath(path))
        checks.usd_output("path", path)
        self.format = USD_EXTENSIONS[ext]
        self.model = model
        self.fps = checks.positive("fps", fps)
        self.append = checks.boolean("append", append)  # 'no' reopened the file to continue it
        self._plane_size = None if plane_size is None else checks.positive("plane_size", plane_size)
        if not isinstance(surface, bool):
            raise ValueError(f"surface = {checks.shorten(surface)!r} is not allowed: must be True or False")
        self.surface = surface
        if view is not None:
            try:
                az, el = (float(v) for v in view)
            except (TypeError, ValueError):
                raise ValueError(f"view = {checks.shorten(view)!r} is not allowed: must be (azimuth, elevation) in degrees") from None
            view = (checks.number("view azimuth", az), checks.in_range("view elevation", el, -VIEW_ELEVATION, VIEW_ELEVATION))
        self.view = view
        if run_id is not None and (not isinstance(run_id, str) or not run_id):
            raise ValueError(f"run_id = {checks.shorten(run_id)!r} is not allowed: must be a non-empty string or None")
        self.run_id = run_id
        self.file_run_id = None
        #: Seconds spent building surfaces, over all frames.
        self.surface_seconds = 0.0
        self._surface_warned: set[str] = set()
        self._folder, self._name, self._ext = folder, name, ext
        self._work = [os.path.join(folder, f".{name}.w{tag}{ext}") for tag in "ab"]
        self._tmp = os.path.join(folder, f".{name}.{os.getpid()}.publish{ext}")
        self._prim_names = body_prim_names(model)
        self._lock_path = os.path.join(folder, f".{name}.lock")
        self._lock = self._take_lock(os.fspath(path))
        self._stages: list[Usd.Stage] = []
        self._published: int | None = None
        self._use_links = True
        self._truncate_pending = self.append
        self._widths = [Vt.FloatArray.FromNumpy(np.full(b.count, model.spacing, dtype=np.float32)) for b in model.bodies]
        self.closed = False
        #: Frames written by this writer; the smallest and largest frame index in the file (None
        #: while it holds none: a new file, or one appended to that holds no frame).
        self.frames_written = 0
        self.first_frame: int | None = None
        self.last_frame: int | None = None
        #: Seconds spent saving and publishing, over all frames (measure the USD cost).
        self.save_seconds = 0.0
        try:
            if self.append:
                self._open_existing()
            else:
                self._create_new()
        except BaseException:
            self._release()
            self._remove_work_files()
            self._drop_lock()
            raise

    def _take_lock(self, given: str):
        """Hold the file for this writer: two writers of one file (two runs given one
        output) shared its working copies, and the first failed mid-run with pxr's 'Unable to
        open .a.usdc.wa.usdc', saying its file kept its frames, while the file was the
        second's. An advisory lock (flock) on a file beside it, which the system releases
        with a killed process; ``None`` where there is no flock."""
        try:
            import fcntl  # noqa: PLC0415
        except ImportError:
            return None
        while True:
            writable = True
            try:
                try:
                    fd = os.open(self._lock_path, os.O_RDWR | os.O_CREAT, 0o644)
                except PermissionError:
                    # Another user's lock file, left by a killed run in a shared folder: flock
                    # needs no write access, and refusing it refused an output this user may write.
                    fd = os.open(self._lock_path, os.O_RDONLY)
                    writable = False
            except OSError as e:
                # A failed write (a read-only folder), as pxr's at the working copies was: a
                # FileNotFoundError read as 'the input is missing' (exit 2).
                raise OSError(f"could not create {self._lock_path}: {e.strerror or e}") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                try:
                    holder = os.read(fd, 32).decode(errors="replace").strip() or "?"
                finally:
                    os.close(fd)
                if holder == str(os.getpid()):
                    # One this process opened and did not close (a notebook's cell run again, the
                    # old writer still referenced): waiting for it would wait forever.
                    raise OutputInUse(given, f"another writer of this process ({holder}) is writing it; close() that "
                                             "one first, or write another file") from None
                raise OutputInUse(given, f"another writer (process {holder}) is writing it; wait for it to finish, "
                                         "or write another file") from None
            except OSError:
                # A file system without flock (some network mounts): written as before, unguarded.
                os.close(fd)
                with contextlib.suppress(OSError):
                    os.remove(self._lock_path)
                return None
            try:
                same = os.fstat(fd).st_ino == os.stat(self._lock_path).st_ino
            except FileNotFoundError:
                same = False
            if same and not writable:
                # Held by nobody: replaced by a file of ours, so that a writer refused while
                # this one writes is told this process, not the killed one named in it.
                try:
                    os.remove(self._lock_path)
                except OSError:
                    break  # a folder that lets no one remove it (sticky): held as it is
                same = False
            if same:
                break
            os.close(fd)  # its holder removed it between our open and our lock: take the new one
        if writable:
            os.ftruncate(fd, 0)
            os.write(fd, str(os.getpid()).encode())
        # An abandoned writer (never closed) lets the file go when it is collected.
        return weakref.finalize(self, os.close, fd)

    def _drop_lock(self):
        if self._lock is not None and self._lock.alive:
            # Removed while still held, so no other writer takes the old file as this one lets go.
            with contextlib.suppress(OSError):
                os.remove(self._lock_path)
            self._lock()

    # ------------------------------------------------------------------ setup
    def _new_layer(self, file: str) -> Sdf.Layer:
        if os.path.exists(file):
            os.remove(file)
        stale = Sdf.Layer.Find(file)
        if stale is not None:
            # A layer of that name is still alive in this process (an earlier writer's
            # stage not yet garbage-collected): USD refuses to create a second one.
            raise OSError(f"cannot create {checks.shown_path(file, False)}: a USD layer of that name is still open in this process")
        layer = Sdf.Layer.CreateNew(file, args={"format": self.format})
        if layer is None:
            raise OSError(f"cannot create {checks.shown_path(file, False)}")
        return layer

    def _create_new(self):
        for file in self._work:
            try:
                stage = Usd.Stage.Open(self._new_layer(file))
            except Tf.ErrorException as e:
                # pxr writes the new layer at once: a full disk there reached the CLI as pxr's
                # error, taken for a damaged input file ('cannot read', exit 2); it is a failed write.
                raise OSError(f"USD could not create {checks.shown_path(file, False)}: {checks.read_reason(e)}") from None
            self._author_static(stage)
            self._stages.append(stage)
        # Publish the empty stage (prims, colliders, metadata) at once: the file at
        # ``path`` is valid from here on.
        self._save_and_publish()

    def _open_existing(self):
        if not os.path.isfile(self.path):
            raise FileNotFoundError(f"cannot append to {checks.shown_path(self.path, False)}: no such file")
        open_layer_checked(self.path, "append to")  # a damaged file: one message, not pxr's warnings
        for file in self._work:
            if os.path.exists(file):
                os.remove(file)
            shutil.copyfile(self.path, file)
            layer = Sdf.Layer.FindOrOpen(file)
            if layer is None:
                raise ValueError(f"cannot append to {checks.shown_path(self.path, False)}: it is not a USD file pxr can open")
            layer.Reload(force=True)  # a layer of that name may be cached from an earlier writer
            stage = Usd.Stage.Open(layer)
            self._check_compatible(stage)
            self._author_surfaces(stage)
            self._author_collider_reactions(stage)
            self._stages.append(stage)
        # The frames the file holds are its bodies' point samples (what UsdFrames reads), not the
        # stage's start and end time codes: a file with no frame yet (its writer stopped before
        # the first) has both at 0, and read as holding frame 0, so a resume at frame 1 onto it
        # passed the CLI's check of the frames before it and left frame 0 unwritten.
        held = sorted({t for name in self._prim_names
                       for t in UsdGeom.Points(self._stages[0].GetPrimAtPath(f"{_ROOT}/{name}")).GetPointsAttr().GetTimeSamples()})
        self.first_frame, self.last_frame = (int(held[0]), int(held[-1])) if held else (None, None)
        # ``path`` itself stays untouched until the first frame is published.

    def _check_compatible(self, stage: Usd.Stage):
        where = f"cannot append to {checks.shown_path(self.path, False)}"
        tcps = stage.GetTimeCodesPerSecond()
        if not math.isclose(tcps, self.fps, rel_tol=1e-9):
            raise ValueError(f"{where}: it was written at fps = {tcps:g}, not {self.fps:g}")
        theirs = (stage.GetRootLayer().customLayerData or {}).get(_RUN_ID)
        #: The run id the appended file names (None: written without one).
        self.file_run_id = theirs
        if self.run_id is not None and theirs is not None and theirs != self.run_id:
            # Another run wrote the file since (or the checkpoint was copied from elsewhere): its
            # frames and the checkpoint's state would be spliced into one file.
            raise ValueError(f"{where}: it holds the frames of another run (run id {theirs!r}), not those of the run "
                             f"{self.run_id!r} it would continue")
        # A file holds one run's precision, as a checkpoint's run record does (``run --resume``
        # refuses --dtype): a model of the other one wrote its frames in its own precision after
        # the file's (a float64 model's double positions after float32 ones, a float32 model's
        # rounded positions where the layer's warp_esph:dtype promised float64), and converting
        # up cannot restore the digits a float32 run never had. A file naming no precision
        # (another program's) names nothing to keep.
        written = (stage.GetRootLayer().customLayerData or {}).get(f"{_KEY}:dtype")
        ours = self.model.scalar.__name__
        if written is not None and written != ours:
            raise ValueError(f"{where}: it holds a {written} run's frames (warp_esph:dtype) and the model is {ours}; a file "
                             f"keeps one precision: finalize the model with dtype=wp.{written} to continue it, or write a new file")
        for body, name in zip(self.model.bodies, self._prim_names):
            prim = stage.GetPrimAtPath(f"{_ROOT}/{name}")
            if not prim or not prim.IsA(UsdGeom.Points):
                raise ValueError(f"{where}: it has no Points prim {_ROOT}/{name} for body {body.name!r}")
            count = (prim.GetCustomDataByKey(f"{_KEY}:particle_count"))
            if count is not None and int(count) != body.count:
                raise ValueError(f"{where}: body {body.name!r} has {count} particles there, {body.count} in the model")
        # A body the model has not: its samples from the resume on were dropped and none written,
        # so the file held it up to there only, and its particle count named frames it no longer had.
        ours = {f"{_ROOT}/{name}" for name in self._prim_names}
        world = stage.GetPrimAtPath(_ROOT)
        for prim in world.GetChildren() if world else []:
            if prim.IsA(UsdGeom.Points) and str(prim.GetPath()) not in ours:
                name = prim.GetCustomDataByKey(f"{_KEY}:body_name") or prim.GetName()
                count = prim.GetCustomDataByKey(f"{_KEY}:particle_count")
                held = f"{count} particles, " if count is not None else ""
                raise ValueError(f"{where}: it holds body {name!r} ({held}Points prim {prim.GetPath()}), which the model has "
                                 "not; a file continues the scene that wrote it: append with that scene's model, or write "
                                 "a new file")

    def _author_static(self, stage: Usd.Stage):
        m = self.model
        stage.SetTimeCodesPerSecond(self.fps)
        stage.SetFramesPerSecond(self.fps)
        stage.SetStartTimeCode(0.0)
        stage.SetEndTimeCode(0.0)
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        world = UsdGeom.Xform.Define(stage, _ROOT)
        stage.SetDefaultPrim(world.GetPrim())
        from . import __version__  # noqa: PLC0415 (package fully imported by now)

        stage.GetRootLayer().customLayerData = {
            f"{_KEY}:version": __version__,
            f"{_KEY}:particle_count": m.particle_count,
            f"{_KEY}:spacing": m.spacing,
            f"{_KEY}:support_radius": m.support_radius,
            f"{_KEY}:fit_weight": m.fit_weight,
            f"{_KEY}:gravity": Gf.Vec3d(*m.gravity),
            f"{_KEY}:dtype": m.scalar.__name__,
        }
        if self.view is not None or self.run_id is not None:
            data = dict(stage.GetRootLayer().customLayerData)
            if self.view is not None:
                data[_VIEW] = Gf.Vec2d(*self.view)
            if self.run_id is not None:
                data[_RUN_ID] = self.run_id
            stage.GetRootLayer().customLayerData = data
        for body, name, widths in zip(m.bodies, self._prim_names, self._widths):
            pts = UsdGeom.Points.Define(stage, f"{_ROOT}/{name}")
            prim = pts.GetPrim()
            mat = m.materials[body.material]
            prim.SetCustomDataByKey(f"{_KEY}:body_name", body.name)
            prim.SetCustomDataByKey(f"{_KEY}:kind", body.kind)
            prim.SetCustomDataByKey(f"{_KEY}:first_particle", body.start)
            prim.SetCustomDataByKey(f"{_KEY}:particle_count", body.count)
            # Every field of the Material, so that the file says what ran: a list of names left
            # out pair_repulsion, clamp_pressure and pressure_force, which change the forces.
            for field in dataclasses.fields(mat):
                value = getattr(mat, field.name)
                prim.SetCustomDataByKey(f"{_KEY}:material:{field.name}",
                                        value if isinstance(value, (str, bool)) else float(value))
            pts.CreatePointsAttr()
            pts.CreateVelocitiesAttr()
            pts.CreateWidthsAttr()
            pts.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
            pts.CreateExtentAttr()
            pv = UsdGeom.PrimvarsAPI(prim)
            # In the run's precision: a float64 run's alpha and singular values were rounded to
            # float32 here while its points and velocities were kept to the last bit.
            doubles = m.scalar.__name__ == "float64"
            pv.CreatePrimvar(_SINGULAR_VALUES, Sdf.ValueTypeNames.Double3Array if doubles else Sdf.ValueTypeNames.Float3Array,
                             UsdGeom.Tokens.vertex)
            pv.CreatePrimvar(_ALPHA, Sdf.ValueTypeNames.DoubleArray if doubles else Sdf.ValueTypeNames.FloatArray,
                             UsdGeom.Tokens.vertex)
            pv.CreatePrimvar(_MATERIAL_ID, Sdf.ValueTypeNames.Int, UsdGeom.Tokens.constant).Set(int(body.material))
            color = _PALETTE[body.material % len(_PALETTE)]
            pts.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(Vt.Vec3fArray([Gf.Vec3f(*color)]))
        self._author_colliders(stage)
        self._author_collider_reactions(stage)
        self._author_surfaces(stage)
        tools.usd_author(stage, m, _KEY, self._plane_quad_size())

    def _author_surfaces(self, stage: Usd.Stage):
        """The surface Mesh prims (idempotent: also used when appending to an existing file)."""
        m = self.model
        if self.surface:
            UsdGeom.Scope.Define(stage, _SURFACES)
            for body, name in zip(m.bodies, self._prim_names):
                mesh = UsdGeom.Mesh.Define(stage, surface_prim_path(name))
                mesh.CreatePointsAttr()
                mesh.CreateFaceVertexCountsAttr()
                mesh.CreateFaceVertexIndicesAttr()
                mesh.CreateExtentAttr()
                mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
                mesh.GetPrim().SetCustomDataByKey(f"{_KEY}:body_name", body.name)
                color = _PALETTE[body.material % len(_PALETTE)]
                mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(Vt.Vec3fArray([Gf.Vec3f(*color)]))

    def _author_colliders(self, stage: Usd.Stage):
        m = self.model
        # As the kernels run them (their arrays): a ground moved in place is drawn where it is.
        planes, spheres, boxes = m.static_colliders()
        if not (planes or spheres or boxes):
            return
        UsdGeom.Scope.Define(stage, _COLLIDERS)
        x0 = np.asarray(m.particle_x0, dtype=np.float64)
        center = 0.5 * (x0.min(axis=0) + x0.max(axis=0))
        size = self._plane_quad_size()
        grey = Vt.Vec3fArray([Gf.Vec3f(0.55, 0.55, 0.6)])
        for k, p in enumerate(planes):
            n = np.asarray(p.normal, dtype=np.float64)
            origin = center - (n @ center - p.offset) * n
            t1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 0.0, 1.0])
            t1 /= np.linalg.norm(t1)
            t2 = np.cross(n, t1)  # t1 x t2 = n: the quad faces +n
            h = 0.5 * size
            corners = [origin - h * t1 - h * t2, origin + h * t1 - h * t2, origin + h * t1 + h * t2, origin - h * t1 + h * t2]
            mesh = UsdGeom.Mesh.Define(stage, f"{_COLLIDERS}/plane_{k}")
            mesh.CreatePointsAttr(Vt.Vec3fArray([Gf.Vec3f(*c) for c in corners]))
            mesh.CreateFaceVertexCountsAttr(Vt.IntArray([4]))
            mesh.CreateFaceVertexIndicesAttr(Vt.IntArray([0, 1, 2, 3]))
            mesh.CreateNormalsAttr(Vt.Vec3fArray([Gf.Vec3f(*n)] * 4))
            mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
            mesh.CreateDoubleSidedAttr(True)
            c = np.array(corners)
            mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*c.min(axis=0)), Gf.Vec3f(*c.max(axis=0))]))
            mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(grey)
            self._collider_data(mesh.GetPrim(), "plane", friction=p.friction, normal=Gf.Vec3d(*p.normal), offset=p.offset)
        for k, s in enumerate(spheres):
            sph = UsdGeom.Sphere.Define(stage, f"{_COLLIDERS}/sphere_{k}")
            sph.CreateRadiusAttr(float(s.radius))
            r = float(s.radius)
            sph.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(-r, -r, -r), Gf.Vec3f(r, r, r)]))
            sph.AddTranslateOp().Set(Gf.Vec3d(*s.center))
            sph.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(grey)
            self._collider_data(sph.GetPrim(), "sphere", friction=s.friction, center=Gf.Vec3d(*s.center), radius=s.radius)
        for k, b in enumerate(boxes):
            cube = UsdGeom.Cube.Define(stage, f"{_COLLIDERS}/box_{k}")
            cube.CreateSizeAttr(2.0)
            cube.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(-1, -1, -1), Gf.Vec3f(1, 1, 1)]))
            cube.AddTranslateOp().Set(Gf.Vec3d(*b.center))
            cube.AddScaleOp().Set(Gf.Vec3f(*b.half_extents))
            cube.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(grey)
            self._collider_data(cube.GetPrim(), "box", friction=b.friction, center=Gf.Vec3d(*b.center), half_extents=Gf.Vec3d(*b.half_extents))

    def _collider_prim_paths(self) -> list[str]:
        """The static colliders' prims in the order of ``Solver.collider_reactions`` (world 0)."""
        m = self.model
        return ([f"{_COLLIDERS}/plane_{k}" for k in range(len(m.planes))] + [f"{_COLLIDERS}/sphere_{k}" for k in range(len(m.spheres))]
                + [f"{_COLLIDERS}/box_{k}" for k in range(len(m.boxes))])

    def _author_collider_reactions(self, stage: Usd.Stage):
        """Each static collider's reaction attributes (time-sampled by ``write_frame``) and its
        row name (``plane<k>``, ... as ``Solver.collider_reactions`` names it); idempotent, so
        a file appended to gets them too."""
        from .sim.integrate import static_collider_names  # noqa: PLC0415

        names = static_collider_names(self.model)
        for path, name in zip(self._collider_prim_paths(), names):
            prim = stage.GetPrimAtPath(path)
            if not prim:
                continue  # a file written without this collider: nothing to attach to
            prim.SetCustomDataByKey(f"{_KEY}:collider_name", name.split("/")[-1])
            prim.CreateAttribute(f"{_KEY}:reaction_force", Sdf.ValueTypeNames.Double3)
            prim.CreateAttribute(f"{_KEY}:reaction_torque", Sdf.ValueTypeNames.Double3)

    def _write_collider_reactions(self, stage: Usd.Stage, state, t):
        """The static colliders' force and torque of the step that produced ``state``
        (world 0's rows, as the tools' attributes; the others are in ``state.collider_force``)."""
        paths = self._collider_prim_paths()
        if not paths:
            return
        f = state.collider_force.numpy().astype(np.float64)
        tq = state.collider_torque.numpy().astype(np.float64)
        for k, path in enumerate(paths):
            prim = stage.GetPrimAtPath(path)
            force = prim.GetAttribute(f"{_KEY}:reaction_force") if prim else None
            if force:
                force.Set(Gf.Vec3d(*f[k]), t)
                prim.GetAttribute(f"{_KEY}:reaction_torque").Set(Gf.Vec3d(*tq[k]), t)

    def _plane_quad_size(self) -> float:
        """Edge of the quads that show planes (static colliders and plane tools alike)."""
        if self._plane_size:
            return self._plane_size
        x0 = np.asarray(self.model.particle_x0, dtype=np.float64)
        return max(4.0, 10.0 * float(np.linalg.norm(x0.max(axis=0) - x0.min(axis=0)))) if len(x0) else 4.0

    @staticmethod
    def _collider_data(prim: Usd.Prim, kind: str, **values):
        prim.SetCustomDataByKey(f"{_KEY}:collider", kind)
        for key, value in values.items():
            prim.SetCustomDataByKey(f"{_KEY}:{key}", float(value) if isinstance(value, (int, float)) else value)

    # ----------------------------------------------------------------- frames
    def record_solver(self, solver, frame: int | None = None, state=None) -> None:
        """Record in the layer's custom data what ``solver`` runs from ``state``
        (``Solver.record(state)``; ``simulate`` passes the state it writes next: the start, then
        the state the frame's last step wrote, which says what that step ran; None: from a new
        state), saved with the next frame. ``fit="auto"`` resolves by the material values, so
        the requested fit alone does not say which model wrote the frames, and a callback that
        changes a material can switch it within a run.

        Without ``frame`` (a run's start, as ``simulate`` calls it): ``warp_esph:fit`` (the fit
        asked for), ``warp_esph:resolved_fit``, ``warp_esph:hourglass`` (the strength run) and
        ``warp_esph:rest_model`` (whether the rest-configuration model ran), for the run's
        first frames (an appended run's solver replaces the earlier run's entry). With
        ``frame`` (``simulate`` calls it before writing each frame): ``warp_esph:solver_frames``
        gains ``"<frame>: <Solver.label>"`` where the label differs from the one before it
        (``"0: rest curvature_corrected c=0.05; 3: incremental linear c=0"``: frames 3 on ran
        the incremental composition); entries of an earlier run at or after ``frame`` are
        dropped (a resumed or appended run rewrites those frames). In a file written before
        this key existed (appended to or resumed into), it starts at that run's first ``frame``:
        the earlier frames have no entry, their solver not recorded. ``frame`` is an integer >= 0,
        and a closed writer refuses it as ``write_frame`` does."""
        key = f"{_KEY}:solver_frames"
        if frame is None:
            # Asked without the state where none is given: a solver-like object of the earlier
            # protocol takes none.
            r = solver.record() if state is None else solver.record(state)
            entries = {f"{_KEY}:fit": r["fit"], f"{_KEY}:resolved_fit": r["resolved_fit"],
                       f"{_KEY}:hourglass": float(r["resolved_hourglass"]), f"{_KEY}:rest_model": bool(r["rest_model"])}
        else:
            if self.closed or not self._stages:
                # Called before each frame's write_frame: a closed writer met an IndexError
                # here, before write_frame's refusal.
                raise ValueError(f"cannot write frame {frame!r}: the writer of {checks.shown_path(self.path, False)} is closed")
            if isinstance(frame, bool) or not isinstance(frame, (int, np.integer)) or frame < 0:
                raise ValueError(f"frame = {checks.shorten(frame)!r} is not allowed: must be an integer >= 0 (the frame index "
                                 "write_frame writes next)")
            data = dict(self._stages[0].GetRootLayer().customLayerData or {})
            before = str(data.get(key, ""))
            kept = [e for e in before.split("; ") if e and int(e.split(":", 1)[0]) < int(frame)]
            label = solver.label() if state is None else solver.label(state)
            if not kept or kept[-1].split(": ", 1)[1] != label:
                kept.append(f"{int(frame)}: {label}")
            # A resume at an earlier frame by the solver of the entry before it still drops the
            # later entries: they named what ran in frames this run rewrites.
            if "; ".join(kept) == before:
                return
            entries = {key: "; ".join(kept)}
        for stage in self._stages:
            layer = stage.GetRootLayer()
            layer.customLayerData = {**dict(layer.customLayerData or {}), **entries}

    def write_frame(self, frame_index: int, state) -> None:
        """Write ``state`` as frame ``frame_index`` (time code = frame index) and make it durable."""
        if self.closed or not self._stages:
            # A close() whose clean-up raised has released the stages but is not marked closed
            # (a later close() finishes it): writing on raised an IndexError from the publish.
            raise ValueError(f"cannot write frame {frame_index!r}: the writer of {checks.shown_path(self.path, False)} is closed")
        if isinstance(frame_index, bool) or not isinstance(frame_index, (int, np.integer)) or frame_index < 0:
            raise ValueError(f"frame_index = {checks.shorten(frame_index)!r} is not allowed: must be an integer >= 0")
        frame = int(frame_index)
        m = self.model
        checks.same_state(m, "state", state)
        x = state.x.numpy()
        v = state.v.numpy()
        bad = ~(np.isfinite(x).all(axis=1) & np.isfinite(v).all(axis=1))
        if bad.any():  # the file promises finished frames: a broken one is refused, not written
            raise ValueError(f"state is not allowed: particle {int(np.argmax(bad))} has a non-finite position or velocity "
                             f"({int(bad.sum())} particles); frame {frame} is not written")
        sv = _singular_values(state.F.numpy())
        alpha = state.alpha.numpy()
        x32, v32 = x.astype(np.float32), v.astype(np.float32)
        doubles = x.dtype == np.float64

        if self._truncate_pending:
            for stage in self._stages:
                self._drop_frames_from(stage, frame)
            self._truncate_pending = False
            self.first_frame = min(self.first_frame, frame) if self.first_frame is not None else frame
            self.last_frame = None

        t = Usd.TimeCode(float(frame))
        half_w = 0.5 * m.spacing
        samples = []
        for body, widths in zip(m.bodies, self._widths):
            s = slice(body.start, body.start + body.count)
            xb = x32[s]
            finite = np.isfinite(xb).all(axis=1)
            if finite.any():
                lo, hi = xb[finite].min(axis=0) - half_w, xb[finite].max(axis=0) + half_w
            else:
                lo = hi = np.zeros(3, np.float32)
            samples.append((
                Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(xb)),
                Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(v32[s])),
                widths,
                Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]),
                sv[s],
                alpha[s],
                (Vt.Vec3dArray.FromNumpy(np.ascontiguousarray(x[s])), Vt.Vec3dArray.FromNumpy(np.ascontiguousarray(v[s])))
                if doubles else None,
            ))
        surfaces = self._surfaces(x32) if self.surface else None
        self.first_frame = frame if self.first_frame is None else min(self.first_frame, frame)
        self.last_frame = frame if self.last_frame is None else max(self.last_frame, frame)
        for stage in self._stages:
            if surfaces is not None:
                for name, (pts, counts, indices, ext) in zip(self._prim_names, surfaces):
                    mesh = UsdGeom.Mesh(stage.GetPrimAtPath(surface_prim_path(name)))
                    mesh.GetPointsAttr().Set(pts, t)
                    mesh.GetFaceVertexCountsAttr().Set(counts, t)
                    mesh.GetFaceVertexIndicesAttr().Set(indices, t)
                    mesh.GetExtentAttr().Set(ext, t)
            for name, (pts, vel, wid, ext, svals, alph, exact) in zip(self._prim_names, samples):
                prim = stage.GetPrimAtPath(f"{_ROOT}/{name}")
                geom = UsdGeom.Points(prim)
                geom.GetPointsAttr().Set(pts, t)
                geom.GetVelocitiesAttr().Set(vel, t)
                geom.GetWidthsAttr().Set(wid, t)
                geom.GetExtentAttr().Set(ext, t)
                _set_primvar(prim.GetAttribute(_PRIMVAR_SINGULAR_VALUES), svals, t)
                _set_primvar(prim.GetAttribute(_PRIMVAR_ALPHA), alph, t)
                if exact is not None:
                    for key, value in zip((_POINTS64, _VELOCITIES64), exact):
                        attr = prim.GetAttribute(key) or prim.CreateAttribute(key, Sdf.ValueTypeNames.Double3Array)
                        attr.Set(value, t)
            tools.usd_write_frame(stage, m, state, t, _KEY)
            self._write_collider_reactions(stage, state, t)
            stage.SetStartTimeCode(float(self.first_frame))
            stage.SetEndTimeCode(float(self.last_frame))
        self._save_and_publish()
        self.frames_written += 1

    def _surfaces(self, x32: np.ndarray) -> list:
        """(points, counts, indices, extent) of each body's surface, as USD arrays."""
        from .surface import particle_surface  # noqa: PLC0415 (Warp kernels, only when asked)

        t0 = time.perf_counter()
        out = []
        for body in self.model.bodies:
            xb = x32[body.start: body.start + body.count]
            v, tri = np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
            if np.isfinite(xb).all(axis=1).any():
                try:
                    v, tri = particle_surface(xb, self.model.spacing, device=self.model.device)
                except ValueError as e:  # e.g. particles scattered over kilometres: the grid would not fit
                    if body.name not in self._surface_warned:
                        self._surface_warned.add(body.name)
                        warnings.warn(f"no surface for body {body.name!r} (an empty mesh is written): {e}", stacklevel=3)
            v32 = np.ascontiguousarray(v, dtype=np.float32)
            lo, hi = (v32.min(axis=0), v32.max(axis=0)) if len(v32) else (np.zeros(3), np.zeros(3))
            out.append((
                Vt.Vec3fArray.FromNumpy(v32),
                Vt.IntArray.FromNumpy(np.full(len(tri), 3, dtype=np.int32)),
                Vt.IntArray.FromNumpy(np.ascontiguousarray(tri.reshape(-1), dtype=np.int32)),
                Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]),
            ))
        self.surface_seconds += time.perf_counter() - t0
        return out

    @staticmethod
    def _drop_frames_from(stage: Usd.Stage, frame: int):
        """Remove every time sample at or after ``frame`` (append mode: resume there)."""
        for prim in stage.Traverse():
            for attr in prim.GetAttributes():
                for t in attr.GetTimeSamples():
                    if t >= frame:
                        attr.ClearAtTime(t)

    def _save_and_publish(self):
        t0 = time.perf_counter()
        target = 0 if self._published is None else 1 - self._published
        layer = self._stages[target].GetRootLayer()
        try:
            saved = layer.Save(force=True)
        except Tf.ErrorException as e:
            # A full disk or a vanished folder reaches here as pxr's error, which the CLI took
            # for a damaged input file (exit 2, 'cannot read'); it is a failed write.
            raise OSError(f"USD could not save {self._work[target]}: {checks.read_reason(e)}") from None
        if not saved:
            raise OSError(f"USD could not save {self._work[target]}")
        self._publish(self._work[target])
        self._published = target
        self.save_seconds += time.perf_counter() - t0

    def _publish(self, source: str):
        """Atomically make ``path`` a complete copy of ``source`` (a hard link where possible)."""
        if os.path.lexists(self._tmp):
            os.remove(self._tmp)
        if self._use_links:
            try:
                os.link(source, self._tmp)
            except OSError:
                self._use_links = False  # e.g. a file system without hard links
        if not self._use_links:
            shutil.copyfile(source, self._tmp)
        os.replace(self._tmp, self.path)

    # ------------------------------------------------------------------ close
    def _release(self):
        self._stages = []

    def _remove_work_files(self):
        for file in (*self._work, self._tmp):
            try:
                os.remove(file)
            except FileNotFoundError:
                pass

    def close(self) -> None:
        """Finish: ``path`` keeps every written frame; the working copies are removed."""
        if self.closed:
            return
        if self._lock is not None and not self._lock.alive:
            # An earlier close() failed after letting the file go (below): the working copies
            # are this writer's to remove only while no other writer has taken the file since.
            try:
                self._lock = self._take_lock(os.fspath(self.path))
            except OutputInUse:
                self.closed = True
                return
        # Marked closed only once the working copies are gone: an interrupt inside (a signal
        # while the stages are released) left them beside the output, and every later close()
        # returned at once.
        try:
            self._release()
            self._remove_work_files()
        finally:
            # Even when the clean-up fails: the lock was held until the writer was collected,
            # and a second writer of the path was refused (OutputInUse) though this one was gone.
            self._drop_lock()
        self.closed = True

    def __enter__(self) -> "UsdWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self):
        return f"UsdWriter({self.path!r}, frames_written={self.frames_written}, closed={self.closed})"


# ----------------------------------------------------------------------------- reading
# The reader sits beside the writer so both use the same prim paths and keys; the
# renderer (``warp_esph.render``) and the exporter (``warp_esph.export``) read through it.
@dataclasses.dataclass
class Collider:
    kind: str            # "plane", "sphere", "box"
    center: np.ndarray   # sphere/box centre; a point of the plane
    size: np.ndarray     # sphere: (r, r, r); box: half extents; plane: (half size of the quad, 0, 0)
    normal: np.ndarray | None = None
    offset: float = 0.0


@dataclasses.dataclass
class Tool:
    """A tool (moving collider) of ``/World/Tools``: its shape in its own frame and the prim
    whose time-sampled ``xformOp:translate`` / ``xformOp:orient`` give its pose per frame."""

    name: str
    kind: str                     # one of tools.KINDS
    prim: object                  # the tool's Xform prim
    param: np.ndarray             # box: half extents; sphere: (r, 0, 0); capsule/cylinder: (r, half height, 0); plane: local normal
    points: np.ndarray | None = None     # plane (the quad) and mesh: vertices in the tool's frame
    triangles: np.ndarray | None = None  # mesh: (T, 3) vertex indices
    #: ``frame -> (A, b)`` taking the tool prim's parent coordinates to metres and world
    #: coordinates (``UsdFrames.placement``), or None where that is the identity.
    placement: object = None

    def pose(self, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """``(position (3,), quaternion (x, y, z, w))`` at ``frame`` (held outside the samples),
        in metres and world coordinates: the prim's translate and orient, then its parent's
        transform and the stage's metersPerUnit (whose scale ``UsdFrames`` gave the shape)."""
        t = Usd.TimeCode(float(frame))
        p = self.prim.GetAttribute("xformOp:translate").Get(t)
        q = self.prim.GetAttribute("xformOp:orient").Get(t)
        p = np.zeros(3) if p is None else np.array(p, dtype=np.float64)
        if q is None:
            q = np.array([0.0, 0.0, 0.0, 1.0])
        else:
            im = q.GetImaginary()
            q = np.array([im[0], im[1], im[2], q.GetReal()], dtype=np.float64)
            q = q / np.linalg.norm(q)
        world = None if self.placement is None else self.placement(frame)
        if world is None:
            return p, q
        A, b = world
        # x_world = (x_tool R^T + p) A + b, with A = s Q (its scale, in the shape already, and
        # rotation): the pose's rotation becomes Q^T R (column vectors), its position p A + b.
        return p @ A + b, _matrix_quat(_rotation_part(A).T @ quat_matrix(q))


def quat_matrix(q) -> np.ndarray:
    """Rotation matrix of a unit quaternion ``(x, y, z, w)``."""
    x, y, z, w = (float(v) for v in q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def _matrix_quat(R) -> np.ndarray:
    """The unit quaternion ``(x, y, z, w)`` of a rotation matrix (``quat_matrix``'s inverse)."""
    R = np.asarray(R, dtype=np.float64)
    w = math.sqrt(max(0.0, 1.0 + R[0, 0] + R[1, 1] + R[2, 2])) / 2.0
    x = math.copysign(math.sqrt(max(0.0, 1.0 + R[0, 0] - R[1, 1] - R[2, 2])) / 2.0, R[2, 1] - R[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1.0 - R[0, 0] + R[1, 1] - R[2, 2])) / 2.0, R[0, 2] - R[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1.0 - R[0, 0] - R[1, 1] + R[2, 2])) / 2.0, R[1, 0] - R[0, 1])
    q = np.array([x, y, z, w])
    return q / np.linalg.norm(q)


def _scale_of(A) -> float:
    """The mean scale of a linear map (the cube root of its volume ratio)."""
    return float(abs(np.linalg.det(A)) ** (1.0 / 3.0))


def _rotation_part(A) -> np.ndarray:
    """The rotation nearest to ``A`` (its polar factor): the rotation of a transform that
    also scales."""
    u, _, vt = np.linalg.svd(np.asarray(A, dtype=np.float64))
    if np.linalg.det(u @ vt) < 0.0:  # a mirroring transform: the nearest rotation, not a reflection
        u[:, -1] = -u[:, -1]
    return u @ vt


def _fan(counts, idx) -> np.ndarray:
    """Polygons (face vertex counts, indices) split into triangle fans (T, 3)."""
    counts = np.asarray(counts, dtype=np.int64)
    idx = np.asarray(idx, dtype=np.int64)
    if (counts == 3).all():
        return idx.reshape(-1, 3)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    face = np.repeat(np.arange(len(counts)), counts - 2)
    k = np.arange(len(face)) - np.repeat(np.cumsum(counts - 2) - (counts - 2), counts - 2)
    first = start[face]
    return np.stack([idx[first], idx[first + k + 1], idx[first + k + 2]], axis=1)


def _held_stderr(method):
    """Run a reader method with what pxr prints to ``sys.stderr`` held back: on a damaged
    file pxr prints the Python error of a value it cannot convert and then raises its own;
    the raised error is reported (one line, by the caller), so the print is dropped. When the
    method succeeds whatever was printed is passed on."""

    @functools.wraps(method)
    def held(*args, **kwargs):
        buffer = io.StringIO()
        with contextlib.redirect_stderr(buffer):
            result = method(*args, **kwargs)
        if buffer.getvalue():
            sys.stderr.write(buffer.getvalue())
        return result

    return held


class NotAnOutput(ValueError):
    """A USD file that opens but holds no ``warp-esph run`` particles (a mesh file, say)."""


#: The file name endings pxr reads as USD (``UsdFrames`` refuses others up front).
USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")


class UsdFrames:
    """The particles, surfaces, colliders and tools of a ``UsdWriter`` file, frame by frame,
    all in metres and world coordinates (``placement``: another program's file may be in
    other units or under transforms)."""

    @_held_stderr
    def __init__(self, path):
        if not isinstance(path, (str, os.PathLike)):  # None, 123: a TypeError from os.fspath before
            raise ValueError(f"path = {checks.shown_path(path)} is not allowed: must be the path of a warp-esph USD file")
        self.path = os.fspath(path)
        if not self.path:  # (an unset shell variable) said as nothing: 'cannot read : no such file'
            raise FileNotFoundError("cannot read '': the path is empty; give the path of a warp-esph USD file")
        if not os.path.isfile(self.path):
            why = "it is a folder" if os.path.isdir(self.path) else f"no such file{checks.tilde_note(self.path)}"
            raise FileNotFoundError(f"cannot read {checks.shown_path(self.path, False)}: {why}")
        suffix = os.path.splitext(self.path)[1].lower()
        if suffix not in USD_SUFFIXES:
            # pxr's own words named no format it reads ("Cannot determine file format for @s.toml@").
            hint = ": a scene file is run with 'warp-esph run' (or warp_esph.simulate)" if suffix == ".toml" else ""
            raise ValueError(f"cannot read {checks.shown_path(self.path)}: it is not a USD file ({', '.join(USD_SUFFIXES)}){hint}")
        # Anonymous: a file rewritten in this process (run, then render) is read afresh.
        layer = open_layer_checked(self.path)
        if layer.GetCompositionAssetDependencies():
            # Another program's file that references, pays in or sublayers others: composed from
            # the file itself, so that relative paths ('./parts.usda') resolve beside it (from the
            # anonymous copy they resolved nowhere, and the file read as holding no frames).
            # Reloaded, as the anonymous copy is, in case this process holds an older one.
            layer = Sdf.Layer.FindOrOpen(self.path)
            layer.Reload(force=True)
        self._layer = layer
        with _native_stderr() as notes:
            self.stage = Usd.Stage.Open(layer)
        lost = [re.search(r"In <([^>]*)>: Could not open asset @([^@]*)@", n) for n in notes]
        lost = [m for m in lost if m]
        if lost:
            # pxr composes without what it cannot open, printing a warning: the prims it held
            # were missing, and the file read as holding no frames.
            raise ValueError(f"cannot read {checks.shown_path(self.path)}: the file {lost[0][2]} it refers to (at {lost[0][1]}) cannot be "
                             f"opened{f', nor {len(lost) - 1} more' if len(lost) > 1 else ''}")
        for n in notes:  # anything else pxr said, passed on
            if n.strip():
                sys.stderr.write(n + "\n")
        rate = float(self.stage.GetTimeCodesPerSecond())
        if not (math.isfinite(rate) and rate > 0.0):
            # 0 was read as 30 fps and -24 as -24 (negative times in frames.pvd, a GIF's warning).
            raise ValueError(f"cannot read {checks.shown_path(self.path)}: timeCodesPerSecond = {rate:g} is not allowed: must be a finite "
                             "number > 0 (the frames per second)")
        self.fps = rate
        #: Whether the file authors its rate (``timeCodesPerSecond`` or ``framesPerSecond``);
        #: else ``fps`` is USD's fallback, 24, which no program recorded.
        self.fps_authored = any(self.stage.HasAuthoredMetadata(k) for k in ("timeCodesPerSecond", "framesPerSecond"))
        data = dict(self.stage.GetRootLayer().customLayerData or {})
        # Read where it is used (render): export and fit read no view, yet warned about a bad one.
        self._stored_view = data.get(_VIEW)
        self.bodies = []       # (name, prim)
        for prim in self.stage.GetPrimAtPath(_ROOT).GetChildren() if self.stage.GetPrimAtPath(_ROOT) else []:
            if prim.IsA(UsdGeom.Points):
                self.bodies.append((prim.GetName(), prim))
        if not self.bodies:
            raise NotAnOutput(f"cannot read {checks.shown_path(self.path, False)}: it has no UsdGeom.Points under {_ROOT} (not a warp-esph output?)")
        times = set()
        #: Each body's sample times (an empty set: a body with a value for all time, no samples).
        self._samples = []
        for _, prim in self.bodies:
            self._samples.append(set(UsdGeom.Points(prim).GetPointsAttr().GetTimeSamples()))
            times.update(self._samples[-1])
        between = sorted(t for t in times if not float(t).is_integer())
        if between:
            # A frame is a whole time code: samples at 0.5 and 1.5 (another program's subframes)
            # were rounded onto frames 0 and 2, which were then drawn twice and the samples never read.
            raise ValueError(f"cannot read {checks.shown_path(self.path)}: its points have time samples at time codes that are not whole "
                             f"numbers ({', '.join(f'{t:g}' for t in between[:3])}{', ...' if len(between) > 3 else ''}); "
                             "a warp-esph output has one per frame, at time code = frame index")
        self.frames = sorted(int(t) for t in times)
        if self.frames and self.frames[0] < 0:
            # A fit target's frame -1 ended in a KeyError traceback, and '-1' of --frames counts
            # from the end, so a negative frame index cannot even be chosen.
            before = [f for f in self.frames if f < 0]
            raise ValueError(f"cannot read {checks.shown_path(self.path)}: its points have time samples at negative time codes "
                             f"({', '.join(map(str, before[:3]))}{', ...' if len(before) > 3 else ''}); "
                             "a warp-esph output has one per frame, at time code = frame index >= 0")
        if not self.frames:
            raise ValueError(f"cannot read {checks.shown_path(self.path, False)}: it holds no frames")
        #: Metres per unit of the file's coordinates (USD's fallback, centimetres, where not
        #: authored; a run's file authors 1).
        self.meters_per_unit = float(UsdGeom.GetStageMetersPerUnit(self.stage))
        if not UsdGeom.StageHasAuthoredMetersPerUnit(self.stage):
            warnings.warn(f"{checks.shown_path(self.path, False)}: its stage does not author metersPerUnit, so USD's fallback of "
                          f"{self.meters_per_unit:g} m per unit (centimetres) is assumed (USD's rule); if its points are "
                          "in metres, author metersPerUnit = 1 in the file (UsdGeom.SetStageMetersPerUnit)",
                          UserWarning, stacklevel=3)
        self.material_ids = []
        self.display_colors = []
        for _, prim in self.bodies:
            mid = prim.GetAttribute(_PRIMVAR_MATERIAL_ID).Get()
            self.material_ids.append(int(mid) if mid is not None else 0)
            col = UsdGeom.Points(prim).GetDisplayColorAttr().Get()
            self.display_colors.append(np.array(col[0], dtype=np.float32) if col else np.array((0.8, 0.6, 0.4), np.float32))
        try:
            self.colliders = self._read_colliders()
            #: The tools (moving colliders) under ``/World/Tools``; pinned sets are left out.
            self.tools = self._read_tools()
        except (TypeError, IndexError, KeyError, AttributeError, ValueError) as e:
            # A damaged file can hold a collider or tool prim whose custom data or geometry is
            # missing or of the wrong type; say which file, not the parser's traceback. Nothing
            # they call raises a message naming the file, so every error is wrapped: a re-raise of
            # those whose text held the path let float()'s bare words out for a value that held it.
            detail = (str(e).strip().splitlines() or [checks.read_reason(e)])[0]
            raise ValueError(f"cannot read {checks.shown_path(self.path, False)}: a collider or tool is damaged ({detail})") from None
        # The surface Mesh of each body (``surface_prim_path``), or None where the file has none.
        self.surface_prims = []
        for name, _ in self.bodies:
            prim = self.stage.GetPrimAtPath(surface_prim_path(name))
            self.surface_prims.append(prim if prim and prim.IsA(UsdGeom.Mesh) else None)

    @property
    def view(self) -> tuple[float, float] | None:
        """The ``(azimuth, elevation)`` the file suggests (``_read_view``: None, with a warning
        naming the file, where it holds no pair of finite degrees), read on first use."""
        if not hasattr(self, "_view"):
            self._view = None if self._stored_view is None else _read_view(self.path, self._stored_view)
        return self._view

    @property
    def has_surfaces(self) -> bool:
        """Whether any body has a surface Mesh prim (``warp-esph run --surface``)."""
        return any(p is not None for p in self.surface_prims)

    @_held_stderr
    def surface(self, frame: int, body: int):
        """``(vertices (V, 3) float32, triangles (T, 3) int64)`` of body ``body``'s surface at
        ``frame`` (polygons split into fans), or None where there is no surface, it is empty,
        or its points have time samples but none at ``frame``."""
        prim = self.surface_prims[body]
        if prim is None:
            return None
        t = Usd.TimeCode(float(frame))
        mesh = UsdGeom.Mesh(prim)
        points = mesh.GetPointsAttr()
        if points.GetNumTimeSamples() and not points.GetTimeSamplesInInterval(Gf.Interval(float(frame), float(frame))):
            # USD answers with the last sample held: a file continued without surfaces (append,
            # surface=False) drew the body as its surface of the resume frame, standing still.
            return None
        pts, counts, idx = (a.Get(t) for a in (mesh.GetPointsAttr(), mesh.GetFaceVertexCountsAttr(),
                                                mesh.GetFaceVertexIndicesAttr()))
        if pts is None or counts is None or idx is None or len(pts) == 0 or len(counts) == 0:
            return None
        v = np.asarray(pts, dtype=np.float32).reshape(-1, 3)
        counts = np.asarray(counts, dtype=np.int64)
        idx = np.asarray(idx, dtype=np.int64)
        if counts.sum() != len(idx) or (counts < 3).any() or idx.min() < 0 or idx.max() >= len(v):
            raise ValueError(f"cannot read {checks.shown_path(self.path, False)}: the surface {prim.GetPath()} at frame {frame} is not a valid mesh")
        tri = _fan(counts, idx)
        world = self.placement(prim, frame)
        if world is not None:  # in metres and world coordinates, as the particles (arrays)
            v = (v.astype(np.float64) @ world[0] + world[1]).astype(np.float32)
        keep = np.isfinite(v).all(axis=1)
        if not keep.all():
            tri = tri[keep[tri].all(axis=1)]
        return (v, tri) if len(tri) else None

    def _read_colliders(self) -> list[Collider]:
        """The static colliders in metres and world coordinates, as the particles are read:
        their geometry (custom data, in the coordinates of the prim's parent: a plane's normal
        and offset too, its quad in its own, and drawn where it lies on the plane) under the
        transforms of the first frame and the stage's metersPerUnit (a box turned off the axes
        by them is held as its axis-aligned bounds)."""
        out = []
        scope = self.stage.GetPrimAtPath(_COLLIDERS)
        if not scope:
            return out
        first = self.frames[0]
        for prim in scope.GetChildren():
            kind = prim.GetCustomDataByKey(f"{_KEY}:collider")
            get = prim.GetCustomDataByKey
            if kind == "plane":
                n = np.array(get(f"{_KEY}:normal"), dtype=np.float64)
                n /= np.linalg.norm(n)
                offset = float(get(f"{_KEY}:offset"))
                pts = np.array(UsdGeom.Mesh(prim).GetPointsAttr().Get(), dtype=np.float64)
                quad = self.placement(prim, first)
                if quad is not None:
                    pts = pts @ quad[0] + quad[1]
                # The normal and offset, as every collider's custom data (the sphere's and box's
                # centre), in the parent's frame: they were moved by the plane prim's own
                # transform too, so a foreign file that moved the quad moved the plane it shows.
                world = self.placement(prim, first, parent=True)
                if world is not None:
                    A, b = world
                    # n . x = offset with x = (x_w - b) A^-1: m . x_w = offset + m . b, m = n A^-T.
                    m = n @ np.linalg.inv(A).T
                    n, offset = m / np.linalg.norm(m), (offset + float(m @ b)) / float(np.linalg.norm(m))
                center = pts.mean(axis=0)
                if quad is not None:  # a quad moved off its plane by its own transform is drawn on it
                    center = center - (float(n @ center) - offset) * n
                half = 0.5 * float(np.linalg.norm(pts[1] - pts[0]))
                out.append(Collider("plane", center, np.array([half, 0.0, 0.0]), n, offset))
            elif kind in ("sphere", "box"):
                center = np.array(get(f"{_KEY}:center"), dtype=np.float64)
                size = np.full(3, float(get(f"{_KEY}:radius"))) if kind == "sphere" else \
                    np.array(get(f"{_KEY}:half_extents"), dtype=np.float64)
                world = self.placement(prim, first, parent=True)
                if world is not None:
                    A, b = world
                    center = center @ A + b
                    size = size * _scale_of(A) if kind == "sphere" else size @ np.abs(A)
                out.append(Collider(kind, center, size))
        return out

    def _read_tools(self) -> list[Tool]:
        out = []
        scope = self.stage.GetPrimAtPath(tools.USD_ROOT)
        if not scope:
            return out
        for prim in scope.GetChildren():
            kind = prim.GetCustomDataByKey(f"{_KEY}:tool")
            geom = prim.GetChild("geom")
            if kind not in tools.KINDS or not geom:
                continue  # a pinned set (no geometry) or something this reader does not know
            name = str(prim.GetCustomDataByKey(f"{_KEY}:tool_name") or prim.GetName())
            param, points, tri = np.zeros(3), None, None
            if kind == "box":
                scale = np.ones(3)
                for op in UsdGeom.Xformable(geom).GetOrderedXformOps():
                    if op.GetOpType() == UsdGeom.XformOp.TypeScale:
                        scale = np.array(op.Get(), dtype=np.float64)
                param = scale * 0.5 * float(UsdGeom.Cube(geom).GetSizeAttr().Get() or 2.0)
            elif kind == "sphere":
                param = np.array([float(UsdGeom.Sphere(geom).GetRadiusAttr().Get()), 0.0, 0.0])
            elif kind in ("capsule", "cylinder"):
                g = (UsdGeom.Capsule if kind == "capsule" else UsdGeom.Cylinder)(geom)
                param = np.array([float(g.GetRadiusAttr().Get()), 0.5 * float(g.GetHeightAttr().Get()), 0.0])
            else:
                mesh = UsdGeom.Mesh(geom)
                points = np.asarray(mesh.GetPointsAttr().Get(), dtype=np.float64).reshape(-1, 3)
                tri = _fan(mesh.GetFaceVertexCountsAttr().Get(), mesh.GetFaceVertexIndicesAttr().Get())
                if kind == "plane":
                    # The quad faces +n (tools.usd_author: t1 x t2 = n).
                    n = np.cross(points[1] - points[0], points[2] - points[1])
                    param = n / np.linalg.norm(n)
            param = np.asarray(param, dtype=np.float64)
            world = self.placement(prim, self.frames[0], parent=True)
            if world is not None:
                # The shape in metres, by the mean scale of the transforms over the tool (those
                # of the first frame); its pose takes their rotation and translation per frame.
                s = _scale_of(world[0])
                param = param if kind == "plane" else param * s
                points = None if points is None else points * s
            out.append(Tool(name, kind, prim, param, points, tri,
                            placement=functools.partial(self.placement, prim, parent=True)))
        return out

    def has_sample(self, body: int, frame: int) -> bool:
        """Whether body ``body`` (index into ``bodies``) has points at ``frame``: a time sample
        there, or no samples at all (a value for all time)."""
        return not self._samples[body] or float(frame) in self._samples[body]

    def to_world(self, body: int, frame: int):
        """``(A (3, 3), b (3,))`` taking body ``body``'s points at ``frame`` to metres and world
        coordinates as ``p @ A + b`` (its prim's local-to-world transform, then
        ``meters_per_unit``), or None where that is the identity (a run's own file)."""
        return self.placement(self.bodies[body][1], frame)

    def placement(self, prim, frame: int, parent: bool = False):
        """``(A (3, 3), b (3,))`` taking coordinates in ``prim``'s own frame (``parent``: its
        parent's) at ``frame`` to metres and world coordinates as ``p @ A + b``, or None where
        that is the identity. Every geometry of the file is read through it: particles
        (``to_world``), surfaces, colliders and tools alike."""
        t = Usd.TimeCode(float(frame))
        xf = UsdGeom.Xformable(prim)
        M = np.array(xf.ComputeParentToWorldTransform(t) if parent else xf.ComputeLocalToWorldTransform(t), dtype=np.float64)
        if self.meters_per_unit == 1.0 and np.array_equal(M, np.eye(4)):
            return None  # skipped, not multiplied: a float64 run's positions read to the bit
        # USD matrices act on row vectors: p_world = [p, 1] @ M.
        return M[:3, :3] * self.meters_per_unit, M[3, :3] * self.meters_per_unit

    def _placement_rate(self, prim, frame: int):
        """``(dA/dt, db/dt)`` per second of ``placement(prim)`` at ``frame``, or None where it
        does not change: the difference over half a frame either side (USD interpolates a
        transform's samples linearly between frames; at a frame where its rate changes, this
        is the mean of the two), one-sided at the file's first and last frame."""
        lo = max(frame - 0.5, self.frames[0])
        hi = min(frame + 0.5, self.frames[-1])
        if hi <= lo:
            return None
        before, after = ((np.eye(3), np.zeros(3)) if w is None else w for w in (self.placement(prim, lo), self.placement(prim, hi)))
        if all(np.array_equal(x, y) for x, y in zip(before, after)):
            return None
        per_second = self.fps / (hi - lo)
        return (after[0] - before[0]) * per_second, (after[1] - before[1]) * per_second

    def _holds(self, frame: int) -> bool:
        # A search of the sorted frames: 'frame in self.frames' scanned them all, and reading
        # each of F frames cost O(F^2).
        try:
            i = bisect.bisect_left(self.frames, frame)
        except TypeError:  # not a number: held by no file, as 'in' answered
            return False
        return i < len(self.frames) and self.frames[i] == frame

    def resolve(self, frame: int) -> int:
        if not self._holds(frame):
            raise ValueError(f"frame = {checks.shorten(frame)!r} is not allowed: {checks.shown_path(self.path, False)} holds frames {self.frames[0]}..{self.frames[-1]}")
        return frame

    def _frame(self, frame) -> int:
        # A frame not in the file read as no particles at all (every body without a sample
        # there), and True, 1.0 or '1' as frame 1.
        if isinstance(frame, (int, np.integer)) and not isinstance(frame, (bool, np.bool_)) and self._holds(int(frame)):
            return int(frame)
        held = (f"{self.frames[0]}..{self.frames[-1]}" if self.frames == list(range(self.frames[0], self.frames[-1] + 1))
                else ", ".join(map(str, self.frames[:8])) + (", ..." if len(self.frames) > 8 else ""))
        raise ValueError(f"frame = {checks.shorten(frame)!r} is not allowed: must be one of the file's frames ({held})")

    @_held_stderr
    def arrays(self, frame: int) -> dict:
        """Every particle at ``frame``: points, velocities, widths, alpha, singular_values
        (N, 3), body (index into ``bodies``) and material_id. Points, velocities and widths are
        in metres and world coordinates (``to_world``; a run's file is read as written, float64
        where a float64 run wrote them, to the last bit, else float32; alpha and
        singular_values likewise); velocities under a
        time-sampled transform carry its motion too (``_placement_rate``). A body without a
        sample at ``frame`` (``has_sample``) is left out of it. ``frame`` must be one of
        ``frames`` (a ``ValueError`` names it)."""
        frame = self._frame(frame)
        t = Usd.TimeCode(float(frame))
        cols = {k: [] for k in ("points", "velocities", "widths", "alpha", "singular_values", "body", "material_id")}
        for k, (_, prim) in enumerate(self.bodies):
            if not self.has_sample(k, frame):
                # USD answers between samples with the last one held, or interpolated: a body of
                # another program's file whose samples stopped (or skipped a frame) was drawn and
                # exported there standing still, or on a straight line, which nothing recorded.
                continue
            geom = UsdGeom.Points(prim)
            p = geom.GetPointsAttr().Get(t)
            if p is None or len(p) == 0:
                continue
            n = len(p)

            def get(attr, shape, fill, keep_doubles=False):
                value = attr.Get(t) if attr else None
                if value is None or len(value) != n:
                    return np.full(shape, fill, dtype=np.float32)
                # A float64 run's primvars are double: read as written, not rounded.
                double = keep_doubles and attr.GetTypeName() in (Sdf.ValueTypeNames.DoubleArray, Sdf.ValueTypeNames.Double3Array)
                return np.asarray(value, dtype=np.float64 if double else np.float32).reshape(shape)

            # Only a sample at this very frame: Get(t) answers with the nearest one, and a file a
            # float64 run began before these attributes existed (then resumed) has them only
            # from the resume on, so its earlier frames read as the resume frame.
            here = Gf.Interval(float(frame), float(frame))
            exact = [prim.GetAttribute(key) for key in (_POINTS64, _VELOCITIES64)]
            exact = [a.Get(t) if a and a.GetTimeSamplesInInterval(here) else None for a in exact]
            if all(e is not None and len(e) == n for e in exact):  # a float64 run's own values
                cols["points"].append(np.asarray(exact[0], dtype=np.float64).reshape(n, 3))
                cols["velocities"].append(np.asarray(exact[1], dtype=np.float64).reshape(n, 3))
            else:
                cols["points"].append(np.asarray(p, dtype=np.float32))
                cols["velocities"].append(get(geom.GetVelocitiesAttr(), (n, 3), 0.0))
            # Checked where they are used (particles: the renderer's radii), not here: export and
            # fit targets never read them, and refused another program's file of widths 0.
            widths = get(geom.GetWidthsAttr(), (n,), 0.02)
            world = self.to_world(k, frame)
            if world is not None:
                # Another program's points in centimetres or under a transform: in metres and
                # world coordinates, as a fit target and a mesh are read (widths by the
                # transform's mean scale; a velocity by its linear part, plus the motion of a
                # time-sampled transform, so that it is the rate of the positions read).
                A, b = world
                local = cols["points"][-1].astype(np.float64)
                cols["points"][-1] = local @ A + b
                cols["velocities"][-1] = cols["velocities"][-1].astype(np.float64) @ A
                rate = self._placement_rate(prim, frame)
                if rate is not None:
                    cols["velocities"][-1] += local @ rate[0] + rate[1]
                widths = (widths * abs(np.linalg.det(A)) ** (1.0 / 3.0)).astype(np.float32)
            cols["widths"].append(widths)
            cols["alpha"].append(get(prim.GetAttribute(_PRIMVAR_ALPHA), (n,), 0.0, keep_doubles=True))
            cols["singular_values"].append(get(prim.GetAttribute(_PRIMVAR_SINGULAR_VALUES), (n, 3), 1.0, keep_doubles=True))
            cols["body"].append(np.full(n, k, np.int32))
            cols["material_id"].append(np.full(n, self.material_ids[k], np.int32))
        if cols["points"] and not np.isfinite(np.concatenate(cols["points"])).all(axis=1).any():
            # The writer never writes a non-finite particle: a frame without one finite is damaged
            # (it rendered as an empty picture and exported NaN, both exiting 0).
            raise ValueError(f"cannot read {checks.shown_path(self.path)}: frame {frame} has no particle with a finite position "
                             "(not a warp-esph output, or damaged)")
        shapes = {"points": (0, 3), "velocities": (0, 3), "singular_values": (0, 3)}
        return {k: (np.concatenate(v) if v else np.zeros(shapes.get(k, (0,)), np.int32 if k in ("body", "material_id") else np.float32))
                for k, v in cols.items()}

    def particles(self, frame: int) -> dict:
        """What the renderer needs at ``frame``: points, radius, body, material, alpha and the
        elastic strain ``max_k |ln sigma_k|`` (as ``singular_values``); non-finite particles dropped."""
        a = self.arrays(frame)
        bad = ~(np.isfinite(a["widths"]) & (a["widths"] > 0.0))
        if bad.any():  # a NaN width failed inside the renderer
            raise ValueError(f"cannot read {checks.shown_path(self.path)}: body {self.bodies[int(a['body'][bad.argmax()])][0]!r} at frame {frame} "
                             "has widths that are not finite and > 0 (not a warp-esph output, or damaged; the particles are "
                             "drawn as spheres of these diameters)")
        with np.errstate(divide="ignore", invalid="ignore"):
            strain = np.abs(np.log(np.abs(a["singular_values"]))).max(axis=1) if len(a["points"]) else np.zeros(0, np.float32)
        out = {"points": a["points"], "radius": 0.5 * a["widths"], "body": a["body"], "material": a["material_id"],
               "alpha": a["alpha"], "singular_values": strain.astype(np.float32)}
        keep = np.isfinite(a["points"]).all(axis=1)
        if not keep.all():
            out = {k: v[keep] for k, v in out.items()}
        return out

    #: A body whose extent grows past this many times its first rendered frame's has blown
    #: up: it is left out of the framing, which would otherwise shrink the rest to a dot.
    BLOWN_UP = 20.0

    @_held_stderr
    def bounds(self, frames) -> tuple[np.ndarray, np.ndarray]:
        """Bounds of the particles over ``frames`` (the per-frame ``extent`` where written),
        leaving out a body in the frames where it has blown up (``BLOWN_UP``)."""
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        first_size = {}
        for f in frames:
            t = Usd.TimeCode(float(f))
            for k, (_, prim) in enumerate(self.bodies):
                if not self.has_sample(k, f):
                    continue  # not drawn there (arrays)
                geom = UsdGeom.Points(prim)
                ext = geom.GetExtentAttr().Get(t)
                if ext is not None and len(ext) == 2:
                    e = np.array(ext, dtype=np.float64)
                else:
                    p = geom.GetPointsAttr().Get(t)
                    if p is None or len(p) == 0:
                        continue
                    p = np.asarray(p, dtype=np.float64)
                    e = np.stack([np.nanmin(p, axis=0), np.nanmax(p, axis=0)])
                if not np.isfinite(e).all():
                    continue
                world = self.to_world(k, f)
                if world is not None:  # the box's corners, as arrays reads the points
                    corners = np.array([[e[i, 0], e[j, 1], e[m, 2]] for i in (0, 1) for j in (0, 1) for m in (0, 1)])
                    corners = corners @ world[0] + world[1]
                    e = np.stack([corners.min(axis=0), corners.max(axis=0)])
                size = float((e[1] - e[0]).max())
                size0 = first_size.setdefault(k, size)
                if size > self.BLOWN_UP * max(size0, 1e-6):
                    continue
                lo, hi = np.minimum(lo, e[0]), np.maximum(hi, e[1])
        if not np.isfinite(lo).all():
            lo, hi = np.full(3, -0.5), np.full(3, 0.5)
        return lo, hi


def parse_frames(spec, available: list[int], what: str = "frames", repeats: bool = False) -> list[int]:
    """Frame indices from a spec: ``all``, ``first``, ``last``, ``N``, ``-N`` (from the end),
    ``A:B`` or ``A:B:STEP`` (B inclusive, either may be left out), or a comma list of those;
    or any other iterable of frame numbers (a range, a 1-D numpy array, an iterator; not a
    nested list or a 2-D array). ``what``: how a refusal names the spec (the CLI's ``--frames``).
    A frame named twice (``1,1``, ``last,2`` of frames 0..2) is refused unless ``repeats``
    (an animation, where a repeat holds the frame)."""
    if spec is None:
        return list(available)
    if isinstance(spec, np.ndarray) and spec.ndim == 0:
        spec = spec.item()
    if not isinstance(spec, (str, bytes, list, tuple, int, np.integer)):
        # Converted here, once, for every caller: the Renderer converted a range, a numpy array
        # or an iterator itself, while render_usd, export and the fit targets, which called this
        # directly, refused them ('frames = array([0, 2]) is not allowed').
        try:
            # An array as plain numbers: list() kept numpy scalars and rows, which the refusal
            # showed as 'frames = [np.float64(0.5), ...]' or '[array([0, 1])]'.
            spec = spec.tolist() if isinstance(spec, np.ndarray) else list(spec)
        except TypeError:
            pass  # not iterable: refused below by its value
    shown = spec  # as given: a list was shown joined ('' for [], '1,x' for [1, 'x'])

    def plain(v):
        # Frames picked with numpy were shown as numpy writes them: 'np.int64(3)'.
        if isinstance(v, np.ndarray) and v.ndim == 0:
            v = v.item()
        return int(v) if isinstance(v, np.integer) else v

    if isinstance(spec, (list, tuple)):
        shown = [s.tolist() if isinstance(s, np.ndarray) and s.ndim else plain(s) for s in spec]
        shown = tuple(shown) if isinstance(spec, tuple) else shown
        # A 2-D array or a list of lists was joined into one text and split at its commas, so the
        # refusal blamed a fragment of an entry: "'[0' is not 'all', ...".
        nested = next((s for s, v in zip(shown, spec)
                       if not isinstance(v, (str, bytes)) and hasattr(v, "__iter__")
                       and not (isinstance(v, np.ndarray) and v.ndim == 0)), None)
        if nested is not None:
            raise ValueError(f"{what} = {checks.shorten(shown)!r} is not allowed: its entry {checks.shorten(nested)!r} is itself "
                             "a sequence (a nested list or a 2-D array); frames must be frame numbers, a range or 'all', "
                             "e.g. [0, 30, 60], range(0, 61, 5), '0:60:5' or 'all'")
    else:
        shown = plain(spec)
    if isinstance(spec, (int, np.integer)) and not isinstance(spec, bool):
        spec = str(int(spec))
    if isinstance(spec, (list, tuple)):
        spec = ",".join(str(s) for s in spec)
    if not isinstance(spec, str) or not spec.strip():
        raise ValueError(f"{what} = {checks.shorten(shown)!r} is not allowed: give e.g. 'all', 'last', '10', '0:60:5' or '0,30,60'")
    if not len(available):
        # An IndexError before: 'first' of nothing names no frame, and no spec selects one.
        raise ValueError(f"{what} = {checks.shorten(shown)!r} is not allowed: there is no frame to choose from (none is held)")
    first, last = available[0], available[-1]
    have = set(available)

    def one(text: str) -> int:
        v = int(text)
        if v == 0 and text.lstrip().startswith("-"):  # '-0': from the end, or frame 0? neither said
            raise ValueError
        return last + 1 + v if v < 0 else v

    out: list[int] = []
    past = bad_step = None
    for part in spec.split(","):
        p = part.strip().lower()
        try:
            if p == "all":
                out.extend(available)
            elif p == "first":
                out.append(first)
            elif p == "last":
                out.append(last)
            elif ":" in p:
                bits = p.split(":")
                if len(bits) > 3:
                    raise ValueError
                a = one(bits[0]) if bits[0] else first
                b = one(bits[1]) if bits[1] else last
                step = int(bits[2]) if len(bits) == 3 and bits[2] else 1
                if step < 1:
                    # Of the form A:B:STEP: refused as not being it, which left the step to be guessed.
                    bad_step = (part.strip(), step)
                    break
                if b > last or a > last:
                    # Cut at the last frame without a word: render 0:100 of 11 frames drew 11.
                    # One starting past it was told to end there, which selects nothing.
                    past, late = part.strip(), a > last
                    break
                if a < first:
                    # Cut at the first frame without a word, as at the end: 0:6 of an .npz storing
                    # frames 2, 4, 6 fitted 2..6, -20: of 11 frames drew 0..10.
                    past, late = part.strip(), None
                    break
                out.extend(f for f in available if a <= f <= b and (f - a) % step == 0)
            else:
                out.append(one(p))
        except ValueError:
            raise ValueError(
                f"{what} = {checks.shorten(shown)!r} is not allowed: {checks.shorten(part)!r} is not 'all', 'first', 'last', N, -N, A:B or A:B:STEP"
            ) from None
    if bad_step is not None:
        raise ValueError(f"{what} = {checks.shorten(shown)!r} is not allowed: {checks.shorten(bad_step[0])!r} steps by {bad_step[1]}: "
                         "the STEP of A:B:STEP must be an integer >= 1 (B included)")
    if past is not None:
        held = f"{last}: it holds {len(available)} frames, {first}..{last}"
        if late is None:
            start = past.split(":")[0].strip()
            if start.startswith("-"):
                raise ValueError(f"{what} = {checks.shorten(shown)!r} is not allowed: {checks.shorten(past)!r} counts back past "
                                 f"the first frame (the file holds {first}..{last}, so -1 to -{last + 1 - first})")
            # (a and step: the range refused.) Its frames step from its start: where the first frame
            # is off that step, neither starting at it nor leaving the start out keeps them ('0:100:10'
            # of frames 1..100 is 10, 20, ...; from 1 it would be 1, 11, ...).
            on_step = a + -((a - first) // step) * step
            how = (f"start the range at {first} or leave its start out" if on_step == first else
                   f"start the range at {on_step}, the first frame on its step from {first} on (starting at {first} "
                   f"would choose {first}, {first + step}, ...)")
            raise ValueError(f"{what} = {checks.shorten(shown)!r} is not allowed: {checks.shorten(past)!r} starts before the "
                             f"file's first frame, {first}: it holds {len(available)} frames, {first}..{last}; {how}")
        if late:
            raise ValueError(f"{what} = {checks.shorten(shown)!r} is not allowed: {checks.shorten(past)!r} starts past the "
                             f"file's last frame, {held}")
        raise ValueError(f"{what} = {checks.shorten(shown)!r} is not allowed: {checks.shorten(past)!r} runs past the file's "
                         f"last frame, {held}; end the range at {last} or leave its end out")
    missing = [f for f in out if f not in have]
    if missing and missing[0] < 0:  # -N counted back past the first frame
        raise ValueError(f"{what} = {checks.shorten(shown)!r} is not allowed: it counts back past the first frame (the file holds "
                         f"{first}..{last}, so -1 to -{last + 1 - first})")
    if missing:
        raise ValueError(f"{what} = {checks.shorten(shown)!r} is not allowed: frame {missing[0]} is not in the file (it holds {first}..{last})")
    if not out:
        raise ValueError(f"{what} = {checks.shorten(shown)!r} is not allowed: it selects no frame of the file (it holds {first}..{last})")
    if not repeats:
        # A sheet drew the frame twice, a fit's target weighed it twice, and export and a
        # folder of pictures wrote it once while the rest of the selection was taken as asked.
        seen = set()
        twice = next((f for f in out if f in seen or seen.add(f)), None)
        if twice is not None:
            raise ValueError(f"{what} = {checks.shorten(shown)!r} is not allowed: it names frame {twice} twice; name each "
                             "frame once")
    return out
