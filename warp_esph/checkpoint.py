"""Checkpoints: the full simulation state in one ``.npz`` file, written atomically.

A checkpoint holds every array a step reads (``State.STATE_FIELDS``: ``x, v, F, alpha`` and
the rest-configuration model's ``F_p``, the round-off ``x_lo``, ``F_lo`` of ``x`` and ``F``,
and the floor images' own ``F_image`` and ``alpha_image``; an older checkpoint without them
loads them as ``I`` and 0, ``F_image`` as ``F``, ``alpha_image`` as ``alpha``),
the simulated time, the current values of
the per-material parameters (they may have been fitted or edited since the scene was
built), the step and frame counters, the tools' work on the bodies since the run's start
(``State.tool_work``, where ``simulate`` counted it: a resumed run's blow-up bounds add it),
a free-form ``run`` record (the CLI stores the
scene, scale, time step, output and solver options there) and the settings of the solver
that ran (``solver_settings``: the one ``save_state`` is given, else the one whose step wrote
the state, while it exists). The step depends on nothing else, so
on the CPU a run resumed from a checkpoint with the same solver settings reproduces the
uninterrupted run bit for bit.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import os
import pathlib
import zipfile
import zlib

import numpy as np

from . import checks
from .model import Model, State, flowed_by_hardening

FORMAT = "warp_esph.checkpoint/1"


#: The fingerprint's version a checkpoint records (``fingerprint_version``): 2 covers the
#: moving tools, pinned sets and ghost floors; a checkpoint without it (written before) is
#: compared with the fingerprint of version 1, which left them out. 3 records the static
#: colliders as the model's precision holds them, built or moved (``Model.static_colliders(held=True)``):
#: a float32 plane built at -1/3 and one moved there in place record alike; a scene whose every
#: collider value the precision holds as given (every float64 one) has the fingerprint of 2, and a
#: checkpoint of version 2 is compared with the fingerprint of 2, so none written before is refused.
#: 4 records what 3 does (every scene's fingerprint is 3's): it marks a file written since the
#: Tresca ground's hold reads each particle's hardened yield stress, which one of 3 or before
#: does not say (``older_hold``).
FINGERPRINT_VERSION = 4
#: The first fingerprint version written by the Tresca ground's hold as it is now: it reads
#: ``yield_stress + hardening * alpha`` at the step's start (2026-12-07, the package's version
#: unchanged), where before it read ``yield_stress`` as given.
HARDENED_HOLD = 4
#: What a file's ``fingerprint_version`` may be (``read_fingerprint_version``), as a refusal says it.
FINGERPRINT_VERSIONS = f"an integer from 1 to {FINGERPRINT_VERSION}, the versions this warp_esph reads"


def read_fingerprint_version(value) -> int | None:
    """The fingerprint version ``value`` a checkpoint or sweep table records, as the int every
    comparison reads, or None where it is none of ``FINGERPRINT_VERSIONS`` (the caller refuses
    it, naming the field). JSON and a hand edit may write 3.0 for 3: both are version 3, read
    one way by every check (3.0 passed the range check, then ``older_hold`` read it as no
    version and resumed a file it refuses); a bool, a string, 3.5, 0 or a version newer than
    this build's is none."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 1 <= value <= FINGERPRINT_VERSION:
        return None
    return int(value) if value == int(value) else None


def older_hold(version, shear_cap: float, hardening, alpha=None) -> str | None:
    """Why a checkpoint or sweep table of fingerprint ``version`` (an int, as
    ``read_fingerprint_version`` reads the file's) does not continue in a scene
    of Tresca ground ``shear_cap`` (0: none) whose materials (a sweep's samples too) have the
    ``hardening`` values, or None where it does. Written before ``HARDENED_HOLD``, a flowed
    particle's hold read the given yield stress: resumed, the run would be one hold's up to
    the file and the other's after it, which no run straight through is. The two holds are
    the same where there is no Tresca ground or every hardening is 0 (bit for bit,
    docs/physics.md, "The Tresca ground (built)"), and up to a checkpoint whose ``alpha`` (its
    hardening variables; None: a sweep's rows, finished runs) shows no particle flowed yet:
    ``alpha`` only grows, so every step before it read ``yield_stress + hardening * 0``. Every
    such file resumes as before."""
    h = np.asarray(hardening, dtype=np.float64).ravel()
    if (version >= HARDENED_HOLD or not shear_cap > 0.0 or not np.any(h != 0.0)
            or (alpha is not None and not flowed_by_hardening(alpha))):
        return None
    return (f"it was written with fingerprint version {version}, before the Tresca ground's hold read the hardened "
            f"yield stress (yield_stress + hardening * alpha, since version {HARDENED_HOLD}), and this scene has a "
            f"Tresca ground (shear_cap = {shear_cap:g}) under a hardening of {h[h != 0.0][0]:g} Pa, so resumed it "
            "would mix the two holds")


