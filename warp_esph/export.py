"""Particle frames for ParaView and other tools: one ``.vtu`` or ``.ply`` file per frame (meshio).

Reads a file ``UsdWriter`` wrote and writes, for every chosen frame, the particles as
points (one ``vertex`` cell each, so ParaView shows them without a filter) with point
data:

=================  =========  =================================================================
name               shape      meaning
=================  =========  =================================================================
velocity           (N, 3)     m/s, in world coordinates (with the motion of a moving transform)
alpha              (N,)       accumulated plastic strain
singular_values    (N, 3)     signed singular values of the elastic deformation gradient (the
                              smallest negative where it is inverted, det F < 0)
body_id            (N,)       index of the body (order of the USD prims / the model)
material_id        (N,)       index of the material
=================  =========  =================================================================

PLY has no vector properties: there ``velocity`` and ``singular_values`` become
``velocity_x``/``_y``/``_z`` and ``singular_values_0``/``_1``/``_2``. For ``.vtu`` a
``frames.pvd`` collection beside the frames gives ParaView the time of each one (open it
instead of the single files). File names: ``frame_00012.vtu`` (the frame index).
Points are float64; velocity, alpha and singular_values are float64 from a float64 run's
file (``--dtype float64``, to the last bit), float32 from a float32 run's.
"""

from __future__ import annotations

import os
from xml.sax.saxutils import quoteattr

import numpy as np

from .checks import OutputWriteError

__all__ = ["EXPORT_FORMATS", "ExportWriteError", "export_frames", "frame_arrays_to_mesh"]

EXPORT_FORMATS = ("vtu", "ply")


def _kept(files: list[str], chosen: int, folder: str) -> str:
    """The frames an export that stopped early leaves whole in ``folder``."""
    frames = sum(not f.endswith(".pvd") for f in files)
    listed = "; frames.pvd lists them" if any(f.endswith(".pvd") for f in files) else ""
    return f"{frames} of the {chosen} frames are written whole in {folder}{listed}"


class ExportWriteError(OutputWriteError):
    """A file ``export_frames`` could not write (a full disk, a folder gone); ``files``: those
    it wrote whole before, which stay. Its text names the file and what is kept."""

    def __init__(self, cause: OSError, files: list[str], chosen: int, folder: str):
        self.files = list(files)
        super().__init__(f"cannot write {cause.filename or folder}: {cause.strerror or cause} "
                         f"({_kept(files, chosen, folder)})", cause)


def _real(values) -> np.ndarray:
    a = np.asarray(values)
    return a if a.dtype == np.float64 else a.astype(np.float32)


def frame_arrays_to_mesh(arrays: dict, fmt: str):
    """A ``meshio.Mesh`` of one frame's particle arrays (``UsdFrames.arrays``)."""
    import meshio  # noqa: PLC0415

    pts = np.asarray(arrays["points"], dtype=np.float64)
    n = len(pts)
    data = {
        "velocity": np.asarray(arrays["velocities"]),  # float64 where a float64 run wrote it
        # As written: float64 where a float64 run wrote them, else float32.
        "alpha": _real(arrays["alpha"]),
        "singular_values": _real(arrays["singular_values"]),
        "body_id": np.asarray(arrays["body"], dtype=np.int32),
        "material_id": np.asarray(arrays["material_id"], dtype=np.int32),
    }
    if fmt == "ply":
        for name, suffixes in (("velocity", "xyz"), ("singular_values", "012")):
            vec = data.pop(name)
            for k, s in enumerate(suffixes):
                data[f"{name}_{s}"] = np.ascontiguousarray(vec[:, k])
    # PLY has no 64-bit integers (meshio casts them down, warning once per file).
    cells = [("vertex", np.arange(n, dtype=np.int32 if fmt == "ply" else np.int64).reshape(-1, 1))] if n else []
    return meshio.Mesh(pts, cells, point_data=data)


