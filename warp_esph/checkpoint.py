"""Checkpoints: the full simulation state in one ``.npz`` file, written atomically.

A checkpoint holds every array a step reads (``State.STATE_FIELDS``: ``x, v, F, alpha`` and
the rest-configuration model's ``F_p``; an older checkpoint without it loads it as ``I``),
the simulated time, the current values of
the per-material parameters (they may have been fitted or edited since the scene was
built), the step and frame counters, and a free-form ``run`` record (the CLI stores the
scene, scale, time step and output there). The step depends on nothing else, so on the
CPU a run resumed from a checkpoint reproduces the uninterrupted run bit for bit.
"""

from __future__ import annotations

import json
import os
import pathlib
import tempfile
import zipfile

import numpy as np

from .model import Model, State

FORMAT = "warp_esph.checkpoint/1"


def save_state(path, model: Model, state: State, *, step: int, frame: int, run: dict | None = None) -> pathlib.Path:
    """Write ``state`` (and ``model``'s material parameters) to ``path`` atomically.

    The file appears complete or not at all: it is written beside ``path`` and renamed
    over it, so an interrupted save leaves the previous checkpoint intact.
    """
    path = pathlib.Path(path)
    if path.suffix != ".npz":
        raise ValueError(f"checkpoint path = {str(path)!r} is not allowed: must end in .npz")
    meta = {
        "format": FORMAT,
        "step": int(step),
        "frame": int(frame),
        "particle_count": model.particle_count,
        "dtype": model.scalar.__name__,
        "bodies": [b.name for b in model.bodies],
        "run": run or {},
        "time": float(getattr(state, "time", 0.0)),
    }
    arrays = {name: getattr(state, name).numpy() for name in State.STATE_FIELDS}
    arrays.update({f"material_{name}": getattr(model, name).numpy() for name in Model.MATERIAL_FIELDS})
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent or ".")
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def read_checkpoint(path) -> tuple[dict, dict[str, np.ndarray]]:
    """The metadata and arrays of a checkpoint file; ``ValueError`` if it is not one."""
    path = pathlib.Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
        meta = json.loads(arrays.pop("meta").tobytes().decode())
    except FileNotFoundError:
        raise ValueError(f"checkpoint = {str(path)!r} is not allowed: no such file") from None
    except (OSError, KeyError, ValueError, zipfile.BadZipFile, json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"checkpoint = {str(path)!r} is not allowed: not a readable warp_esph checkpoint ({type(e).__name__})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ValueError(f"checkpoint = {str(path)!r} is not allowed: unknown format {meta.get('format') if isinstance(meta, dict) else None!r}")
    missing = [n for n in State.STATE_FIELDS if n not in arrays and n not in State.OPTIONAL_FIELDS]
    if missing:
        raise ValueError(f"checkpoint = {str(path)!r} is not allowed: it lacks {', '.join(missing)}")
    return meta, arrays


def load_state(path, model: Model) -> tuple[State, dict]:
    """A new ``State`` of ``model`` from a checkpoint, and the checkpoint's metadata.

    The model's material parameters are set to the checkpoint's. The checkpoint must
    come from the same scene: same particle count, bodies and precision.
    """
    meta, arrays = read_checkpoint(path)
    where = f"checkpoint = {str(path)!r} is not allowed"
    if meta["particle_count"] != model.particle_count or meta["bodies"] != [b.name for b in model.bodies]:
        raise ValueError(
            f"{where}: it holds {meta['particle_count']} particles in bodies {meta['bodies']}, "
            f"the model {model.particle_count} in {[b.name for b in model.bodies]}"
        )
    if meta["dtype"] != model.scalar.__name__:
        raise ValueError(f"{where}: it is {meta['dtype']}, the model {model.scalar.__name__}")
    state = model.state()
    for name in State.STATE_FIELDS:
        if name in arrays:
            getattr(state, name).assign(arrays[name])
    state.time = float(meta.get("time", 0.0))
    for name in Model.MATERIAL_FIELDS:
        key = f"material_{name}"
        if key in arrays:
            getattr(model, name).assign(arrays[key])
    return state, meta