def model_fingerprint(model: Model, version: int = FINGERPRINT_VERSION, rest_positions=None,
                      fit_weight: str | None = None) -> str:
    """A hash of everything a step depends on that a checkpoint does not carry: the initial
    particles, bodies, lattice, colliders, force fields, gravity, each material's kind and
    density (the fitted parameters ``Model.MATERIAL_FIELDS`` are in the checkpoint itself),
    the ghost floors and the moving tools and pinned sets (shape, motion, friction, particles).

    A checkpoint resumed into a model with another fingerprint would continue a different
    scene from this one's state, so ``load_state`` refuses it. ``rest_positions``: hashed in
    place of ``model.particle_x0`` (a state's ``Model.scene_snapshot``, ``_check_state_model``);
    ``fit_weight``: hashed in place of ``model.fit_weight`` (``load_state`` names the weight a
    checkpoint was written with).
    """
    h = hashlib.sha256()
    x0 = model.particle_x0 if rest_positions is None else rest_positions
    for arr in (x0, model.particle_v0, model.particle_material_np, model.particle_body_np):
        a = np.ascontiguousarray(arr, dtype=np.float64 if arr.dtype.kind == "f" else np.int64)
        h.update(repr(a.shape).encode())
        h.update(a.tobytes())
    h.update(repr(scene_record(model, version, fit_weight)).encode())
    return h.hexdigest()[:32]


def scene_record(model: Model, version: int = FINGERPRINT_VERSION, fit_weight: str | None = None) -> dict:
    """What ``model_fingerprint`` hashes beside the particle arrays: the lattice, bodies,
    colliders, force fields, gravity, each material's kind and density, the ghost floors and
    the moving tools and pinned sets, as values whose ``repr`` is the same in every process
    (a sweep's identity hashes it too, ``sweep._model_digest``)."""
    record = {
        "spacing": model.spacing, "support_radius": model.support_radius, "max_neighbors": model.max_neighbors,
        "bodies_interact": model.bodies_interact, "gravity": model.gravity,
        "bodies": [(b.name, b.start, b.count, b.material, b.kind) for b in model.bodies],
        "materials": [(m.density, m.model, m.deformation, m.elastic_force, bool(m.clamp_pressure), m.pressure_force)
                      for m in model.materials],
        # As the kernels run them (their arrays): a ground moved in place is another scene.
        "colliders": [repr(c) for kind in model.static_colliders(held=version >= 3) for c in kind],
        "fields": [repr(f) for f in model.force_fields],
    }
    fit_weight = model.fit_weight if fit_weight is None else fit_weight
    if fit_weight != "poly6":  # poly6 was the only weight before the option: its checkpoints still match
        record["fit_weight"] = fit_weight
    if any(m.pair_repulsion for m in model.materials):  # likewise; not a fitted parameter, so not in the arrays
        record["pair_repulsion"] = [m.pair_repulsion for m in model.materials]
    # Likewise only where the model has them: ghost floors and the moving tools and pinned sets.
    ghosts = [(b.name, b.ghost_floor, b.ghost_plane, b.ghost_slip) for b in model.bodies if b.ghost_floor > 0]
    if version < 2:
        ghosts, tools = [], None
    else:
        tools = model.tools
    if ghosts:
        record["ghost_floors"] = ghosts
    if tools is not None:
        record["tools"] = [(c.name, c.kind, c.param, _motion_key(c.motion), c.friction, c.static_friction,
                            _array_key(c.mesh_points), _array_key(c.mesh_triangles)) for c in tools.colliders]
        record["pins"] = [(p.name, _array_key(p.indices), _motion_key(p.motion)) for p in tools.pins]
    return record


def _array_key(a) -> str | None:
    """A short stable hash of an array's shape and values (None stays None)."""
    if a is None:
        return None
    a = np.ascontiguousarray(a)
    return hashlib.sha256(repr((a.shape, a.dtype.str)).encode() + a.tobytes()).hexdigest()[:16]


def _motion_key(motion):
    """A tool's or pinned set's motion as the same text in every process: its values, or for
    a Python callable (``tools.Scripted``) its qualified name (its address changes per run)."""
    fn = getattr(motion, "fn", None)
    if fn is not None:
        return (type(motion).__name__, getattr(fn, "__module__", None), getattr(fn, "__qualname__", type(fn).__name__))
    return repr(motion)