def export_frames(usd_path, fmt: str, output_dir, frames=None, progress=None, flag=None, clear: bool = False) -> list[str]:
    """Write ``frames`` (see ``usd.parse_frames``; default all) of ``usd_path`` as ``fmt``
    (``vtu`` or ``ply``) files into ``output_dir`` (created, but not its parents: a missing parent
    folder is a ``ValueError``); returns the files written. A frame named twice is refused. A file
    that cannot be written raises ``ExportWriteError`` (an ``OSError``) naming it; the files
    written before stay whole, and ``frames.pvd`` lists them where it can still be written; a
    Ctrl-C raises a ``KeyboardInterrupt`` whose ``kept`` says so (``checks.interrupted``).
    ``flag(name)``: how a refusal names the option ``name`` (the CLI's ``--frames``). ``clear``
    (the CLI's): first remove the frame files of an earlier export in ``output_dir``
    (``checks.remove_frame_files``: ``frame_NNNNN.<fmt>``, and ``frames.pvd`` for ``vtu``; no
    other file), once the input and the selection are checked, so that the folder holds this
    export's frames alone, also when it stops early."""
    import meshio  # noqa: PLC0415

    from . import checks  # noqa: PLC0415
    from .usd import UsdFrames, parse_frames  # noqa: PLC0415

    flag = flag or (lambda name: name)
    fmt = checks.choice(flag("format"), fmt, EXPORT_FORMATS)
    if progress is not None and not callable(progress):  # 5 failed after the first frame was written
        raise ValueError(f"progress = {checks.shorten(progress)!r} is not allowed: must be callable as progress(k, n)")
    out = checks.output_place(flag("output"), output_dir, folder=True)
    if os.path.splitext(out)[1].lower() in (".vtu", ".ply", ".pvd") and not os.path.isdir(out):
        # 'export -o out.vtu' made a folder named out.vtu: the user named a file and got a folder.
        # A folder of that name already there is written into: it is what the name means there.
        pvd = " and frames.pvd" if fmt == "vtu" else ""
        raise ValueError(f"{flag('output')} = {checks.shown_path(out)} is not allowed: it names a file, and {flag('output')} is "
                         f"the folder the frames' files are written into (frame_00000.{fmt}, frame_00001.{fmt}, ...{pvd}): "
                         "give a folder's name")
    data = UsdFrames(usd_path)
    # One file per frame: a frame named twice is refused (it was written once and counted twice).
    chosen = parse_frames(frames, data.frames, flag("frames"))
    checks.output_files(flag("output"), out, [f"frame_{f:05d}.{fmt}" for f in chosen] + ["frames.pvd"] * (fmt == "vtu"))
    if clear:
        checks.remove_frame_files(out, fmt)
    os.makedirs(out, exist_ok=True)
    files = []

    def collection():
        # The collection lists the frames written, also when the export stops early.
        if fmt == "vtu" and files:
            lines = ['<?xml version="1.0"?>', '<VTKFile type="Collection" version="0.1">', "  <Collection>"]
            for f, file in zip(chosen, files):
                lines.append(f"    <DataSet timestep=\"{f / data.fps:.9g}\" file={quoteattr(os.path.basename(file))}/>")
            lines += ["  </Collection>", "</VTKFile>", ""]
            pvd = os.path.join(out, "frames.pvd")
            with checks.replaced_atomically(pvd) as part, open(part, "w") as fh:
                fh.write("\n".join(lines))
            files.append(pvd)

    f = None
    try:
        for k, f in enumerate(chosen):
            file = os.path.join(out, f"frame_{f:05d}.{fmt}")
            mesh = frame_arrays_to_mesh(data.arrays(f), fmt)
            # Whole or not at all: Ctrl-C inside a write left a truncated file, over the same
            # frame of an earlier export too.
            with checks.replaced_atomically(file) as part:
                meshio.write(part, mesh, file_format=fmt, binary=True)
            files.append(file)
            if progress is not None:
                progress(k + 1, len(chosen))
    except BaseException as e:
        try:
            collection()
        except OSError:
            # On a full disk the collection fails too, and its error stood in place of the
            # frame's: a bare '[Errno 28] No space left on device', naming no file.
            pass
        if isinstance(e, OSError):
            raise ExportWriteError(e, files, len(chosen), out) from e
        if isinstance(e, KeyboardInterrupt) and getattr(e, "kept", None) is None:
            raise checks.interrupted(_kept(files, len(chosen), out)) from e
        checks.stopped_writing(e, _kept(files, len(chosen), out), f)
        raise
    try:
        collection()
    except OSError as e:
        raise ExportWriteError(e, files, len(chosen), out) from e
    except KeyboardInterrupt as e:
        # Every frame is whole by now: the line said 'interrupted' alone, as if none were.
        raise checks.interrupted(f"{_kept(files, len(chosen), out)}; frames.pvd is not written") from e
    except Exception as e:
        checks.stopped_writing(e, f"{_kept(files, len(chosen), out)}; frames.pvd is not written")
        raise
    return files