def save_state(path, model: Model, state: State, *, step: int, frame: int, run: dict | None = None,
               solver=None) -> pathlib.Path:
    """Write ``state`` (and ``model``'s material parameters) to ``path`` (ending in ``.npz``,
    in any case: ``STATE.NPZ`` is written under that very name) atomically.

    The file appears complete or not at all: it is written beside ``path`` and renamed
    over it, so an interrupted save leaves the previous checkpoint intact. A state with a
    non-finite value is refused (``ValueError``): a checkpoint is for resuming. So is a state
    of another model (``model.state()`` and ``load_state`` make a model's states; one that
    ``Solver.step`` wrote or ``State.assign`` copied into stays the state of the model that
    made it), unless that model is of the same scene (the same ``model_fingerprint``, of the rest
    positions it had when it made the state).

    ``solver`` (a ``Solver`` of ``model``; optional) records the settings of the solver that
    ran (``solver_settings``: fit, hourglass, contact ramp, guards, the yield test's pressure,
    fused kernels, whether the rest-configuration model runs from ``state``: not where its
    body flowed), which
    ``load_state(..., solver=)`` compares with the solver that resumes. Without it, those of
    the solver of ``model`` whose step wrote ``state``, or whose ``simulate`` run it starts (a
    callback's checkpoint of the start frame), are recorded (``State.written_by``) while that
    solver exists (a hourglass strength set by hand, ``Solver.hourglass``, as it runs); a
    state no step of it wrote (a new or loaded one) records none.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"path = {checks.shown_path(path)} is not allowed: must be a file path ending in .npz")
    path = pathlib.Path(path)
    # Any case, as every other reader of .npz here takes it (fit targets, masks): 'STATE.NPZ'
    # was refused. The file is written through a handle, so numpy appends no second '.npz'
    # (np.savez('STATE.NPZ') would write 'STATE.NPZ.npz').
    if path.suffix.lower() != ".npz":
        raise ValueError(f"path = {checks.shown_path(path)} is not allowed: must end in .npz (any case)")
    if not isinstance(model, Model):
        raise ValueError(f"model = {checks.shorten(model)!r} is not allowed: must be a warp_esph Model")
    # What load_state asks of them, asked here: it refused the files this wrote with a step of
    # -1 or 1.7 (stored as 1), a run record that is no table, or parameters no material takes.
    for name, value in (("step", step), ("frame", frame)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < -1 or (name == "frame" and value < 0):
            raise ValueError(f"{name} = {checks.shorten(value)!r} is not allowed: must be an integer >= {0 if name == 'frame' else -1}"
                             + (" (-1: not a function of the frame)" if name == "step" else ""))
    if run is not None and not isinstance(run, dict):
        raise ValueError(f"run = {checks.shorten(run)!r} is not allowed: must be a dict (the run record) or None")
    if run is not None:
        try:
            json.dumps(run)
        except (TypeError, ValueError) as e:
            # It is stored as JSON: a value JSON cannot hold was a TypeError out of json.
            raise ValueError(f"run is not allowed: it must hold JSON values (numbers, text, lists, dicts): {e}") from None
    _check_solver(model, solver)
    if solver is None and getattr(state, "written_by", None) is not None:
        # Without solver= no settings were recorded, and a resume with another hourglass
        # strength (or fit, guard, kernel) ran another run without a word: those of the solver
        # whose step wrote the state, while it exists (one of another model: none).
        writer = state.written_by()
        solver = writer if writer is not None and writer.model is model else None
    checks.output_place("path", path)
    if isinstance(state, State) and getattr(state, "_model", None) is not None:
        # First: its refusal says what a checkpoint of another scene's state would do.
        _check_state_model(model, state)
    checks.same_state(model, "state", state)
    time_ = state.time
    if isinstance(time_, bool) or not isinstance(time_, (int, float, np.integer, np.floating)) \
            or not (math.isfinite(float(time_)) and float(time_) >= 0.0):
        # load_state refuses it: the file would hold a run that cannot resume
        raise ValueError(f"state.time = {checks.shorten(time_)!r} is not allowed: must be a finite number >= 0")
    model._check_parameter_values(model._read_parameters())
    arrays = {name: getattr(state, name).numpy() for name in State.STATE_FIELDS}
    for name, a in arrays.items():
        if not np.isfinite(a).all():
            raise ValueError(f"state is not allowed: its {name} has non-finite values; a checkpoint must resume a sound run")
    _renormalised_roundoff(arrays, model)
    rows = dict(zip(Model.MATERIAL_FIELDS, model._read_parameters()))
    _check_state_values("state is not allowed", arrays, model,
                        _takes_inverted_fits(model, state.rest_model, rows["yield_stress"], rows["flow_rate"]))
    meta = {
        "format": FORMAT,
        "step": int(step),
        "frame": int(frame),
        "particle_count": model.particle_count,
        "dtype": model.scalar.__name__,
        "bodies": [b.name for b in model.bodies],
        "run": run or {},
        "time": float(getattr(state, "time", 0.0)),
        # Whether the step that wrote it ran the rest model: a resumed run hands F over as the
        # uninterrupted one would (State.rest_model).
        "rest_model": getattr(state, "rest_model", None),
        "fingerprint": model_fingerprint(model),
        "fingerprint_version": FINGERPRINT_VERSION,
    }
    work = getattr(state, "tool_work", None)
    if work is not None:
        # What a resumed run's blow-up bounds need of the run before it (State.tool_work):
        # without it they fell back on the height the tools can have given.
        if isinstance(work, bool) or not isinstance(work, (int, float, np.integer, np.floating)) \
                or not math.isfinite(float(work)):
            raise ValueError(f"state.tool_work = {checks.shorten(work)!r} is not allowed: must be a finite number of "
                             "joules (the tools' work since the run's start) or None (not known)")
        meta["tool_work"] = float(work)
    if solver is not None:
        # What it runs from this state (a body that flowed keeps the incremental composition),
        # as a resume reads it: State.flowed is not saved, load_state reads it from the
        # hardening the file holds, so the state is asked so here too.
        resumed = copy.copy(state)
        resumed.flowed = flowed_by_hardening(arrays["alpha"])
        meta["solver"] = solver_settings(solver, resumed)
    arrays.update({name: getattr(state, name).numpy() for name in State.STEP_REPORTS if hasattr(state, name)})
    arrays.update({f"material_{name}": getattr(model, name).numpy() for name in Model.MATERIAL_FIELDS})
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    # The working file is made inside replaced_atomically's guard: made by mkstemp before the
    # guard began, an interrupt between the two left it beside the checkpoint. (mkstemp also
    # made it private, 0600, whatever the umask; open() gives the umask's permissions, as the
    # USD file and force log beside it have.)
    with checks.replaced_atomically(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)
        f.flush()
        os.fsync(f.fileno())
    return path


def solver_settings(solver, state: State | None = None) -> dict:
    """What of ``solver`` a step depends on beyond the model's scene and the state, as the
    step runs it at the model's current material values: the fit and hourglass strength
    (``Model.solver_choice``: ``"auto"`` resolved, so ``fit="linear"`` where ``"auto"`` runs
    the linear fit is the same run; a strength set by hand, ``Solver.hourglass``, as it runs),
    the model's contact ramp, the neighbourhood guards,
    whether the yield test reads the SPH pressure (``Solver.yield_with_pressure``), whether the
    fused kernels run (the same equations, another round-off; the curvature-corrected fit,
    comparison models, ghost floors and ``yield_with_pressure`` never take them) and whether a step
    from ``state`` runs the rest-configuration model (``Solver.runs_rest``; None: a new
    state): False from a state an incremental step wrote whose body flowed, where the
    incremental composition runs whatever the parameters allow. Not the neighbour skin: it
    changes the cost only, bit for bit (``Solver``)."""
    m = solver.model
    fit = m.solver_choice(*solver._asked)[0]
    # The strength the step runs: one set by hand (Solver.hourglass) is not the requested one,
    # which a fresh solver without the control matched.
    c = solver.next_hourglass()
    pressure_yield = bool(solver.yield_with_pressure)
    fused = (solver.fused and not solver._cmp and fit != "curvature_corrected" and solver.ghost_search is None
             and not pressure_yield)
    # The yield test before the kernel path: it is what a solver without it differs in first.
    return {"fit": fit, "hourglass": float(c), "contact_ramp": float(m.contact_ramp),
            "min_neighbors": int(solver.min_neighbors), "max_condition": float(solver.max_condition),
            "yield_with_pressure": pressure_yield, "fused": bool(fused),
            "rest_model": bool(solver.runs_rest(state))}


def _check_solver(model: Model, solver) -> None:
    from .sim.solver import Solver  # noqa: PLC0415 (the kernels load on demand)

    if solver is not None and (not isinstance(solver, Solver) or solver.model is not model):
        raise ValueError(f"solver = {checks.shorten(solver)!r} is not allowed: it must be None or a warp_esph.Solver "
                         "built for this model")


def _check_state_model(model: Model, state: State) -> None:
    """``state`` is a state of ``model``, or of a model of the same scene (the same
    fingerprint: ``finalize`` run twice): the checkpoint is filed under ``model``'s
    fingerprint, and a state of another scene of as many particles would resume there.

    The owner's fingerprint hashes the rest positions it had when it made ``state`` (its
    ``_made_of``, as ``checks.same_state`` judges them): one edited since
    (``calibrate.jitter_model``) no longer describes the state, and ``model``, holding those
    positions, does. Its materials, colliders, tools and bodies' records are hashed as they are
    now (``same_state``, run next, compares the bodies with the snapshot's)."""
    owner = getattr(state, "_model", None)
    if owner is model:
        return
    made_of = getattr(state, "_made_of", None)
    theirs = (model_fingerprint(owner, rest_positions=None if made_of is None else made_of[1])
              if isinstance(owner, Model) else None)
    if theirs != model_fingerprint(model):
        raise ValueError(f"state is not allowed: it was made by another model, {owner!r}, of another scene (its "
                         f"fingerprint {theirs!r} is not this model's {model_fingerprint(model)!r}); a checkpoint of it "
                         "would resume that scene's state in this one: save a state made by this model (model.state(), "
                         "load_state(path, model))")


def _not_a_checkpoint(path, exc: BaseException) -> str:
    """Why the file ``path``, whose reading raised ``exc``, is no checkpoint, in words: the
    name of the class raised was all a refusal said ('(ValueError)' of a USD file given to
    ``--resume``)."""
    special = checks.special_file(path)
    if special is not None:
        # Not opened again: a named pipe's second open waits for a writer that has gone, and
        # the refusal hung. numpy reads a .npz by seeking, which a pipe or a device cannot.
        return f"it is {special}, not a file: a checkpoint is read from its .npz file"
    try:
        with open(path, "rb") as fh:
            head = fh.read(8)
    except OSError:
        head = b"PK"  # read once already: said as a damaged archive
    if not head:
        return "it is empty"
    if head.startswith((b"PXR-USDC", b"#usda")):
        return "it is a USD file, a run's frames; a checkpoint is the .npz that save_state and run --checkpoint-every write"
    if not head.startswith(b"PK"):  # np.load read it as pickled data, which it refuses
        return "it is not a .npz archive, which a checkpoint is"
    if isinstance(exc, KeyError):
        return "it holds no checkpoint record, 'meta': a .npz written by something else?"
    if isinstance(exc, (json.JSONDecodeError, UnicodeDecodeError)):
        return "its checkpoint record, 'meta', is damaged"
    return "its .npz archive is damaged or cut short"


def read_checkpoint(path, what: str = "path") -> tuple[dict, dict[str, np.ndarray]]:
    """The metadata and arrays of a checkpoint file; ``ValueError`` if it is not one, naming the
    file as ``what``: the caller's own name for it, this parameter or the CLI's ``--resume``
    ('checkpoint' named neither)."""
    if not isinstance(path, (str, os.PathLike)):  # None, 123: a TypeError from pathlib
        raise ValueError(f"{what} = {checks.shown_path(path)} is not allowed: must be a path")
    if not os.fspath(path) or "\0" in os.fspath(path):
        # pathlib reads '' (an unset shell variable) as '.': "--resume = '.' ... (Is a directory)".
        raise ValueError(f"{what} = {checks.shown_path(path)} is not allowed: must be a path (not empty, no NUL character)")
    path = pathlib.Path(path)
    single = None
    try:
        # Our own handle: np.load leaves its file open when the zip is damaged.
        with open(path, "rb") as fh:
            loaded = np.load(fh, allow_pickle=False)
            if isinstance(loaded, np.ndarray):
                # A .npy, which np.load reads as one array: a TypeError traceback at 'with' before.
                single = loaded.shape
            else:
                with loaded as data:
                    arrays = {k: data[k] for k in data.files}
        if single is None:
            meta = json.loads(arrays.pop("meta").tobytes().decode())
    except FileNotFoundError:
        raise ValueError(f"{what} = {checks.shown_path(path)} is not allowed: no such file") from None
    except OSError as e:
        if e.errno is None:  # raised by a reader of the bytes, not by the system: a damaged file
            raise ValueError(f"{what} = {checks.shown_path(path)} is not allowed: not a readable warp_esph checkpoint "
                             f"({_not_a_checkpoint(path, e)})") from None
        # The system's reason: 'not a readable warp_esph checkpoint (IsADirectoryError)' or
        # '(OSError)', for a folder or a name too long, named no cause or the wrong one.
        raise ValueError(f"{what} = {checks.shown_path(path)} is not allowed: it cannot be read ({e.strerror or e})") from None
    # zipfile also raises RuntimeError (a damaged 'encrypted' flag) and NotImplementedError
    # (a damaged compression method): in this block, only reading the file can raise them.
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile, zlib.error, json.JSONDecodeError, UnicodeDecodeError,
            RuntimeError, NotImplementedError) as e:
        raise ValueError(f"{what} = {checks.shown_path(path)} is not allowed: not a readable warp_esph checkpoint "
                         f"({_not_a_checkpoint(path, e)})") from None
    if single is not None:
        raise ValueError(f"{what} = {checks.shown_path(path)} is not allowed: it holds one numpy array of shape {single} (a .npy), not a "
                         "warp_esph checkpoint (the .npz save_state writes)")
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ValueError(f"{what} = {checks.shown_path(path)} is not allowed: unknown format {meta.get('format') if isinstance(meta, dict) else None!r}")
    missing = [n for n in State.STATE_FIELDS if n not in arrays and n not in State.OPTIONAL_FIELDS]
    # Every checkpoint of this format holds every material array (MATERIAL_FIELDS has not
    # changed since the first): without one, the model's value resumed without a word.
    missing += [f"material_{n}" for n in Model.MATERIAL_FIELDS if f"material_{n}" not in arrays]
    if missing:
        raise ValueError(f"{what} = {str(path)!r} is not allowed: it lacks {', '.join(missing)}")
    return meta, arrays


def load_state(path, model: Model, solver=None, what: str = "path") -> tuple[State, dict]:
    """A new ``State`` of ``model`` from a checkpoint, and the checkpoint's metadata.

    The model's material parameters are set to the checkpoint's. The checkpoint must
    come from the same scene: same particle count, bodies and precision. It must hold
    every material array, and values a step leaves (else ``ValueError``, naming the array
    and the first bad particle): finite; ``F``, ``F_p``, ``F_image`` of positive
    determinant (but an ``F`` that is a rest fit taken inverted: of a state the rest model
    wrote, or of a ``"rest"`` material that cannot flow, ``_takes_inverted_fits``); ``alpha``, ``alpha_image`` >= 0; the round-off ``x_lo``, ``F_lo`` at most
    the precision's epsilon times the particle's largest ``|x|``, ``|F|`` entry (a step leaves
    at most half that). ``save_state`` refuses a state that breaks the others, and files a
    state's round-off split again where it exceeds that bound (a state moved by hand).

    ``solver`` (a ``Solver`` of ``model``; optional): the solver that will continue the run.
    Where the checkpoint records the settings of the solver that ran (``save_state(...,
    solver=)``, or without it the solver whose step wrote the state), a setting that differs
    is refused (``ValueError`` naming it and both values): the continuation would not be the
    run it continues. A checkpoint that records none (a state no step wrote, saved without
    ``solver=``; a file written before) is not compared. ``what``: how a refusal names the
    file (``path``, or the CLI's ``--resume``).
    """
    if not isinstance(model, Model):
        raise ValueError(f"model = {checks.shorten(model)!r} is not allowed: must be the warp_esph.Model the checkpoint "
                         "resumes")
    _check_solver(model, solver)
    meta, arrays = read_checkpoint(path, what)
    where = f"{what} = {checks.shown_path(path)} is not allowed"
    _check_meta(where, meta)
    if meta["particle_count"] != model.particle_count or meta["bodies"] != [b.name for b in model.bodies]:
        raise ValueError(
            f"{where}: it holds {meta['particle_count']} particles in bodies {meta['bodies']}, "
            f"the model {model.particle_count} in {[b.name for b in model.bodies]}"
        )
    if meta["dtype"] != model.scalar.__name__:
        # Refused, not converted: a float32 state taken up to float64 continues neither the float32
        # run (another round-off from the first step on) nor a float64 one (digits it never had).
        raise ValueError(f"{where}: it is {meta['dtype']}, the model {model.scalar.__name__}; a checkpoint resumes in the "
                         f"precision it was written in: finalize the model with dtype=wp.{meta['dtype']}")
    version = read_fingerprint_version(meta.get("fingerprint_version", 1))  # an int: _check_meta refused the rest
    if "fingerprint" in meta and meta["fingerprint"] != model_fingerprint(model, version):
        from .sim.smoothing import FIT_WEIGHTS  # noqa: PLC0415

        # Since the biweight became the default (2026-12-06) a script that built its model
        # without naming a weight meets its older poly6 checkpoints here: say the weight, not
        # "was the scene edited?".
        weight = next((w for w in FIT_WEIGHTS if w != model.fit_weight
                       and meta["fingerprint"] == model_fingerprint(model, version, fit_weight=w)), None)
        if weight is not None:
            raise ValueError(f"{where}: it was written by a model of the {weight} fit weight, this model's is "
                             f"{model.fit_weight} (the default is the biweight since 2026-12-06, poly6 before): build the model "
                             f"with SceneBuilder(fit_weight={weight!r}) (a scene file's [solver] fit_weight) to resume "
                             f"it")
        raise ValueError(
            f"{where}: it was written for another scene (its fingerprint {meta['fingerprint']!r} is not this model's "
            f"{model_fingerprint(model, version)!r}: particles, bodies, colliders, tools, pins, fields or materials differ; "
            "was the scene edited?)"
        )
    n, np_dtype = model.particle_count, model.types.np_dtype
    shapes = {"x": (n, 3), "v": (n, 3), "F": (n, 3, 3), "alpha": (n,), "F_p": (n, 3, 3), "x_lo": (n, 3),
              "F_lo": (n, 3, 3), "F_image": (n, 3, 3), "alpha_image": (n,)}
    shapes.update({f"material_{name}": (len(model.materials),) for name in Model.MATERIAL_FIELDS})
    for key, shape in shapes.items():
        if key not in arrays:
            continue
        a = arrays[key]
        if a.shape != shape or a.dtype != np_dtype:
            raise ValueError(f"{where}: its {key} is {a.dtype} {a.shape}, the model needs {np.dtype(np_dtype)} {shape}")
        # A yield stress may be +inf (a purely elastic material); nothing else may be.
        ok = np.isfinite(a) | (np.isposinf(a) if key == "material_yield_stress" else False)
        if not ok.all():
            bad = int(np.argmax(~ok.reshape(a.shape[0], -1).all(axis=1)))
            raise ValueError(f"{where}: its {key} has non-finite values (first at index {bad})")
    # Finite is not enough: a negative shear modulus or viscosity diverged, a negative flow
    # rate or a zero modulus ran on and exited 0. Each material's values pass Material's own
    # checks, and the state's values are a step's (_check_state_values).
    for k, m in enumerate(model.materials):
        values = {name: float(arrays[f"material_{name}"][k]) for name in Model.MATERIAL_FIELDS}
        try:
            m.replace(**values)
        except ValueError as e:
            raise ValueError(f"{where}: its material {k}: {e}") from None
    # At the checkpoint's hardening, which the run it continues had (the model's is set to it).
    why = older_hold(version, model.shear_cap, arrays["material_hardening"], arrays["alpha"])
    if why is not None:
        raise ValueError(f"{where}: {why}; run it again from the start")
    _check_state_values(where, arrays, model,
                        _takes_inverted_fits(model, meta.get("rest_model"), arrays["material_yield_stress"],
                                             arrays["material_flow_rate"]))
    # The file's state replaces the model's start (x and v are in every file): a NaN left in
    # particle_v0, which no run from this state reads, refused the load by name.
    state = model._scratch_state(model.requires_grad)
    for name in State.STATE_FIELDS:
        if name in arrays:
            getattr(state, name).assign(arrays[name])
    if "F_image" not in arrays:
        # Written before the images had an F of their own: theirs was their particle's.
        state.F_image.assign(arrays["F"])
    if "alpha_image" not in arrays:
        # Written before the images had a hardening of their own: they flowed with their particle's.
        state.alpha_image.assign(arrays["alpha"])
    for name in State.STEP_REPORTS:  # written since they were carried; zero before (as a fresh state's)
        a = getattr(state, name, None)
        if name in arrays and a is not None:
            b = arrays[name]
            if b.shape != (a.shape[0], 3) or b.dtype != np_dtype or not np.isfinite(b).all():
                raise ValueError(f"{where}: its {name} is {b.dtype} {b.shape}, the model needs {np.dtype(np_dtype)} "
                                 f"{(a.shape[0], 3)} finite values")
            a.assign(b)
    state.time = float(meta.get("time", 0.0))
    # Written before it was kept (or by a run that did not count it): None, and a resumed run's
    # bounds read the height the tools can have given in its place (docs/errors.md).
    state.tool_work = meta.get("tool_work")
    if "rest_model" in meta:
        state.rest_model = meta["rest_model"] if meta["rest_model"] in (True, False) else None
    else:
        # Written before fit="auto" ran the rest model: every step then ran the incremental
        # composition, so a rest step hands its F over (a flag of None skipped that, and the
        # resumed body sprang to the rest fit of its positions); a state no step wrote is new.
        state.rest_model = False if meta.get("step", 0) else None
    # Whether the body has flowed (State.flowed), from the hardening the file holds: a resumed
    # flowed body is not handed over to the rest model, as the uninterrupted run's was not.
    state.flowed = flowed_by_hardening(arrays["alpha"])
    before = {name: getattr(model, name).numpy().copy() for name in Model.MATERIAL_FIELDS}
    for name in Model.MATERIAL_FIELDS:
        getattr(model, name).assign(arrays[f"material_{name}"])
    if solver is not None and "solver" in meta:
        # Compared at the checkpoint's material values, which decide what "auto" runs.
        # From this state, as at the save: a flowed body's run said rest_model = True, and a
        # solver of its fit and control, which runs the same steps bit for bit, was refused.
        ours = solver_settings(solver, state)
        for key, value in meta["solver"].items():
            if key in ours and value != ours[key]:
                for name, a in before.items():  # a refused resume leaves the model as it was
                    getattr(model, name).assign(a)
                raise ValueError(f"{where} with this solver: the run it continues had {key} = {value!r}, this solver "
                                 f"{key} = {ours[key]!r}; make the Solver (and set the model) as that run's")
    return state, meta


def _takes_inverted_fits(model: Model, rest_model, yield_stress: np.ndarray, flow_rate: np.ndarray) -> np.ndarray:
    """Per particle, whether a step may have left its ``F`` inverted: a rest fit taken inverted
    where the material cannot flow on the variational force (``comparison.continues_inverted``),
    by the rest model (``rest_model`` True: the step that wrote the state ran it,
    ``State.rest_model``; it runs only where no material could flow then, so whatever the
    parameters are now: a step that lets one flow hands such an ``F`` back, ``Solver``) or by a
    ``"rest"`` material (``yield_stress`` inf or ``flow_rate`` <= 0)."""
    cannot_flow = np.isinf(np.asarray(yield_stress)) | (np.asarray(flow_rate) <= 0.0)
    takes = np.array([m.elastic_force == "variational" and (rest_model is True or (m.deformation == "rest" and c))
                      for m, c in zip(model.materials, cannot_flow)], dtype=bool)
    return takes[model.particle_material_np]


def _check_state_values(where: str, arrays: dict[str, np.ndarray], model: Model,
                        inverted_ok: np.ndarray | None = None) -> None:
    """The state arrays in ``arrays`` (finite, of the model's shapes) hold values a step
    leaves: a hand-edited or foreign file resumed them without a word. ``F``, ``F_p`` and
    ``F_image`` are deformations (determinant > 0), but ``F`` where ``inverted_ok`` (a rest
    fit taken inverted, ``_takes_inverted_fits``); the hardening ``alpha``, ``alpha_image``
    is an accumulated plastic strain (>= 0); the round-off ``x_lo``, ``F_lo`` of ``x``, ``F``
    (``sim/roundoff.py``) is within the last place of the particle's largest entry. Arrays an
    older checkpoint lacks are skipped."""
    for name in ("F", "F_p", "F_image"):
        if name in arrays:
            det = np.linalg.det(arrays[name].astype(np.float64))
            refused = ~(det > 0.0)
            if name == "F" and inverted_ok is not None:
                refused &= ~inverted_ok
            if refused.any():
                bad = int(np.argmax(refused))
                raise ValueError(f"{where}: its {name} at particle {bad} has determinant {det[bad]:.3g}: not a deformation "
                                 "(must be > 0)")
    for name in ("alpha", "alpha_image"):
        if name in arrays:
            a = arrays[name]
            if not (a >= 0.0).all():
                bad = int(np.argmax(~(a >= 0.0)))
                raise ValueError(f"{where}: its {name} at particle {bad} is {float(a[bad]):.3g}: an accumulated plastic "
                                 "strain, it must be >= 0")
    # A step's compensated sum leaves |lo| <= half a unit in the last place of its entry
    # (Knuth's TwoSum, measured so in both precisions), so at most a unit in the last place of
    # the particle's largest entry: twice the margin there, more on its smaller entries.
    for name, of in (("x_lo", "x"), ("F_lo", "F")):
        if name not in arrays:
            continue
        size, bound = _roundoff_and_bound(arrays[name], arrays[of], model)
        if not (size <= bound).all():
            bad = int(np.argmax(~(size <= bound)))
            lo = arrays[name].reshape(len(size), -1)
            value = float(lo[bad, int(np.argmax(np.abs(lo[bad])))])
            raise ValueError(f"{where}: its {name} at particle {bad} holds {value:.3g}: the round-off carried beside {of} "
                             f"must be at most {bound[bad]:.3g} there ({model.scalar.__name__}'s epsilon times the "
                             f"size of the particle's largest {of} entry); set it to 0 where {of} is set by hand")


def _roundoff_and_bound(lo: np.ndarray, of: np.ndarray, model: Model) -> tuple[np.ndarray, np.ndarray]:
    """Per particle: the largest round-off entry ``|lo|`` and its bound, the precision's
    epsilon times the particle's largest ``|of|`` entry (plus the smallest normal number)."""
    info, n = np.finfo(model.types.np_dtype), lo.shape[0]
    size = np.abs(lo.astype(np.float64).reshape(n, -1)).max(axis=1, initial=0.0)
    bound = float(info.eps) * np.abs(of.astype(np.float64).reshape(n, -1)).max(axis=1, initial=0.0) + float(info.tiny)
    return size, bound


def _renormalised_roundoff(arrays: dict[str, np.ndarray], model: Model) -> None:
    """Where a state's round-off exceeds its bound, ``x + x_lo`` (``F + F_lo``) is split again
    into a value and its round-off (``roundoff.compensated_sum``, exactly: the sum the step
    reads is kept). A state whose ``x`` was set by hand keeps the old round-off (``State``'s
    note), up to half a unit in the last place of the old value: a body moved nearer the
    origin holds more than its new values' last place, which ``load_state`` refuses in a file.
    A state a step left is written as it is, bit for bit."""
    for name, of in (("x_lo", "x"), ("F_lo", "F")):
        size, bound = _roundoff_and_bound(arrays[name], arrays[of], model)
        over = ~(size <= bound)
        if over.any():
            a, b = arrays[of][over], arrays[name][over]
            s = a + b
            bb = s - a
            hi, lo = arrays[of].copy(), arrays[name].copy()
            hi[over], lo[over] = s, (a - (s - bb)) + (b - bb)
            arrays[of], arrays[name] = hi, lo


def _check_meta(where: str, meta: dict) -> None:
    """The metadata's fields have the types ``save_state`` writes (a hand-edited or foreign
    file must not end in a ``TypeError`` later)."""
    def is_int(v, lowest=0):
        return isinstance(v, int) and not isinstance(v, bool) and v >= lowest

    wrong = []
    # step -1: a run with the adaptive step, whose step count is no function of the frame.
    for key, lowest in (("step", -1), ("frame", 0), ("particle_count", 0)):
        if not is_int(meta.get(key), lowest):
            wrong.append(f"{key} = {meta.get(key)!r} (must be an integer >= {lowest})")
    if meta.get("dtype") not in ("float32", "float64"):  # a refusal of the other one names it as the dtype to resume in
        wrong.append(f"dtype = {meta.get('dtype')!r} (must be 'float32' or 'float64')")
    bodies = meta.get("bodies")
    if not isinstance(bodies, list) or not all(isinstance(b, str) for b in bodies):
        wrong.append(f"bodies = {bodies!r} (must be a list of names)")
    if not isinstance(meta.get("run", {}), dict):
        wrong.append(f"run = {meta.get('run')!r} (must be a table)")
    t = meta.get("time", 0.0)
    if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t) or t < 0:
        wrong.append(f"time = {t!r} (must be a finite number >= 0)")
    w = meta.get("tool_work")
    if w is not None and (isinstance(w, bool) or not isinstance(w, (int, float)) or not math.isfinite(w)):
        wrong.append(f"tool_work = {w!r} (must be a finite number of joules)")
    if "fingerprint" in meta and not isinstance(meta["fingerprint"], str):
        wrong.append(f"fingerprint = {meta['fingerprint']!r} (must be a string)")
    if not isinstance(meta.get("solver", {}), dict):
        wrong.append(f"solver = {meta.get('solver')!r} (must be a table)")
    version = meta.get("fingerprint_version", 1)
    if read_fingerprint_version(version) is None:
        wrong.append(f"fingerprint_version = {version!r} (must be {FINGERPRINT_VERSIONS})")
    if wrong:
        raise ValueError(f"{where}: its metadata has " + "; ".join(wrong))
