"""The ``warp-esph fit`` command's work: read the targets, build the model, fit, report, write.

``add_calibration_arguments(parser)`` declares the options beyond the basic ones
(optimizer, jitter, support radius, loss scale, checkpointing from memory, global stage,
diagnostics, output folder, USD-run and silhouette targets); ``run_fit(args)`` does the
fit from parsed arguments and writes into ``--output-dir``:

- ``fit.json``: fitted parameters, materials, termination, diagnostics, history;
- ``history.csv``: one row per evaluation (stage, loss, each parameter, seconds);
- ``loss.png``, ``params.png``: loss and parameters per evaluation (matplotlib, Agg);
- ``fitted.usdc``: the fitted run (when USD support is installed; not with ``--no-usd``).

It prints, before the fit, the rollout's memory and checkpointing; after the first
evaluation, the time per evaluation and the estimate for the whole fit; after it, whether
the fit converged, stalled or hit the iteration cap, and the diagnostics table.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import re
import sys

import numpy as np

from . import checks
from ._optimizers import OPTIMIZERS
from .material import UNITS

__all__ = ["add_calibration_arguments", "run_fit", "write_outputs", "jitter_model", "default_optimizer"]

#: Up to this many fitted values the default optimiser is L-BFGS, above it Adam.
LBFGS_MAX_VALUES = 4
#: The most frames ``--target-frames`` may name for one target (a range such as 0:10**12
#: would otherwise be listed in memory before anything else could refuse it).
MAX_TARGET_FRAMES = 10**6


def add_calibration_arguments(parser):
    """Declare the calibration options of ``warp-esph fit`` on ``parser``."""
    g = parser.add_argument_group("calibration")
    g.add_argument("--optimizer", choices=OPTIMIZERS,
                   help=f"lbfgs (default for <= {LBFGS_MAX_VALUES} fitted values), adam (default above; --clip is its "
                        "own) or gauss-newton (Levenberg-Marquardt from forward runs: least-squares targets, few values; "
                        "no --lr)")
    g.add_argument("--output-dir", metavar="DIR",
                   help="folder for fit.json, history.csv, loss.png, params.png, fitted.usdc (default: fit_<scene>/ here)")
    g.add_argument("--target-body", metavar="BODY",
                   help="USD-run targets: observe only this body's particles (default: every particle)")
    g.add_argument("--target-tool", metavar="TOOL",
                   help="reaction-force targets (the <output>_tools.csv of 'warp-esph run'): fit this tool's or static "
                        "collider's force curve (plane0: the ground; default: the only one in the file)")
    g.add_argument("--jitter", type=float, default=0.0, metavar="J",
                   help="jitter the lattice by J * spacing (normal) so no neighbour distance is tied at the support "
                        "radius (e.g. 0.001 with a support radius of 2 spacings; default 0: the scene as written, "
                        "as a previous run of it was)")
    g.add_argument("--seed", type=int, default=5, metavar="S", action=_Given,
                   help="random seed of the jitter and the global stage (default 5; only with --jitter, --samples or "
                        "--starts K > 1, which draw from it)")
    g.add_argument("--support-radius", type=float, metavar="K",
                   help="support radius in spacings (e.g. 2.5: no particle at thin features drops below the neighbour guard)")
    g.add_argument("--loss-scale", type=float, default=1.0, metavar="K",
                   help="multiply the loss by K (e.g. 1e6 to work in mm^2 with Adam); default 1")
    g.add_argument("--memory-limit", type=float, metavar="MB",
                   help="with --checkpoint-every auto: a full tape when it fits in MB, else checkpoint (default 1024; "
                        "not with --optimizer gauss-newton, which records no tape)")
    g.add_argument("--samples", type=int, default=0, metavar="N",
                   help="global first stage: N Latin-hypercube points (loss only) before gradient descent (default 0)")
    g.add_argument("--starts", type=int, default=1, metavar="K",
                   help="descend from the best K of the samples, or without --samples from the guess and K - 1 "
                        "Latin-hypercube points (default 1)")
    g.add_argument("--worlds", action="store_true",
                   help="run the --starts at once, as worlds of one model (same evaluations, one launch per kernel for all)")
    g.add_argument("--sample-range", type=float, metavar="F",
                   help="samples and extra starts within a factor F of the guess (and within --bounds); default 4")
    g.add_argument("--patience", type=int, default=20, metavar="N",
                   help="stop as stalled after N evaluations without a lower loss (default 20)")
    g.add_argument("--noise", type=float, metavar="SIGMA",
                   help="observation noise in m for the diagnostics (default: estimated from the residuals, at least 1%% "
                        "of the spacing); stated, the residuals are tested against it (a chi-square past its 99.9%% limit "
                        "is a warning)")
    g.add_argument("--force-noise", type=float, metavar="N",
                   help="a force log's measurement noise in N for the diagnostics (default: estimated from the curve's "
                        "residuals, at least 1%% of its RMS force); stated, the curve's residuals are tested against it")
    g.add_argument("--force-components", metavar="AXES",
                   help="the force log's columns fitted: distinct axes among x, y, z (default xyz; e.g. z where the log "
                        "measures the loading axis alone and writes 0 for the others, which otherwise count as "
                        "measured zeros)")
    g.add_argument("--no-diagnostics", action="store_true", help="skip the diagnostics (up to 4 P + 1 extra runs for P values, the range check included)")
    g.add_argument("--experiments", metavar="EXPERIMENTS.json",
                   help="a joint fit: more experiments (each its own scene and target) sharing the fitted material "
                        "with SCENE; a JSON list of objects with keys " + ", ".join(EXPERIMENT_KEYS))
    g.add_argument("--cameras", metavar="CAMERAS.json",
                   help="silhouette targets: the cameras (see docs/fitting.md); --target then names mask images")
    return parser


class _Given(argparse.Action):
    """Store the value, and note in ``<dest>_given`` that it was given (a default is no choice
    to refuse)."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, values)
        setattr(namespace, f"{self.dest}_given", True)


def default_optimizer(values: int) -> str:
    return "lbfgs" if values <= LBFGS_MAX_VALUES else "adam"


def jitter_model(model, fraction: float, seed: int):
    """Move every particle by a normal offset of ``fraction * spacing`` and recompute the
    rest density (a perfect lattice has exact distance ties at the support radius, which
    make neighbour lists, and the loss, switch under tiny parameter changes)."""
    if fraction:
        model.particle_x0 += np.random.default_rng(seed).normal(scale=fraction * model.spacing, size=model.particle_x0.shape)
        model.compute_rest_density()
    return model


def _arg(args, name, default=None):
    return getattr(args, name, default)


def _refuse_overwriting_inputs(outputs, inputs) -> None:
    """Refuse a file the fit writes that is one it reads (``-o`` onto the target or the scene
    file, ``--output-dir`` holding the target as fitted.usdc): each was replaced by the
    fit's JSON or run, and the measurement lost. ``outputs``/``inputs``: ``(what, path)``."""
    read = {}
    for what, path in inputs:
        if os.path.isfile(path):
            read.setdefault(os.path.realpath(path), (what, path))
    for what, path in outputs:
        # By real path, not file identity: every output replaces its name (os.replace), so a
        # hard link to an input is written as a file of its own and the input keeps its data.
        hit = read.get(os.path.realpath(path))
        if hit is not None:
            raise ValueError(f"{what} = {checks.shown_path(path)} is not allowed: it is {hit[0]} {checks.shown_path(hit[1])} of this fit, which the fit "
                             "would overwrite; write the results elsewhere")


def run_fit(args, out=None, err=None) -> int:
    """Run ``warp-esph fit`` from parsed ``args``; returns 0 for a converged fit, else
    ``EXIT_NOT_CONVERGED`` (5: stopped without converging, every result written, its line said
    last). Raises ``ValueError`` on bad input.
    ``out``/``err``: the report and the progress messages (default: the current
    ``sys.stdout``/``sys.stderr``, looked up at the call)."""
    out = sys.stdout if out is None else out
    err = sys.stderr if err is None else err
    import warp as wp  # noqa: PLC0415

    from .cli import (  # noqa: PLC0415
        EXIT_NOT_CONVERGED, _parse_bounds, _parse_param_scales, _safe_point, _signal_name, _stopped, option_flag)
    from .fit import (  # noqa: PLC0415
        BoundsError, Experiment, FitInterrupted, ParamScaleRefused, StartRefused, _material_indices, check_options, fit, load_target,
        solvers_record, starts_stable_steps)
    from .rollout import RolloutMemoryError  # noqa: PLC0415
    from .scenes import load_scene  # noqa: PLC0415
    from .simulate import MAX_STEPS_PER_FRAME, _steps_a_frame, resolve_timestep  # noqa: PLC0415

    jitter = checks.in_range("--jitter", _arg(args, "jitter", 0.0), 0.0, 0.5)  # a fraction of the spacing
    loss_scale = checks.positive("--loss-scale", _arg(args, "loss_scale", 1.0))
    if _arg(args, "radius") is not None:  # ChamferLoss refused it later as 'radius = 0.0', no option of the command
        args.radius = checks.positive("--radius", args.radius)
    given_memory = _arg(args, "memory_limit")  # None: not given (1024 MB)
    memory_limit = checks.positive("--memory-limit", 1024.0 if given_memory is None else given_memory) * 2**20
    bounds = _parse_bounds(args.bounds)
    # Each entry as typed ('hardening=-1e6:100'), for a refusal to name it so (_parse_bounds refused any other form).
    typed_bounds = {item.split("=", 1)[0].strip(): item for item in args.bounds or []}
    param_scales = _parse_param_scales(_arg(args, "param_scales", []))
    typed_param_scales = {item.split("=", 1)[0].strip(): item for item in _arg(args, "param_scales", []) or []}
    given_range = _arg(args, "sample_range")  # None: not given (a factor 4)
    sample_range = 4.0 if given_range is None else given_range
    lr = _arg(args, "lr")  # None: not given (fit's default; refused with gauss-newton when given)
    seed = _arg(args, "seed", 5)
    given_seed = seed if _arg(args, "seed_given", False) else None  # None: the default
    # Every option that needs no scene, checked before the scene is built and the targets read.
    opts = check_options(params=str(args.params), iterations=args.iterations, lr=lr, clip=args.clip, bounds=bounds,
                         optimizer=_arg(args, "optimizer") or "adam", patience=_arg(args, "patience", 20),
                         samples=_arg(args, "samples", 0), starts=_arg(args, "starts", 1),
                         sample_range=sample_range, seed=seed, noise=_arg(args, "noise"),
                         memory_limit=memory_limit, flag=option_flag, bounds_typed=typed_bounds,
                         param_scales=param_scales, param_scales_typed=typed_param_scales)
    params = opts["params"]
    # Options nothing would read: refused, not ignored (each ran as without it).
    if given_range is not None and opts["samples"] == 0 and opts["starts"] == 1:
        raise ValueError(f"--sample-range = {checks.shorten(given_range)!r} is not allowed without --samples or --starts: it sizes the "
                         "box of the global stage's samples and the extra starts, and this fit has neither")
    if given_seed is not None and not jitter and opts["samples"] == 0 and opts["starts"] == 1:
        # Nothing else draws from it (the diagnostics' noise is a number, not a draw).
        raise ValueError(f"--seed = {checks.shorten(given_seed)!r} is not allowed without --jitter, --samples or --starts: it seeds the "
                         "lattice's jitter and the global stage's draws, and this fit draws nothing")
    if _arg(args, "noise") is not None and _arg(args, "no_diagnostics", False):
        raise ValueError(f"--noise = {checks.shorten(args.noise)!r} is not allowed with --no-diagnostics: it is the observation noise "
                         "the diagnostics assume, and they are skipped")
    if _arg(args, "force_noise") is not None:
        if _arg(args, "no_diagnostics", False):
            raise ValueError(f"--force-noise = {checks.shorten(args.force_noise)!r} is not allowed with --no-diagnostics: it is the force "
                             "noise the diagnostics assume, and they are skipped")
        checks.noise("--force-noise", args.force_noise)
    if _arg(args, "force_components") is not None:
        given = args.force_components
        axes = given.strip().lower()
        if not axes or any(c not in "xyz" for c in axes) or len(set(axes)) != len(axes):
            raise ValueError(f"--force-components = {checks.shorten(given)!r} is not allowed: give distinct axes among x, y, z (e.g. z, "
                             "or xz)")
        args.force_components = axes
    if _arg(args, "worlds", False) and opts["starts"] < 2:
        raise ValueError(f"--worlds is not allowed with --starts = {opts['starts']}: it runs several starts at once "
                         "as worlds of one model; give --starts K > 1")
    if _arg(args, "worlds", False) and _arg(args, "optimizer") == "gauss-newton":
        # fit() refused it after the scene and targets were read, naming its own parameters
        # ("worlds = True ... optimizer = 'gauss-newton'").
        raise ValueError("--worlds is not allowed with --optimizer gauss-newton: its starts run one after the other "
                         "(forward runs only); leave --worlds out, or give --optimizer lbfgs or adam")
    for flag, name in (("--output-dir", "output_dir"), ("--output", "output"), ("--experiments", "experiments"),
                       ("--cameras", "cameras")):
        value = _arg(args, name)
        if value is not None and (not isinstance(value, (str, os.PathLike)) or not os.fspath(value) or "\0" in os.fspath(value)):
            # '' (an unset shell variable) was taken as not given: the experiments or cameras
            # were dropped and the fit ran without them, the results went to the default place.
            raise ValueError(f"{flag} = {checks.shorten(value)!r} is not allowed: must be a path (not empty, no NUL character)")
    for value in _arg(args, "target") or []:
        if isinstance(value, str) and (not value or "\0" in value):  # '' was 'target file  does not exist'
            raise ValueError(f"--target = {checks.shorten(value)!r} is not allowed: must be a path (not empty, no NUL character)")
    dtype = {"float32": wp.float32, "float64": wp.float64}[args.dtype]
    ck = args.checkpoint_every if args.checkpoint_every is not None else "auto"
    if ck != "auto":
        ck = checks.positive_int("--checkpoint-every", ck)
        if given_memory is not None:
            # Only the automatic choice reads the limit: a fixed segment ran as without it.
            raise ValueError(f"--memory-limit = {checks.shorten(given_memory)!r} is not allowed with --checkpoint-every = {ck}: it sizes "
                             "the automatic checkpointing (--checkpoint-every auto, the default); give one of the two")
    if _arg(args, "optimizer") == "gauss-newton":
        # Its runs go forward only (the Jacobian by forward differences), two states each: there
        # is no tape to checkpoint, and either option ran as if it had not been given.
        for flag, given in (("--memory-limit", given_memory), ("--checkpoint-every", None if ck == "auto" else ck)):
            if given is not None:
                raise ValueError(f"{flag} = {checks.shorten(given)!r} is not allowed with --optimizer gauss-newton: it sizes the "
                                 "checkpointing of the tape that gradient runs record, and a Gauss-Newton fit records "
                                 f"none (its runs go forward only, two states each); leave {flag} out")

    main_spec = {"scene": args.scene, "target": args.target, "target_frames": _arg(args, "target_frames"),
                 "target_body": _arg(args, "target_body"), "target_tool": _arg(args, "target_tool"), "cameras": _arg(args, "cameras"), "scale": args.scale,
                 "frames": args.frames, "fps": args.fps, "dt": args.dt, "material": args.material, "weight": 1.0,
                 "noise": _arg(args, "noise"), "force_noise": _arg(args, "force_noise"),
                 "cloud_coverage": _arg(args, "cloud_coverage")}
    specs = [("", main_spec)]
    if _arg(args, "experiments"):
        specs += _read_experiments(args.experiments)
    def load(where, spec, **how):
        try:
            return _experiment(spec, args, where, jitter, dtype, load_scene, load_target, resolve_timestep, **how)
        except (ValueError, FileNotFoundError) as e:
            # Every refusal of an experiment of the file names it (fps, dt, a target's; a
            # missing target's too, which named no experiment).
            said = str(e)
            message = said[len(where):] if where and said.startswith(where) else said
            written = spec.get("scene_as_written")
            if written is not None:
                # The scene file as the JSON wrote it: its resolved path ('/tmp/x/fast.toml:
                # ...') read as a name the user never gave.
                # Matched as the refusal shows it, too: a path over checks.PATH_SHOWN_WHOLE
                # characters by its ends (quoted or not), which the whole path's pattern missed.
                for shown, named in ((checks.shown_path(spec["scene"]), checks.shown_path(written)),
                                     (checks.shown_path(spec["scene"], False), checks.shown_path(written, False)),
                                     (spec["scene"], written)):
                    message = re.sub(re.escape(str(shown)) + r"(?![\w./\\-])", lambda _, named=named: str(named), message)
                unread = f"cannot read scene file {checks.shown_path(written)}"
                if message.startswith(unread):
                    # The name alone read as a file missing from the working folder, where nobody
                    # looked.
                    message = (f"{unread} (looked for relative to {checks.shown_path(spec['scene_folder'], False)}, the folder of the "
                               f"--experiments file){message[len(unread):]}")
            if where and f"{where}{message}" != said:
                # A plain error of its kind, the error read its cause: type(e)(text) raised a
                # TypeError traceback where an error's class takes more than its message
                # (json.JSONDecodeError's three arguments, UnicodeDecodeError's five, the
                # package's checks.Rebuilt errors' fields).
                again = FileNotFoundError if isinstance(e, FileNotFoundError) else ValueError
                raise again(f"{where}{message}") from e
            raise

    # Every experiment's targets whose frames are chosen, before any scene: an experiment's
    # choice was refused after the experiments before it had built theirs, launching kernels.
    # A file that two experiments name is read then too, and one observed alike by both at
    # frames known so far refused (the frames a scene sets, once it is built, below): it was
    # refused after every scene was built and their kernels had run.
    if _arg(args, "worlds", False):
        from .losses import is_tools_csv  # noqa: PLC0415

        logs = [path for _, spec in specs for path in _targets_of(spec) if is_tools_csv(path)]
        if logs:
            # fit() refused it after the scenes were built, in its own words ('worlds=True ...
            # (use worlds=False)'), which the command line never gave.
            raise ValueError(f"--worlds is not allowed with the force-log target {checks.shown_path(logs[0])}: a force curve's "
                             "loss is evaluated on the host for one model, not per world; leave --worlds out (the --starts "
                             "then run one after another)")
    named = [{checks.file_identity(path) for path in _targets_of(spec)} for _, spec in specs]
    shared = {real for i, mine in enumerate(named) for real in mine if any(real in other for other in named[i + 1:])}
    chosen = [load(where, spec, targets_only=True, shared=shared) for where, spec in specs]
    wheres = [where for where, _ in specs]
    _refuse_shared_observations([observed for _, observed in chosen], wheres)
    # Every experiment's force logs held to its scene's rate and tools, before any model.
    read_scenes = [load(where, spec, read_targets=read, scene_only=True) for (where, spec), (read, _) in zip(specs, chosen)]
    exps = [load(where, spec, read_targets=read, read_scene=scene)
            for (where, spec), (read, _), scene in zip(specs, chosen, read_scenes)]
    _refuse_shared_observations([list(zip(e.targets, e.observed, e.target_frames)) for e in exps], wheres)
    # A noise nothing reads: refused, not ignored. --noise is metres, read by position, cloud
    # and mesh targets; a force log (newtons) and silhouettes (occupancy) have noises of
    # their own, and a force-only fit had dropped '--noise 0.05' (meant as newtons) without a word.
    if _arg(args, "noise") is not None and not any(e.geometric for e in exps):
        raise ValueError(f"--noise = {checks.shorten(args.noise)!r} is not allowed: it is the noise of position, point-cloud and mesh "
                         f"targets (m), and the targets are {', '.join(dict.fromkeys(e.kinds for e in exps))}"
                         + ("; give a force log's noise in newtons as --force-noise" if any(e.forces for e in exps)
                            else ""))
    if _arg(args, "force_components") is not None and not any(e.forces for e in exps):
        raise ValueError(f"--force-components = {checks.shorten(args.force_components)!r} is not allowed: it picks the columns of "
                         f"force-log targets, and the targets are {', '.join(dict.fromkeys(e.kinds for e in exps))}")
    if _arg(args, "force_noise") is not None and not any(e.forces for e in exps):
        raise ValueError(f"--force-noise = {checks.shorten(args.force_noise)!r} is not allowed: it is the noise of force-log targets "
                         f"(N), and the targets are {', '.join(dict.fromkeys(e.kinds for e in exps))}")
    if opts["samples"] or opts["starts"] > 1:
        # The steps per frame chosen from the guess's stable step were too long for every
        # stiffer start (a start at 4 x mu ran at 2 x its step, warned and could blow up): the
        # experiments whose step is the command's own choice take the stiffest start's, the
        # same for all starts (fit.starts_stable_steps: the points fit draws, before any run).
        try:
            limits = starts_stable_steps([e.model for e in exps], params, materials=[e.materials or None for e in exps],
                                         bounds=bounds, samples=opts["samples"], starts=opts["starts"],
                                         sample_range=sample_range, seed=seed, names=[e.scene.name for e in exps],
                                         param_scales=param_scales)
        except ParamScaleRefused as e:
            raise ValueError(e.said(option_flag, typed_param_scales.get(e.name))) from None
        except BoundsError as e:
            # Named as typed: it was "bounds['lam'] = (-1e+05, 100)", fit's parameter.
            raise ValueError(e.said(option_flag, typed_bounds.get(e.name))) from None
        except StartRefused as e:
            raise ValueError(e.said(option_flag, typed_bounds)) from None
        for k, (e, limit) in enumerate(zip(exps, limits)):
            if e.auto_step and limit < e.dt:
                steps, n = _steps_a_frame(1.0 / e.fps, limit)
                if not n:
                    # resolve_timestep would blame the scene's materials, which the guess's
                    # own step showed are not the cause: the starts' box is.
                    starts = f"--samples {opts['samples']}" if opts["samples"] else f"--starts {opts['starts']}"
                    raise ValueError(
                        f"{specs[k][0]}the stable step {limit:.3g} s of the stiffest point {starts} starts from is not "
                        f"allowed: a frame (1/fps = {1.0 / e.fps:g} s) would take {steps:.2g} steps, more than "
                        f"{MAX_STEPS_PER_FRAME:.0e} (the guess's step is {e.dt:.3g} s): give a smaller --sample-range "
                        f"(now {sample_range:g}) or narrower --bounds, or give {'its dt' if specs[k][0] else '--dt'}")
                exps[k] = load(specs[k][0], {**specs[k][1], "step_limit": limit})

    # Where the results go, checked before the fit (a folder in the way was found after it).
    folder = _arg(args, "output_dir") or f"fit_{exps[0].scene.name}"
    checks.output_place("--output-dir", folder, folder=True)
    # fitted.usdc even with --no-usd: an earlier fit's is removed (_remove_earlier_run), and a
    # target read from there was deleted.
    names = ["history.csv", "loss.png", "params.png", "fitted.usdc"]
    names += [] if _arg(args, "output") else ["fit.json"]
    for name in names:
        if name == "fitted.usdc" and args.no_usd:
            continue  # not written, and a folder of that name is left alone
        if name == "fitted.usdc":
            checks.usd_output("--output-dir", folder, os.path.join(folder, name))
        if os.path.isdir(os.path.join(folder, name)):
            raise ValueError(f"--output-dir = {checks.shown_path(folder)} is not allowed: {name} in it is a folder; the fit writes a file there")
        checks.output_files("--output-dir", folder, [name])
    if _arg(args, "output"):
        checks.output_place("--output", args.output)
    # With -o elsewhere, an earlier fit's fit.json in the folder is removed (_remove_earlier_run):
    # an input of that name there is refused as one the fit would overwrite.
    _refuse_overwriting_inputs(
        [(f"--output-dir {checks.shown_path(folder, False)}: {name}", os.path.join(folder, name)) for name in dict.fromkeys([*names, "fit.json"])]
        + ([("--output", args.output)] if _arg(args, "output") else []),
        [("the scene", str(spec["scene"])) for _, spec in specs]
        + [("--target", str(t)) for _, spec in specs for t in (spec["target"] if isinstance(spec["target"], (list, tuple))
                                                                else [spec["target"]])]
        + [("--cameras", str(spec["cameras"])) for _, spec in specs if spec.get("cameras")]
        + ([("--experiments", str(args.experiments))] if _arg(args, "experiments") else [])
        # The meshes a scene file reads (Scene.inputs, as run refuses them): -o part.usdc beside
        # part.toml replaced its mesh with the fit's JSON. (Its own file is "the scene" above.)
        + [(f"{what} of {checks.shown_path(spec.get('scene_as_written') or spec['scene'], False)}", path)
           for (_, spec), e in zip(specs, exps) for what, path in e.scene.inputs])
    if _arg(args, "output"):
        from .usd import USD_EXTENSIONS  # noqa: PLC0415

        if os.path.splitext(os.fsdecode(args.output))[1].lower() in USD_EXTENSIONS:
            # run's -o is its USD, fit's its JSON: `-o run.usdc` (the fitted run meant) replaced
            # an earlier run's file with the fit's JSON. (One that is an input is refused above as such.)
            raise ValueError(f"--output = {args.output!r} is not allowed: it is the fit's JSON file (fit.json), and the fitted "
                             "run's USD is fitted.usdc in --output-dir; give a .json name")

    # The experiments' lines wait for the fit's first message, which it gives once every
    # option it checks itself has passed: a refusal stays the run's one line.
    waiting: list[str] = []

    def log(message):
        for line in [*waiting, message]:
            print(f"warp-esph fit: {line}", file=err, flush=True)
        waiting.clear()

    for e in exps:
        e.loss = loss_scale * e.loss if loss_scale != 1.0 else e.loss
    n_values = len(params) * len(_material_indices(exps[0].model, exps[0].materials or None))
    optimizer = _arg(args, "optimizer") or default_optimizer(n_values)
    if args.clip is not None and optimizer != "adam":
        # fit() would refuse it too, under its Python name and without saying the choice was the default.
        chosen = "" if _arg(args, "optimizer") else f" (the default for up to {LBFGS_MAX_VALUES} fitted values)"
        raise ValueError(f"--clip is not allowed with --optimizer {optimizer}{chosen}: it clips Adam's steps; give "
                         "--optimizer adam")
    for e in exps:
        waiting.append(f"{e.scene.name}: {e.model.particle_count} particles, {e.frames} frames at {e.fps:g} fps, "
                       f"dt = {e.dt:.4g} s: each evaluation runs {e.frames * e.substeps} steps; fitting {', '.join(params)} with "
                       f"{optimizer} to {e.kinds} from {', '.join(str(p) for p in e.targets)}")
        waiting.extend(e.readings)
    experiments = [Experiment(e.model, e.loss, steps=e.frames * e.substeps, dt=e.dt, materials=e.materials,
                              checkpoint_every=ck, weight=e.weight, noise=e.noise if e.geometric else None,
                              name=e.scene.name,
                              monitor_exempt=tuple(getattr(e.scene, "diverges", ()) or ())) for e in exps]
    scene, model, frames, fps, dt = exps[0].scene, exps[0].model, exps[0].frames, exps[0].fps, exps[0].dt
    scale = exps[0].scale
    targets = exps[0].targets
    meta = {"scene": scene.name, "scale": scale, "targets": [os.path.abspath(str(p)) for p in targets],
            "target_frames": exps[0].target_frames, "fps": fps, "dt": dt,
            "frames": frames, "params_fitted": params,
            **({"force_components": _arg(args, "force_components") or "xyz"} if any(e.forces for e in exps) else {}), "optimizer": optimizer, "jitter": jitter, "loss_scale": loss_scale,
            "support_radius": model.support_radius,
            # The fit asked for and what it resolves to at the initial values, per experiment
            # where they differ (fit.json's "solver": at the fitted ones; "auto" resolves by the values).
            "solver_initial": solvers_record([e.model for e in exps]),
            "experiments": [{"scene": e.scene.name, "scale": e.scale, "targets": [os.path.abspath(str(p)) for p in e.targets],
                             "target_frames": e.target_frames,
                             "fps": e.fps, "dt": e.dt, "frames": e.frames, "weight": e.weight, "noise": e.noise,
                             "force_noise": e.force_noise}
                            for e in exps]}
    drawn = opts["samples"] > 0 or opts["starts"] > 1
    try:
        result = fit(experiments, None, params, iterations=args.iterations,
                     lr=lr, bounds=bounds, param_scales=param_scales, clip=args.clip, memory_limit=memory_limit,
                     optimizer=optimizer, progress=not args.no_progress, samples=_arg(args, "samples", 0),
                     starts=_arg(args, "starts", 1), worlds=_arg(args, "worlds", False),
                     # Given only where the fit draws (it refuses them elsewhere, as the checks above did).
                     sample_range=sample_range if drawn else None, seed=seed if drawn else None,
                     patience=_arg(args, "patience", 20), diagnostics=not _arg(args, "no_diagnostics", False),
                     noise=_arg(args, "noise"), log=log, callback=lambda *_: _safe_point(args))
    except ParamScaleRefused as e:
        raise ValueError(e.said(option_flag, typed_param_scales.get(e.name))) from None
    except BoundsError as e:
        raise ValueError(e.said(option_flag, typed_bounds.get(e.name))) from None
    except StartRefused as e:
        raise ValueError(e.said(option_flag, typed_bounds)) from None
    except RolloutMemoryError as e:
        k = next((k for k, x in enumerate(experiments) if x is e.experiment), None)
        if k is None:
            raise
        raise ValueError(_memory_refusal(e, exps[k], specs[k][0], ck)) from None
    except FitInterrupted as e:
        # Ctrl-C: the evaluations so far and the best of them are kept, as a run keeps its
        # finished frames; the exit is still the interrupt's.
        # The signal by name, as run's and sweep's lines say it: a SIGTERM was written to fit.json
        # and its line as Ctrl-C ('interrupted'), the exit alone (143) telling.
        stopped = _stopped(args)
        if e.result is not None:
            from .cli import _Deferred  # noqa: PLC0415

            e.result.signal = _signal_name(args)

            # Interrupted in the diagnostics, the fit itself had finished: its fit.json read as
            # a complete run with --no-diagnostics, and the log called it the best so far.
            during = "the fit" if e.result.stopped == "interrupted" else "the diagnostics"
            done: list = []
            # A second signal here (a second Ctrl-C; timeout signals the command, then its
            # group) ended the process at once: no fit.json, the best so far lost. It waits
            # for the files and their line; the exit is still the interrupt's.
            with _Deferred(args):
                _remove_earlier_run(folder, _arg(args, "output"))
                try:
                    written = write_outputs(e.result, folder, {**meta, "interrupted": during},
                                            json_path=_arg(args, "output"), written=done)
                except OSError as w:
                    # A full disk under them: the error reached the command's handler as bad input
                    # (exit 2, the bare '[Errno 28] ...'), the Ctrl-C dropped.
                    kept = (f"the evaluations so far are kept only in {', '.join(map(str, done))}, written before it"
                            if done else "none of its files was written: the evaluations so far are lost")
                    raise checks.interrupted(f"cannot write {w.filename or folder}: {w.strerror or w} ({kept})") from None
                if during == "the fit":
                    # Counted as the summary line counts them: the history's length alone had
                    # added the global stage's samples to the descent's under one word.
                    log(f"{stopped} after {_evaluations_said(e.result)}; wrote the best so far (loss "
                        f"{e.result.loss:.4g}) to {', '.join(written)}")
                else:
                    log(f"{stopped} during the diagnostics: wrote the finished fit ({e.result.stopped}, loss "
                        f"{e.result.loss:.4g}) without them to {', '.join(written)}")
            raise KeyboardInterrupt from None
        # Before a finite loss: the line said 'interrupted' alone, not that no file was written.
        raise checks.interrupted("no evaluation had finished with a finite loss, so there is no best point to "
                                 "keep: nothing is written") from None
    # The results first: a file that cannot be written (a full disk) lost them, the values
    # printed only after every file was written.
    print(f"fit {result.termination}", file=out)
    print(f"loss {result.initial_loss:.4g} -> {result.loss:.4g} in {_evaluations_said(result)}", file=out)
    for name, v in result.params.items():
        print(f"  {name} = {', '.join(f'{x:.6g}' for x in v)} {UNITS[name]}", file=out)
    lab = _lab_values(result)
    if lab:
        print(f"  as a lab measures them: {lab} (Material.from_rheology's)", file=out)
    if result.step_limit_said():
        print(f"warning: {result.step_limit_said()}", file=out)
    if result.diagnostics is not None:
        print(result.diagnostics.summary(), file=out)
    written = []

    def failed(e: OSError, where) -> checks.OutputWriteError:
        kept = f"wrote {', '.join(map(str, written))} before it" if written else "none of its files was written"
        return checks.OutputWriteError(f"cannot write {where}: {e.strerror or e} (the fit's results are printed above; "
                                       f"{kept})", e)

    usd_path = os.path.join(folder, "fitted.usdc")
    try:
        try:
            _remove_earlier_run(folder, _arg(args, "output"))
            write_outputs(result, folder, meta, json_path=_arg(args, "output"), written=written)
        except OSError as e:
            raise failed(e, e.filename or folder) from None
        if not args.no_usd:
            from .fit import write_fitted_usd  # noqa: PLC0415

            try:
                from .usd import OutputInUse  # noqa: PLC0415
            except ImportError:  # without USD support nothing is written there
                OutputInUse = ()  # noqa: N806
            try:
                if write_fitted_usd(result.model, usd_path, frames, fps, dt):
                    written.append(usd_path)
            except OSError as e:
                raise failed(e, usd_path) from None
            except OutputInUse as e:
                # Another writer holds fitted.usdc (a second fit into this folder): the line
                # named the library's 'path' and not what this fit had written before it.
                kept = f"wrote {', '.join(map(str, written))} before it" if written else "none of its files was written"
                named = f"--output-dir = {checks.shown_path(folder)}" if _arg(args, "output_dir") else f"the output folder {checks.shown_path(folder, False)}"
                raise ValueError(f"{named} is not allowed: {e.reason.replace('writing it', f'writing {checks.shown_path(usd_path, False)}')} (the "
                                 f"fit's results are printed above; {kept})") from None
    except KeyboardInterrupt:
        # The fit had finished: the line said 'interrupted' alone, and a fitted run cut short
        # stayed beside fit.json as if it were the fitted run.
        if usd_path not in written and os.path.isfile(usd_path):
            os.remove(usd_path)
        kept = f"wrote {', '.join(written)}; the other files are not written" if written else "none of its files is written"
        log(f"{_stopped(args)} while writing the fit's results (printed above): {kept}")
        raise
    print("wrote " + ", ".join(written), file=out)
    unconverged = _unconverged_said(result, args)
    if unconverged:
        # A fit that stopped short exited 0, as a converged one: a script read its values as fitted.
        log(unconverged)
        return EXIT_NOT_CONVERGED
    return 0


def _unconverged_said(result, args) -> str:
    """The line of a fit that stopped without converging (its status ``EXIT_NOT_CONVERGED``), what
    to change to go further, or "" for a converged one. ``--iterations 0`` asks for the start's
    evaluation and no descent, so nothing is judged converged or not."""
    from .cli import EXIT_NOT_CONVERGED  # noqa: PLC0415

    if result.converged or args.iterations == 0:
        return ""
    how = {
        "iterations": f"it hit the iteration cap (--iterations {args.iterations}); run it again with a larger --iterations "
                      "to go further (it starts again from the scene's values)",
        # A search's stall (the default L-BFGS's on a rough loss) was told to raise --patience,
        # which it never reached.
        "stalled": (f"it stalled (no lower loss in --patience {_arg(args, 'patience', 20)} evaluations); a larger --patience "
                    "waits longer for one, a larger --iterations with it" if result.stalled_by == "patience" else
                    "it stalled: its optimiser's search found no lower loss (an L-BFGS line search shrank its step below "
                    "the tolerance; Gauss-Newton's damping grew past 1e8, or a Jacobian column's runs failed on both sides), which a larger --patience or "
                    "--iterations does not change: a rough loss or a narrow valley (docs/fitting.md, \"How a fit ends\"); "
                    "start elsewhere (--samples) or try another --optimizer"),
        "flat": "the gradient is exactly zero at the start, and more iterations will not change that (the first line "
                "says what to change)",
        "uninformative": "the data do not tell the start from values nearby, and more iterations will not change that "
                         "(the first line says what to change)",
    }.get(result.stopped, f"it stopped: {result.stopped}")
    return f"not converged: {how}; its results are written as above (exit {EXIT_NOT_CONVERGED})"


def _evaluations_said(result) -> str:
    """What ran, as fit.json counts it: ``sample_evaluations`` (the global stage, loss only,
    the guess first), ``evaluations`` (the descent's, every start's) and the diagnostics'
    ``evaluations``. The descent's count alone had been printed as the fit's, a fit with 8
    samples saying 13 evaluations where 22 had run, and the diagnostics' runs not at all."""
    record = result.to_dict()
    descent, samples = record["evaluations"], record["sample_evaluations"]
    starts = len(result.starts)
    of_descent = "of the descent" + (f" ({starts} starts)" if starts > 1 else "")
    if samples:
        said = (f"{checks.plural(samples + descent, 'evaluation')}: {samples} of the global stage (loss only: the guess and "
                f"{checks.plural(samples - 1, 'sample')}), {descent} {of_descent}")
    else:
        said = f"{checks.plural(descent, 'evaluation')} {of_descent}"
    if result.diagnostics is not None:
        said += f"; then {checks.plural(result.diagnostics.evaluations, 'run')} of the diagnostics"
    return said


def _remove_earlier_run(folder, json_path=None) -> None:
    """Remove an earlier fit's results that this fit does not write again from ``folder``
    before this fit's go there: its ``fitted.usdc`` (with ``--no-usd``, an interrupt, or a
    fitted run that fails, it stayed beside this fit's ``fit.json`` as if it were this fit's
    run; it is written again after the fit), and its ``fit.json`` where ``json_path`` (``-o``)
    puts this fit's elsewhere (it stayed beside this fit's history and plots, and read as
    this fit's result)."""
    stale = [os.path.join(folder, "fitted.usdc")]
    mine = os.path.join(folder, "fit.json")
    if json_path is not None and os.path.realpath(json_path) != os.path.realpath(mine):
        stale.append(mine)
    for path in stale:
        if os.path.isfile(path) or os.path.islink(path):
            os.remove(path)


#: Keys of an entry of the ``--experiments`` file.
EXPERIMENT_KEYS = ("scene", "target", "target_frames", "target_body", "target_tool", "cameras", "scale", "frames", "fps", "dt", "material",
                   "weight", "noise", "force_noise", "cloud_coverage")


def _read_experiments(path) -> list[tuple[str, dict]]:
    """``(where, spec)`` of each entry of an ``--experiments`` JSON file: a list of objects
    with ``EXPERIMENT_KEYS`` (``scene`` and ``target`` required; files relative to the JSON
    file's folder)."""
    from .scenes import SCENES  # noqa: PLC0415

    p = os.fspath(path)
    doc = checks.json_file("--experiments", p)
    # Said what it is: an empty list and one experiment's object were both told to give a list.
    if isinstance(doc, dict) and "experiments" in doc:
        doc = doc["experiments"]  # {"experiments": {...}}: the one object under the key, likewise
    single = isinstance(doc, dict) and bool(set(doc) & {"scene", "target"})
    if isinstance(doc, dict):
        doc = None
    if not isinstance(doc, list) or not doc:
        why = ("it is one experiment's object, not a list of them: write it in brackets, [{...}]" if single else
               "it lists no experiments: give one or more objects with the keys scene and target" if doc == [] else
               "give a list of experiments (or {\"experiments\": [...]})")
        raise ValueError(f"--experiments {checks.shown_path(p, False)} is not allowed: {why}")
    base = os.path.dirname(os.path.abspath(p))
    out = []
    for k, spec in enumerate(doc):
        where = f"{checks.shown_path(p, False)}: experiment #{k + 1}: "
        if not isinstance(spec, dict):
            raise ValueError(f"{where}must be an object with keys {', '.join(EXPERIMENT_KEYS)}")
        unknown = sorted(set(spec) - set(EXPERIMENT_KEYS))
        if unknown:
            raise ValueError(f"{where}unknown key {unknown[0]!r} (allowed: {', '.join(EXPERIMENT_KEYS)})")
        for key in ("scene", "target"):
            if key not in spec:
                raise ValueError(f"{where}missing key {key!r}")
        # 3 was a TypeError traceback, null loaded the default scene.
        if not isinstance(spec["scene"], str) or not spec["scene"].strip():
            raise ValueError(f"{where}scene = {checks.shorten(spec['scene'])!r} is not allowed: must be a scene name "
                             "or a .toml path")
        t = spec["target"]
        if not (isinstance(t, str) and t.strip()) and not (
                isinstance(t, list) and t and all(isinstance(x, str) and x.strip() for x in t)):
            raise ValueError(f"{where}target = {checks.shorten(t)!r} is not allowed: must be a file path or a "
                             "non-empty list of them")
        spec = {"scale": 1.0, "weight": 1.0, **spec}
        checks.positive(f"{where}weight", spec["weight"])  # negative: its loss maximised; checked before any scene

        def rel(x):
            return x if os.path.isabs(str(x)) else os.path.join(base, str(x))

        spec["target"] = [rel(t) for t in (spec["target"] if isinstance(spec["target"], list) else [spec["target"]])]
        scene = spec["scene"]
        # Every name load_scene reads as a file, not only '.toml' ones: 'sub/plain' was read
        # relative to the working folder, named without the folder it was looked for in.
        if scene not in SCENES and (os.path.splitext(scene)[1].lower() == ".toml" or os.sep in scene
                                    or (os.altsep and os.altsep in scene) or os.path.exists(rel(scene))):
            if not os.path.isabs(scene):
                spec["scene_as_written"] = spec["scene"]  # how a refusal names it (the caller's)
                spec["scene_folder"] = base  # where a missing one was looked for
            spec["scene"] = rel(spec["scene"])
        elif scene not in SCENES:
            # Neither a built-in nor a file beside the JSON: load_scene would read a file of that
            # name from the working folder, which an experiment's names are never relative to.
            from .scenes import _unknown  # noqa: PLC0415

            raise ValueError(f"{where}{_unknown(scene)} (relative to {checks.shown_path(base, False)}, the folder of the --experiments file)")
        cams = spec.get("cameras")
        if cams is not None and not (isinstance(cams, str) and cams.strip()):
            # "" was taken as no cameras: the masks were then read as other targets, or refused for another reason.
            raise ValueError(f"{where}cameras = {checks.shorten(cams)!r} is not allowed: must be the path of a camera file")
        if cams is not None:
            spec["cameras"] = rel(cams)
        chosen = spec.get("material")
        if isinstance(chosen, bool) or isinstance(chosen, list) and any(isinstance(m, bool) for m in chosen):
            # true read as a body named 'True'
            raise ValueError(f"{where}material = {checks.shorten(chosen)!r} is not allowed: give a material index or a body name, "
                             "or a list of them")
        if isinstance(chosen, (str, int)):
            spec["material"] = [str(chosen)]
        out.append((where, spec))
    return out


def _coverages(spec, args, where, count, key) -> tuple[list[str], str]:
    """The experiment's ``--cloud-coverage`` (``cloud_coverage`` of an ``--experiments`` entry):
    one for all its targets or one per target, in order ([] where none is given), and the name
    a refusal gives it. An entry without its own takes the command's where that is given once
    (for all, as it reached every experiment before it could be given per target); given per
    ``--target``, it is the command's targets' alone."""
    from .losses import ChamferLoss  # noqa: PLC0415

    given, name = spec.get("cloud_coverage"), key("cloud_coverage")
    if where and given is None:
        command = _arg(args, "cloud_coverage")
        given, name = (command, "--cloud-coverage") if command and len(command) == 1 else (None, name)
    if given is None:
        return [], name
    values = list(given) if isinstance(given, (list, tuple)) else [given]
    for v in values:
        if not isinstance(v, str) or v not in ChamferLoss.COVERAGES:
            raise ValueError(f"{where}{name} = {checks.shorten(given)!r} is not allowed: give one of "
                             f"{', '.join(ChamferLoss.COVERAGES)}, or a list of them, one per {key('target')}")
    if len(values) != 1 and len(values) != count:
        raise ValueError(f"{where}{name} is given {len(values)} times for {count} {key('target')} files: give it once "
                         f"per {key('target')}, in the same order, or once for all")
    return values, name


def _numbered_frames(fspec, name: str) -> list[int]:
    """The frames ``fspec`` (``1,2,3``, ``A:B[:STEP]``, B included) names for a target that stores
    no frame numbers of its own; ``name`` (``--target-frames``) names it in a refusal."""
    try:
        chosen = []
        for part in str(fspec).split(","):
            bits = part.split(":")
            if len(bits) == 1:
                chosen.append(int(part))
            elif len(bits) in (2, 3):
                # A:B[:STEP], both ends given (B included): the frames of a file of many
                # entries, which stores none of its own, without writing each out.
                a, b, step = int(bits[0]), int(bits[1]), int(bits[2]) if len(bits) == 3 else 1
                if step < 1 or b < a:
                    raise ValueError
                span = range(a, b + 1, step)
                if len(chosen) + len(span) > MAX_TARGET_FRAMES:  # counted before the list is made
                    raise ValueError(f"{name} = {checks.shorten(fspec)!r} is not allowed: it names more than "
                                     f"{MAX_TARGET_FRAMES} frames")
                chosen.extend(span)
            else:
                raise ValueError
        if min(chosen) < 0:
            raise ValueError
    except ValueError as e:
        if str(e).startswith(name):
            raise
        # -1 ended in a KeyError traceback (.npz) or was dropped (a force log).
        raise ValueError(f"{name} = {checks.shorten(fspec)!r} is not allowed: use comma-separated frame "
                         "indices >= 0 or ranges A:B[:STEP] (B included)") from None
    return chosen


def _chosen_frames(t, fspec, name: str):
    """The frames of target ``t`` (read with ``fspec``) that the fit observes, or None where they
    are known only once the run's length is (a cloud's or a mesh's default: the last)."""
    usd = os.path.splitext(str(t.path))[1].lower() in (".usd", ".usda", ".usdc")
    if fspec is None or usd or t.frames_stored:
        return None if t.frames is None else list(t.frames)
    chosen = _numbered_frames(fspec, name)
    _refuse_frames_not_logged(t, chosen, fspec, name)
    return chosen


def _refuse_frames_not_logged(t, chosen, fspec, name: str) -> None:
    """Refuse frames chosen (``--target-frames``) that force log ``t`` holds no row of: the
    loss refused them as 'frames [5] are not allowed', a name the command never gave, after
    the scene was built."""
    if t.kind != "forces":
        return
    held = sorted({r["frame"] for r in t.data})
    absent = [f for f in chosen if f not in held]
    if absent:
        raise ValueError(f"{name} = {checks.shorten(fspec)!r} is not allowed: the force log {checks.shown_path(t.path, False)} holds "
                         f"{_frames_said(held)} of tool {t.tool!r}, not {', '.join(map(str, absent))}")


def _frames_said(frames) -> str:
    """'frame 2' or 'frames 1, 2, ...' (the first eight, then how many in all)."""
    shown = ", ".join(map(str, frames[:8])) + (f", ... ({len(frames)} in all)" if len(frames) > 8 else "")
    return f"{'frame' if len(frames) == 1 else 'frames'} {shown}"


def _bodies_observed(t) -> frozenset | None:
    """The bodies a target observes: its one body, or every body of a run's USD read whole
    (``Target.bodies``); None for a file that holds no bodies."""
    if t.body is not None:
        return frozenset([t.body])
    return None if t.bodies is None else frozenset(name for name, _ in t.bodies)


def _targets_of(spec) -> list:
    """An experiment's targets: its one ``target`` or its list."""
    return list(spec["target"]) if isinstance(spec["target"], (list, tuple)) else [spec["target"]]


def _refuse_shared_observations(observations, wheres) -> None:
    """Refuse one file observed alike by two experiments (a body of a run's USD both observe,
    a run's USD read whole observing every body of it; the same tool's force log) at a frame
    both fit: its observations there would count twice, as within one experiment
    (``_refuse_repeated_frames``). Another body or tool of the file is another observation.
    ``observations``: each experiment's targets as (path, what it observes: its file identity,
    bodies and tool, or None for silhouettes; its frames, or None where not known yet);
    ``wheres``: each experiment's prefix ('' for the command line's)."""
    seen: dict[tuple, list] = {}
    for i, mine in enumerate(observations):
        for path, observed, frames in mine:
            if observed is None or frames is None:
                continue
            real, bodies, tool = observed
            for j, other_bodies, other_frames in seen.get((real, tool), []):
                shared = None if bodies is None else sorted(bodies & other_bodies)
                both = sorted(set(frames) & set(other_frames))
                if both and shared != []:
                    of = ((f" (bod{'y' if len(shared) == 1 else 'ies'} {', '.join(map(repr, shared))})" if shared else "")
                          + (f" (tool {tool!r})" if tool is not None else ""))
                    first = wheres[j].rstrip(": ") or "the command line's --target"
                    name = "target" if wheres[i] else "--target"
                    raise ValueError(
                        f"{wheres[i]}{name} = {checks.shown_path(path)}{of} is not allowed at {_frames_said(both)}: "
                        f"{first} observes the same file{' alike' if of else ''} there, so its observations would count "
                        "twice, and the diagnostics' standard errors shrink by 1/sqrt(2); give it in one experiment "
                        "(two experiments may share a file for different bodies or tools)")
            seen.setdefault((real, tool), []).append((i, bodies, frames))


def _refuse_repeated_frames(entries, where: str, key) -> None:
    """Refuse one file given as two targets whose frames overlap: each frame's observations would
    count twice. ``entries``: (the target's index, its path, the frames' choice as given or None,
    the frames or None: not known yet), in the order given. Frames shared in part count twice as much as the same
    frames do, so they are refused too: the choice of frames is one option of one target."""
    name, fname = key("target"), key("target_frames")
    seen: dict = {}
    for k, path, fspec, frames in entries:
        if frames is None:
            continue
        real = checks.file_identity(path)
        for j, other_spec, other in seen.get(real, []):
            both = sorted(set(frames) & set(other))
            if both:
                def said(spec):
                    return "left out (the default)" if spec is None else repr(checks.shorten(spec))

                raise ValueError(
                    f"{where}{name} = {checks.shown_path(path)} is not allowed twice at {_frames_said(both)} "
                    f"({name} #{j + 1} and #{k + 1} are one file, and {fname} {said(other_spec)} and {said(fspec)} both "
                    f"choose {'it' if len(both) == 1 else 'them'}): its observations there would count twice, and the "
                    f"diagnostics' standard errors shrink by 1/sqrt(2); give the file once, with {fname} naming every frame "
                    "to fit")
        seen.setdefault(real, []).append((k, fspec, frames))


def _experiment(spec, args, where, jitter, dtype, load_scene, load_target, resolve_timestep, *, targets_only=False,
                shared=frozenset(), read_targets=None, scene_only=False, read_scene=None):
    """One experiment of the command: scene, model (jittered), targets, loss, time step.
    ``targets_only``: only its targets whose frames are chosen, or whose file (by
    ``checks.file_identity``) is in ``shared`` or given twice, or a CSV (where a force log is
    among them, every target), read before any scene is read: those (by index) and what each
    observes (``_refuse_shared_observations``' entries, frames None where the scene sets them);
    ``read_targets``: those, read so before. ``scene_only``: where a force log is among them,
    the scene read without a kernel, the logs held to its rate and tools (else None);
    ``read_scene``: that scene."""
    import types  # noqa: PLC0415

    def key(name):
        # An experiment's keys are named as its file writes them ('frames'), the command's as
        # its options ('--frames'): the file's bad frames were refused as '--frames', which the
        # command line never gave.
        return name if where else "--" + name.replace("_", "-")

    scale_name = f"{where}{key('scale')}"
    scale = checks.positive(scale_name, spec["scale"])
    targets = _targets_of(spec)
    tframes = spec.get("target_frames")
    if isinstance(tframes, (list, tuple)) and not tframes:
        raise ValueError(f"{where}{key('target_frames')} = {checks.shorten(tframes)!r} is not allowed: it chooses no frame; give "
                         f"a choice once for all {key('target')} files or once per {key('target')}, or leave it out for "
                         "every frame")
    # Given is not true: 0 (an experiment's frame 0) and '' were dropped, every frame fitted.
    tframes = tframes if isinstance(tframes, (list, tuple)) else ([] if tframes is None else [tframes])
    if len(tframes) > 1 and len(tframes) != len(targets):
        # A list of frame numbers ([2, 4]) is read as one choice per target, and was refused
        # as given 2 times for 1 target, leaving the user to guess the form a choice takes.
        numbers = all(isinstance(f, int) and not isinstance(f, bool) for f in tframes)
        hint = (f"; a list is one choice per {key('target')}: frames {', '.join(map(str, tframes))} of one target are "
                f"\"{','.join(map(str, tframes))}\"" if numbers else "")
        raise ValueError(f"{where}{key('target_frames')} is given {len(tframes)} times for {len(targets)} "
                         f"{key('target')} files: give it once per {key('target')}, in the same order, or once for all{hint}")
    coverages, coverage_name = _coverages(spec, args, where, len(targets), key)
    cameras = spec.get("cameras")
    fspecs = [tframes[k] if len(tframes) > 1 else (tframes[0] if tframes else None) for k in range(len(targets))]
    # One recording given twice (the same frames of the same file) counted its observations
    # twice: the diagnostics reported standard errors 1/sqrt(2) of the data's. The same choice
    # written alike is refused here; one written otherwise ('1:3' and '1,2,3'), or choices that
    # share some frames, once the frames are read (_refuse_repeated_frames).
    given = {}
    for k, path in enumerate(targets):
        first = given.setdefault((checks.file_identity(path), None if fspecs[k] is None else str(fspecs[k])), k)
        if first != k:
            name = key("target")
            raise ValueError(f"{where}{name} = {checks.shown_path(path)} is not allowed twice ({name} #{first + 1} and "
                             f"#{k + 1} are one file{'' if fspecs[k] is None else ' at the same frames'}): its observations "
                             "would count twice, and the diagnostics' standard errors shrink by 1/sqrt(2); give each file once")
    real = [checks.file_identity(path) for path in targets]
    repeated = {k for k in range(len(targets)) if real.count(real[k]) > 1}

    def read(path, fspec):
        ext = os.path.splitext(str(path))[1].lower()
        usd = ext in (".usd", ".usda", ".usdc")
        # --target-body picks a body of a run's USD; the other targets of the experiment (a force
        # log beside it) take none (refused below where no target is such a USD).
        # load_target's frames are the command's --target-frames: 'frames' named no option (an
        # experiment's refusal is prefixed with its name by the caller).
        t = load_target(path, body=spec.get("target_body") if usd else None, frames=fspec if usd else None,
                        tool=spec.get("target_tool"), frames_name=key("target_frames"), body_name=key("target_body"),
                        tool_name=key("target_tool"))
        if fspec is not None and not usd and t.frames_stored:
            # The file numbers its frames: --target-frames chooses among them, as of a run's USD
            # (all, last, A:B:STEP, ...; it renumbered them: frame 2's positions were fitted at
            # frame 1, exit 0).
            from .fit import choose_stored_frames  # noqa: PLC0415

            try:
                choose_stored_frames(t, fspec, key("target_frames"))
            except ValueError as e:
                raise ValueError(f"{where}{e}") from None
        return t

    flag = "fps" if where else "--fps"

    def held_to_scene(file_targets, scene):
        """The experiment's rate (its ``fps``, a stored target's, or the scene's) and the rates
        ``file_targets`` store (path, fps); each force log refused where its times are not at
        that rate or its tool is none of the scene's (read from its builder: no kernel runs)."""
        fps = spec.get("fps")
        # Frame k of the fit is compared with each target's frame k: a target of another rate was
        # fitted at other times than it was recorded (and --fps 0.001 planned millions of steps).
        # A run's USD and an .npz store their rate; a force log's is implied by its time column.
        stored = [(checks.shown_path(t.path, False), t.fps) for t in file_targets if t.fps is not None and t.kind != "forces"]
        if fps is not None:
            fps = checks.positive(f"{where}{flag}", fps)
            for path, rate in stored:
                if not math.isclose(fps, rate, rel_tol=1e-9):
                    raise ValueError(f"{where}{flag} = {checks.shorten(fps)!r} is not allowed: the target {checks.shown_path(path, False)} was recorded at {rate:g} fps; "
                                     f"leave {flag} out or give {rate:g}")
        rate = fps if fps is not None else next((r for _, r in stored), scene.fps)
        for path, other in stored:
            if not math.isclose(other, rate, rel_tol=1e-9):
                # The first target's rate was taken for all: this one was fitted at other times.
                raise ValueError(f"{where}target {checks.shown_path(path, False)} is not allowed beside the target {stored[0][0]}: it was recorded at "
                                 f"{other:g} fps, the other at {rate:g} fps, and frame k of the fit is one time for both; "
                                 "fit targets of another rate as an experiment of their own (--experiments)")
        for t in file_targets:
            # The reader's own criterion (each row at frame / fps within a tenth of a frame): a float32
            # run's log writes 9 digits of time, which miss the rate by 1e-9 to 1e-8 relative.
            if t.kind == "forces" and t.fps is not None and any(abs(r["time"] * rate - r["frame"]) > 0.1 for r in t.data):
                # The rate is frame / time: a log timed in milliseconds implied 0.03 fps for a
                # 30 fps scene, and the fit planned 33 s frames of 16,000 steps each, exit 0.
                last = max(t.data, key=lambda r: r["frame"])
                implied = f"its column 'time' implies {t.fps:g} fps (frame {last['frame']} at time = {last['time']:g})"
                units = ("times are seconds, frame / fps (a log timed in milliseconds implies 1000 times fewer frames a "
                         "second)")
                if fps is not None:
                    raise ValueError(f"{where}{flag} = {checks.shorten(fps)!r} is not allowed: the force log {checks.shown_path(t.path, False)} says otherwise: "
                                     f"{implied}; {units}")
                if stored:
                    raise ValueError(f"{where}target {checks.shown_path(t.path, False)} is not allowed: {implied}, not the {rate:g} fps the target "
                                     f"{stored[0][0]} was recorded at; {units}")
                raise ValueError(f"{where}target {checks.shown_path(t.path, False)} is not allowed: {implied}, not the scene's {rate:g} fps; {units}; "
                                 f"if the log was recorded at {t.fps:g} fps, give {flag} {t.fps:g}")
        from .sim.integrate import static_collider_names  # noqa: PLC0415
        from .tools import tool_names  # noqa: PLC0415

        for t in file_targets:
            if t.kind == "forces":  # a log of a tool the scene has not: the loss's refusal, before the model
                t.check_tool(tool_names(scene.builder.tools, scene.builder.pins), static_collider_names(scene.builder))
        return rate, stored

    # A target whose frames are chosen is read first: the choice is refused before the scene's
    # checks launch their kernels (a range past the frames an .npz stores was found after them).
    # A file given more than once is read too, its frames compared before the scene's; and a
    # CSV (a force log, or one read as a force log without its header): its refusals came after
    # the scenes of the experiments before it had launched their kernels.
    early = read_targets if read_targets is not None else {
        k: read(path, fspecs[k]) for k, path in enumerate(targets)
        if not cameras and (fspecs[k] is not None or k in repeated or real[k] in shared
                            or os.path.splitext(str(path))[1].lower() == ".csv") and os.path.isfile(path)}
    from .scenes import load_scaled_scene, refuse_unresolved  # noqa: PLC0415

    if targets_only:
        known = {k: _chosen_frames(t, fspecs[k], f"{where}{key('target_frames')}") for k, t in early.items()}
        _refuse_repeated_frames([(k, path, fspecs[k], known[k]) for k, path in enumerate(targets) if k in early and k in repeated],
                                where, key)
        observed = [(targets[k], (real[k], _bodies_observed(t), t.tool), known[k]) for k, t in early.items()]
        if any(t.kind == "forces" for t in early.values()):
            # The rate a force log is held to may be another target's (scene_only, below).
            early.update((k, read(path, fspecs[k])) for k, path in enumerate(targets) if k not in early)
        return early, observed
    if scene_only:
        if not any(t.kind == "forces" for t in early.values()):
            return None
        # A force log's rate and tool are the scene's to judge: its file is read here, with no
        # kernel, so that an experiment's log is refused before the experiments before it build
        # their models (a frame-rate problem in the second was found after the first's kernels).
        scene = load_scaled_scene(spec["scene"], scale, scale_name, resolution=False)
        held_to_scene([early[k] for k in range(len(targets))], scene)
        return scene

    # Read without the check of its resolution, which launches kernels: the targets are read
    # and held to the scene's rate first, so that a bad one (a force log's NaN row, its times
    # in milliseconds) is refused before any kernel runs, as a bad option is.
    scene = read_scene if read_scene is not None else load_scaled_scene(spec["scene"], scale, scale_name, resolution=False)
    # The solver's options checked as options, before the targets are read; set on the builder
    # after the resolution check, which reads the scene as its file sets it.
    from .cli import _apply_solver_options, _solver_options  # noqa: PLC0415

    solver_options = _solver_options(args)  # --solver-fit / --contact over the scene's [solver]
    support = None  # --support-radius, checked against the scene's floors
    if _arg(args, "support_radius") is not None:
        from .builder import SUPPORT_RANGE  # noqa: PLC0415

        k = checks.in_range("--support-radius", args.support_radius, *SUPPORT_RANGE)
        thin = scene.builder.thin_floor(k * scene.builder.spacing)
        if thin is not None:
            raise ValueError(f"--support-radius = {k:g} is not allowed for {spec['scene']} {thin}; give the scene file's "
                             f"floor_layers, or its support_radius in place of --support-radius")
        support = k * scene.builder.spacing

    loaded = []
    any_usd = False
    numbered = set()  # targets without frame numbers of their own that --target-frames numbered
    for k, path in enumerate(targets):
        fspec = fspecs[k]
        if cameras:
            from .silhouette import read_silhouette_masks  # noqa: PLC0415

            # Read now: the masks' frames extend the run as other targets' do (a mask beyond the
            # scene's frames was refused as beyond '--frames', which was not given).
            loaded.append(("silhouette", path, read_silhouette_masks(cameras, path, fspec)))
            continue
        ext = os.path.splitext(str(path))[1].lower()
        usd = ext in (".usd", ".usda", ".usdc")
        usd_spec = fspec if usd else None
        t = early[k] if k in early else read(path, fspec)
        any_usd = any_usd or usd
        if fspec is not None and usd_spec is None and not t.frames_stored:  # (a stored frames' choice is read's)
            chosen = _numbered_frames(fspec, f"{where}{key('target_frames')}")
            if t.kind != "positions":
                seen = set()
                twice = next((f for f in chosen if f in seen or seen.add(f)), None)
                if twice is not None:
                    # A force log's or a cloud's loss keys its frames: '2,2' was observed once
                    # while fit.json recorded [2, 2], where every other target refuses it.
                    raise ValueError(f"{where}{key('target_frames')} = {checks.shorten(fspec)!r} is not allowed: it names frame {twice} twice; "
                                     "name each frame once")
            _refuse_frames_not_logged(t, chosen, fspec, f"{where}{key('target_frames')}")
            t.frames = chosen
            numbered.add(id(t))
            if t.kind == "positions" and len(t.frames) != np.asarray(t.data).shape[0]:
                raise ValueError(f"{where}{key('target_frames')} = {fspec!r} names {len(t.frames)} frames, the target {checks.shown_path(path, False)} "
                                 f"holds {np.asarray(t.data).shape[0]} (one frame number per entry, in order)")
            if t.kind == "positions" and len(set(t.frames)) != len(t.frames):
                # Two entries named as one frame: the later one silently replaced the earlier.
                raise ValueError(f"{where}{key('target_frames')} = {checks.shorten(fspec)!r} is not allowed: it names a frame twice, and "
                                 f"each entry of the target {checks.shown_path(path, False)} is one frame")
        loaded.append(("file", path, t))
    file_targets = [t for kind, _, t in loaded if kind == "file"]
    fps, stored = held_to_scene(file_targets, scene)
    # At scale 1 too: an under-resolved scene file's refusal names the scale that resolves it as the command's option.
    refuse_unresolved(scene, spec["scene"], scale, scale_name)
    _apply_solver_options(scene.builder, solver_options)
    if support is not None:
        scene.builder.support_radius = support
    model = scene.builder.finalize(device=args.device, dtype=dtype, requires_grad=True)
    jitter_model(model, jitter, _arg(args, "seed", 5))

    dt = spec.get("dt")
    given = {"fps": spec.get("fps") is not None, "dt": dt is not None}
    # An experiment's keys are named as written in its file, the command's as its options.
    from .simulate import STABLE_FIELD_ADVICE, STABLE_HOURGLASS_ADVICE, STABLE_REPULSION_ADVICE, StepRefusal  # noqa: PLC0415

    try:
        substeps, dt = resolve_timestep(model, fps, dt=dt if dt is not None else scene.dt,
                                        flag=lambda name: (name if where else f"--{name}") if given.get(name) else name,
                                        limit=spec.get("step_limit"))
    except StepRefusal as e:
        # Its advice is Python's ('give dt= or substeps='): the command has --dt, an experiment its
        # dt; and a rate the targets recorded is no choice.
        higher = "" if stored else (" a higher fps in the experiment," if where else " a higher --fps,")
        # Where the hourglass control's limit sets the step, its strength (--hourglass, or the
        # scene's [solver] hourglass) is what lengthens it, not a softer material.
        cure = ("a smaller --hourglass (or the scene's [solver] hourglass)" if e.advice == STABLE_HOURGLASS_ADVICE else
                "a weaker compression field" if e.advice == STABLE_FIELD_ADVICE else
                "a smaller pair_repulsion or pressure_stiffness" if e.advice == STABLE_REPULSION_ADVICE else "softer materials")
        raise ValueError(f"{where}{e.reason}: use {cure}, a larger spacing,{higher} or give "
                         f"{'its dt' if where else '--dt'}") from None
    except ValueError as e:
        if (not given["dt"] and scene.dt is not None and not (given["fps"] or stored) and str(e).startswith("dt = ")
                and str(spec["scene"]).lower().endswith(".toml")):
            # The scene file's own dt at its own rate: named as a bare 'dt', typed nowhere, where
            # 'warp-esph run' names the file and its table.
            raise ValueError(f"{where}{checks.shown_path(spec['scene'], False)}: [scene] {e}") from None
        if given["dt"] or scene.dt is None or "whole number of steps" not in str(e) or not (given["fps"] or stored):
            raise
        # The scene's own step (a figure's) at a rate the fit set: resolve_timestep named a bare
        # 'dt' that was typed nowhere and advised leaving it out, which a built-in scene's cannot be.
        from .simulate import scene_dt_refusal  # noqa: PLC0415

        set_by = (f"{where}{flag} = {fps:g}" if given["fps"] else f"the {fps:g} fps the target {stored[0][0]} was recorded at")
        raise scene_dt_refusal(f"{where}the scene's dt", scene.dt, fps, set_by, "its dt" if where else "--dt",
                               other_rates=given["fps"]) from None
    shown = [f for t in file_targets for f in (t.frames or [])]
    shown += [f for kind, _, t in loaded if kind == "silhouette" for f in t[2] if f is not None]
    for t in file_targets:
        # Before the frames: a file of the wrong size is refused for that, whatever it holds.
        t.check_particle_count(model)
    if spec.get("frames") is None and shown and max(shown) < 1:
        # It blamed --frames, which was not given.
        raise ValueError(f"{where}{key('target_frames')} = {checks.shorten(tframes[0] if tframes else 0)!r} is not allowed: the targets hold "
                         "only frame 0, the initial state, which says nothing about the material")
    frames = spec.get("frames")
    if frames is None and shown and max(shown) > checks.MAX_INT:
        # It was refused as '--frames = 1000000000000', which was not given (a foreign USD's time code).
        raise ValueError(f"{where}the targets' last frame, {max(shown)}, is not allowed: the fit runs to it, and a run has at "
                         f"most {checks.MAX_INT} frames (a target's frames are rendered frame indices)")
    frames = checks.positive_int(f"{where}{key('frames')}", frames if frames is not None else (max(shown) if shown else scene.frames))
    # What set the rollout's length, as its refusals name it.
    source = (f"{where}{key('frames')} = {frames}" if spec.get("frames") is not None else
              f"the targets' last frame, {frames}," if shown else f"the scene's frames = {frames}")
    if frames * substeps > checks.MAX_INT:  # a rollout's step count (Rollout's steps), named by what set it
        raise ValueError(f"{source} is not allowed: at {substeps} steps a frame the fit's rollout would "
                         f"take {frames * substeps} steps, more than {checks.MAX_INT}")
    _check_fit_start(spec, scene, model, frames, fps, dt, where)

    # The experiment's own force noise, else the command's (as --noise reaches every experiment).
    force_noise = spec.get("force_noise")
    force_noise = checks.noise(f"{where}{key('force_noise')}", force_noise) if force_noise is not None else (
        _arg(args, "force_noise") if where else None)
    # The frames a target without a choice shows (a cloud's, a mesh's: the last) are known
    # only now.
    _refuse_repeated_frames([(k, path, fspecs[k], t.frames if t.frames is not None else [frames])
                             for k, (kind, path, t) in enumerate(loaded) if kind == "file" and k in repeated], where, key)
    loss = None
    zero_readings: list[str] = []
    for k, (kind, path, t) in enumerate(loaded):
        coverage = coverages[k] if len(coverages) > 1 else coverages[0] if coverages else "full"
        if coverage != "full" and not (kind == "file" and (t.kind == "points" or t._read_as_cloud(model))):
            if len(coverages) > 1:
                from .fit import _partial_refused  # noqa: PLC0415

                raise ValueError(f"{where}{coverage_name} #{k + 1} = {checks.shorten(coverage)!r} is not allowed: "
                                 f"{_partial_refused(path, 'silhouettes' if kind == 'silhouette' else t.kind)}")
            coverage = "full"  # given once for all targets: the point clouds' alone
        if kind == "silhouette":
            from .silhouette import silhouette_target  # noqa: PLC0415

            source = (key("frames") if spec.get("frames") is not None else
                      "the targets' last frame" if shown else "the scene's frames")
            from .fit import unpinned_particles  # noqa: PLC0415

            # A camera's mask shows the sample, not a particle floor's pinned particles under it,
            # which had been drawn into the silhouette as a slab the masks leave empty. Other pinned
            # particles are drawn: a clamp's hold the sample's end, which the masks show (left out,
            # a clamped beam's loss at the truth read 0.103, not 0.026, its gradient 16 times it).
            term = silhouette_target(t, frames, substeps, source, camera_file=cameras,
                                     particles=unpinned_particles(model, floors=True))
        else:
            if t.frames is None:
                t.frames = [frames]
            if max(t.frames) > frames:
                raise ValueError(f"{where}the target {checks.shown_path(path, False)} has frame {max(t.frames)}, beyond {key('frames')} = {frames}: "
                                 f"give {key('frames')} {max(t.frames)} or more, or choose target frames up to {frames} "
                                 f"with {key('target_frames')}")
            frame_steps = {f: f * substeps for f in t.frames if f > 0 or t.kind not in ("positions", "forces")}
            offset = _arg(args, "cloud_offset") or 0.0
            if offset == "surface":
                offset = 0.5 * model.spacing
            term = t.loss(model, frame_steps, radius=args.radius, mode=_arg(args, "mesh_mode") or "surface",
                          coverage=coverage, surface_offset=offset,
                          force_noise=force_noise, force_components=_arg(args, "force_components") or "xyz")
            if t.kind == "forces":
                zeros = _zero_force_columns(path, term, _arg(args, "force_components") is not None)
                if zeros:
                    zero_readings.append(zeros)
        loss = term if loss is None else loss + term
    readings = [_frame_reading(path, t, id(t) in numbered, model)
                for kind, path, t in loaded if kind == "file" and t.kind == "positions" and not t.frames_stored
                and os.path.splitext(str(path))[1].lower() not in (".usd", ".usda", ".usdc")]
    readings += [said for kind, path, t in loaded if kind == "file" and t.kind == "positions" and t.frames_stored
                 and (said := _start_frame_later(path, t, model, _scene_run(model, substeps, dt)))]
    readings += zero_readings
    long_run = _long_rollout_reading(scene, frames, fps, substeps, dt, stored, f"{where}{flag}" if given["fps"] else None,
                                     source)
    if long_run:
        readings.append(long_run)
    materials = spec.get("material")
    if materials:
        materials = [int(m) if str(m).isdigit() else m for m in materials]
        # A scene file's material by its name, as the file names it (a body's name first).
        materials = [k if isinstance(m, str) and (k := scene.material_index(m)) is not None else m for m in materials]
        from .fit import _material_indices  # noqa: PLC0415

        try:  # refused here, by experiment, not later without its name
            # An experiment's key is named as written in its file, the command's as its option.
            _material_indices(model, materials, what="material" if where else "--material",
                              material_names=scene.material_names)
        except ValueError as e:
            raise ValueError(f"{where}{e}") from None
    kinds = ", ".join(sorted({("silhouettes" if kind == "silhouette" else t.kind) for kind, _, t in loaded}))
    # Options of a kind of target none of these is: refused, not ignored.
    file_kinds = {t.kind for kind, _, t in loaded if kind == "file"}
    if _arg(args, "radius") is not None and "points" not in file_kinds:
        raise ValueError(f"{where}--radius = {checks.shorten(args.radius)!r} is not allowed: it is the search radius of point-cloud "
                         f"targets, and the targets are {kinds}")
    if _arg(args, "mesh_mode") is not None and "mesh" not in file_kinds:
        raise ValueError(f"{where}--mesh-mode = {checks.shorten(args.mesh_mode)!r} is not allowed: it is how mesh targets are compared, "
                         f"and the targets are {kinds}")
    if coverages and "points" not in file_kinds:
        said = coverages[0] if len(coverages) == 1 else coverages
        raise ValueError(f"{where}{coverage_name} = {checks.shorten(said)!r} is not allowed: it is how much of the body "
                         f"point-cloud targets show, and the targets are {kinds}")
    if _arg(args, "cloud_offset") is not None and "points" not in file_kinds:
        raise ValueError(f"{where}--cloud-offset = {checks.shorten(args.cloud_offset)!r} is not allowed: it is how far outside the "
                         f"particles' centres point-cloud targets lie, and the targets are {kinds}")
    if spec.get("target_body") is not None and not any_usd:
        raise ValueError(f"{where}{key('target_body')} = {checks.shorten(spec['target_body'])!r} is not allowed: it picks a body of a run's USD "
                         f"target, and the targets are {kinds}")
    if spec.get("target_tool") is not None and "forces" not in file_kinds:
        raise ValueError(f"{where}{key('target_tool')} = {checks.shorten(spec['target_tool'])!r} is not allowed: it picks the tool of a "
                         f"force-curve target (<output>_tools.csv), and the targets are {kinds}")
    if where and spec.get("force_noise") is not None and "forces" not in file_kinds:
        raise ValueError(f"{where}force_noise = {checks.shorten(spec['force_noise'])!r} is not allowed: it is the noise of force-log "
                         f"targets (N), and the targets are {kinds}")
    geometric = bool(file_kinds & {"positions", "points", "mesh"})
    noise = spec.get("noise")
    if where and noise is not None and not geometric:
        raise ValueError(f"{where}noise = {checks.shorten(noise)!r} is not allowed: it is the noise of position, point-cloud and mesh "
                         f"targets (m), and the targets are {kinds}"
                         + ("; give a force log's noise in newtons as force_noise" if "forces" in file_kinds else ""))
    return types.SimpleNamespace(scene=scene, model=model, loss=loss, frames=frames, fps=fps, dt=dt, substeps=substeps,
                                 auto_step=spec.get("dt") is None and scene.dt is None,
                                 frames_source=source[len(where):],
                                 materials=materials, kinds=kinds, targets=targets, scale=scale,
                                 readings=readings, target_frames=[None if kind == "silhouette" else list(t.frames)
                                                                   for kind, _, t in loaded],
                                 # What each target observes: the file, its bodies (a run's USD read whole
                                 # observes every body of it) and its tool.
                                 observed=[None if kind == "silhouette" else (checks.file_identity(path), _bodies_observed(t),
                                                                              t.tool)
                                           for kind, path, t in loaded],
                                 weight=checks.positive(f"{where}weight", spec.get("weight", 1.0)),
                                 geometric=geometric, forces="forces" in file_kinds, force_noise=force_noise,
                                 noise=None if noise is None else checks.noise(f"{where}noise", noise))


def _memory_refusal(e, exp, where: str, ck) -> str:
    """``warp-esph fit``'s refusal of an experiment's rollout that would not fit in memory
    (``rollout.RolloutMemoryError``), in the command's words: the fit's refusal named
    ``steps`` and ``checkpoint_every``, no options of the command, and gave the segment
    ``--checkpoint-every auto`` had chosen as if it had been typed."""
    fewer = "fit fewer frames (" + ("the experiment's frames, target_frames)" if where else "--frames, --target-frames)")
    if not e.taped:
        # A Gauss-Newton fit's rollout, which records no tape (--checkpoint-every N is refused with it).
        return (f"{where}{exp.frames_source} is not allowed with --optimizer gauss-newton on {e.device}: at "
                f"{exp.substeps} steps a frame (dt = {exp.dt:.4g} s at {exp.fps:g} fps) the fit's rollout takes {e.steps} "
                f"steps, and even untaped (as every run of a Gauss-Newton fit is) {e.reason}; {fewer}")
    if ck == "auto":
        said, fix = f"even at its least memory, a checkpoint every {e.least} steps, ", fewer
    elif e.least_fits:
        said, fix = "", (f"give --checkpoint-every auto (the default: it chooses a segment that fits) or {e.least} (the "
                         f"least memory, about {e.least_gib:.3g} GiB), or {fewer}")
    elif e.segment == e.least:
        said, fix = "", fewer
    else:
        said, fix = "", f"{fewer} (with --checkpoint-every {e.least}, the least, it would need about {e.least_gib:.3g} GiB)"
    copies = f" and --worlds ({e.worlds} copies of the scene)" if e.worlds else ""
    fix += ", or fewer --starts, or leave out --worlds (the starts one after another)" if e.worlds else ""
    return (f"{where}{exp.frames_source} is not allowed with --checkpoint-every {ck}{copies} on {e.device}: at "
            f"{exp.substeps} steps a frame (dt = {exp.dt:.4g} s at {exp.fps:g} fps) the fit's rollout takes {e.steps} "
            f"steps, and {said}{e.reason}; {fix}")


def _check_fit_start(spec, scene, model, frames, fps, dt, where) -> None:
    """Refuse, before the fit, a start or a tool faster than a spacing a step, as ``warp-esph
    run`` does (``simulate._check_run_start``): the rollouts took them, a tool at 50 spacings a
    step was fitted to, and fitted.usdc's run refused it after the fit with a Python caller's
    'a smaller dt='. The advice names the command's --dt, or an experiment's dt."""
    from .simulate import START_ADVICE, StepRefusal, _check_run_start  # noqa: PLC0415
    from .tools import TOO_FAST_ADVICE  # noqa: PLC0415

    try:
        _check_run_start(model, model.state(requires_grad=False), frames, fps, dt)
    except StepRefusal as e:
        step = "dt in the experiment" if where else "--dt"
        advice = {START_ADVICE: f"; give a smaller velocity (or angular_velocity) or a smaller {step}",
                  TOO_FAST_ADVICE: f"; give a slower motion or a smaller {step}"}.get(e.advice, "")
        table = ""
        if str(spec["scene"]).lower().endswith(".toml"):
            if e.reason.startswith("initial velocity"):
                table = f"{scene.builder.origins.get(('body', getattr(e, 'body_index', None)), '[[bodies]]')}: "
            table = f"{checks.shown_path(spec['scene'], False)}: {table}"
        raise ValueError(f"{where}{table}{e.reason}{advice}") from None


def _frame_reading(path, t, numbered: bool, model) -> str:
    """The plan's line on which frames a positions target without frame numbers of its own
    (an ``.npy``, an ``.npz`` without ``frames``) is read as. Such a file that starts at frame
    1 was read one frame early, silently: its first entry as frame 0, which is not fitted, and
    every later entry one frame before its time. The entry read as frame 0 is set beside the
    scene's initial positions, which it should be, so that such a shift shows."""
    entries = np.asarray(t.data).shape[0]
    what = "a .npy" if str(path).lower().endswith(".npy") else "an .npz without 'frames'"
    if numbered:
        return (f"target {checks.shown_path(path, False)}: {what} holds no frame numbers; its {entries} entries are read as frames "
                f"{', '.join(map(str, t.frames))} (--target-frames)")
    if entries == 1 and t.frames and len(t.frames) == 1 and t.frames[0] != 0:
        return f"target {checks.shown_path(path, False)}: {what} holds no frame numbers; its one frame of positions is read as the run's last frame, {t.frames[0]}"
    line = (f"target {checks.shown_path(path, False)}: {what} holds no frame numbers; its {entries} entries are read as frames 0 to {entries - 1}, "
            "entry 0 as frame 0, the initial state, which is not fitted")
    first = np.asarray(t.data)[0]
    x0 = np.asarray(model.particle_x0, dtype=np.float64)
    seen = np.isfinite(first).all(axis=1) if first.ndim == 2 else None
    if first.shape == x0.shape and seen.any():
        # Over the markers entry 0 observes (NaN: missing; the mean of all read 'nan spacings').
        rms = float(np.sqrt(np.mean(np.sum((first[seen] - x0[seen]) ** 2, axis=1))))
        line += f" (it lies {rms / model.spacing:.3g} spacings RMS from the scene's initial positions)"
    return line + f"; if they are other frames, name them with --target-frames (e.g. 1:{entries} for frames 1 to {entries})"


def _lab_values(result) -> str | None:
    """The fitted yield stress and flow rate as a lab gives them (a rheometer's shear yield
    stress, a compression test's uniaxial one, the plastic viscosity: ``Material``'s
    properties), one value per fitted material; None where neither is fitted or a fitted
    material is no Bingham fluid (the properties refuse it)."""
    materials = [result.materials[k] for k in result.material_indices]
    # mu fitted with the flow rate held moves the plastic viscosity (mu / flow_rate) with it: a
    # scene's plastic_viscosity = 5 Pa s (a rheometer's) ended as 2.37 Pa s, and nothing said so.
    moved = "mu" in result.params and "flow_rate" not in result.params and all(m.plastic for m in materials)
    names = (["shear_yield_stress", "uniaxial_yield_stress"] if "yield_stress" in result.params else []) + (
        ["plastic_viscosity"] if "flow_rate" in result.params or moved else [])
    try:
        said = [f"{name} = {', '.join(f'{getattr(m, name):.6g}' for m in materials)} {'Pa s' if 'visc' in name else 'Pa'}"
                for name in names]
    except ValueError:
        return None
    if moved:
        said[-1] += " (mu / flow_rate, the flow rate held: it moved with the fitted mu)"
    return ", ".join(said) or None


def _zero_force_columns(path, term, chosen: bool) -> str | None:
    """The plan's line where a fitted column of a force log is 0 in every frame fitted (every
    column: no contact was measured), and another is not: a zero is fitted as a measured force (the model's force along that axis held
    to 0), and the diagnostics count each as an observation, which lowers the noise they
    estimate where the model's force there is ~0 anyway (a symmetric press). Said, not dropped:
    a measured zero does inform where the model pushes sideways; a load cell that writes 0 for
    axes it does not measure is fitted along its axis with --force-components."""
    t = np.asarray(term.targets)
    zero = [c for j, c in enumerate(term.components) if not np.any(t[:, j])]
    if zero and len(zero) == len(term.components):
        # A plate that never touched the sample: the fit stopped on a zero gradient and blamed
        # the material ("no particle reaches the yield stress").
        return (f"target {checks.shown_path(path, False)}: the force on {term.tool!r} is 0 in every frame fitted: the log holds no contact, which "
                "the model matches only where its tool touches nothing either (no gradient: the fit stops at once); check "
                "that the scene's tool reaches the sample in the frames measured and that --target-tool names the tool "
                "the log measured")
    if not zero:
        return None
    kept = "".join(c for c in term.components if c not in zero)
    names = ", ".join(f"f{c}" for c in zero)
    line = (f"target {checks.shown_path(path, False)}: {names} {'is' if len(zero) == 1 else 'are'} 0 in every frame fitted: fitted as measured "
            f"zeros, the model's force along {'that axis' if len(zero) == 1 else 'those axes'} held to 0, and counted "
            "as observations by the diagnostics")
    if chosen:
        return line + " (--force-components names them)"
    return line + f"; if the log does not measure {'it' if len(zero) == 1 else 'them'}, give --force-components {kept}"


#: An evaluation simulating this many times the scene's own duration (its frames at its fps)
#: or more is warned of in the plan (_long_rollout_reading).
LONG_ROLLOUT_FACTOR = 10.0


def _long_rollout_reading(scene, frames, fps, substeps, dt, stored, fps_flag, source) -> str | None:
    """A warning where each evaluation simulates ``LONG_ROLLOUT_FACTOR`` times the scene's own
    duration or more, naming the rate and where it was read. An ``.npz`` storing a frame
    interval as its ``fps`` (0.03 for 33 fps) planned 99966 steps an evaluation, about 6
    minutes each, said only as a step count in the plan. A low rate can be a real one (a slow
    creep filmed once a minute), so it is said, not refused."""
    seconds, own = frames / fps, scene.frames / scene.fps
    if not (own > 0 and seconds >= LONG_ROLLOUT_FACTOR * own):
        return None
    line = (f"warning: each evaluation runs {frames * substeps} steps, {seconds:.4g} s simulated ({frames} frames at "
            f"{fps:g} fps), {seconds / own:.3g} times the scene's own {scene.frames} frames at {scene.fps:g} fps "
            f"({own:.4g} s, {math.ceil(own / dt - 1e-9)} steps at this dt)")
    if fps >= 1.0:
        # A rate of a frame a second or more is no frame interval written as a rate (that would
        # be a camera at 1 fps or slower): the target is long, and its frames set the length.
        return f"{line}: the target's last frame, {frames}, sets its length"
    interval = (f"if {fps:g} is a frame interval (seconds per frame), the rate is {1.0 / fps:.4g} fps")
    if fps_flag is not None:
        return f"{line}: {fps_flag} = {fps:g}; {interval}: give {fps_flag} {1.0 / fps:.4g}"
    if stored:
        return (f"{line}: the rate {fps:g} fps was read from the target {stored[0][0]}; {interval}: store "
                f"fps = {1.0 / fps:.4g} in the file")
    return f"{line}: {source} sets its length"


#: A stored frame after 0 this close to the scene's start (RMS, in spacings), where the data
#: move at least 1 / START_MOTION_SHARE times as far and the next stored frame is already
#: farther than this, is said to hold the start (_start_frame_later).
START_TOLERANCE = 0.05
START_MOTION_SHARE = 0.05
#: How far (RMS, in spacings) the scene's own run must have moved from its start by a stored
#: frame that holds the start for that frame to be said late (_start_frame_later): a spacing,
#: twice what a lattice settling onto its ground moves (a box a half spacing above it settles
#: 0.53 spacings and stops), a free fall's second frame at 30 fps.
SCENE_MOTION = 1.0


def _scene_run(model, substeps: int, dt: float):
    """The scene's own run as ``_start_frame_later`` reads it: a function of one frame number
    returning the model's positions there (its current values; untaped, so a model without
    gradients runs too), or None where the run does not run to finite positions (it tells
    nothing then)."""

    def run(frame: int):
        from .sim.solver import Solver  # noqa: PLC0415

        solver = Solver(model)
        current, spare = model.state(requires_grad=False), model.state(requires_grad=False)
        try:
            with solver.caller_checks():  # the caller reads the state back (None where it failed)
                for _ in range(int(frame) * substeps):
                    solver.step(current, spare, dt)
                    current, spare = spare, current
        except (ValueError, ArithmeticError, RuntimeError):  # a refused step, a neighbour overflow
            return None
        x = current.x.numpy().astype(np.float64)
        return x if np.isfinite(x).all() else None

    return run


def _start_frame_later(path, t, model, run=None) -> str | None:
    """A warning where an ``.npz``'s earliest stored frame is after 0 and holds the scene's
    initial positions (a camera's frame counter, which starts where it was switched on): each
    entry is fitted at its stored frame's time, so the whole motion was fitted that many
    frames late, and the diagnostics could only say the residuals were large.

    Said from the data alone where the motion starts at that frame, the next stored frame
    already off the start. Where the data hold the start over several stored frames, or the
    file stores that one frame alone, they can be late or a body resting until something
    reaches it (a press): the scene's own run (``run``, ``_scene_run``; None: not judged)
    tells them apart, the data said late where it has moved ``SCENE_MOTION`` spacings from
    its start by the last stored frame that holds it. A body falling from frame 0, recorded
    at rest over stored frames 3 to 5, had been told nothing, as had a lone frame 5 at rest.
    A stored frame off the start is not judged: its frame and the material trade off."""
    order = np.argsort(np.asarray(t.frames), kind="stable")
    first, start = int(t.frames[order[0]]), np.asarray(model.particle_x0, dtype=np.float64)
    data = np.asarray(t.data, dtype=np.float64)
    if first == 0 or data.shape[1:] != start.shape:
        return None

    def rms(x, seen=None):
        seen = np.isfinite(x).all(axis=1) if seen is None else seen
        return float(np.sqrt(np.mean(np.sum((x[seen] - start[seen]) ** 2, axis=1)))) / model.spacing if seen.any() else None

    away = [rms(data[k]) for k in order]  # in frame order
    near, moved = away[0], max((r for r in away if r is not None), default=None)
    if near is None or near > START_TOLERANCE:
        return None
    following = next((r for r in away[1:] if r is not None), None)
    if following is not None and near <= START_MOTION_SHARE * moved and following > START_TOLERANCE:
        return (f"warning: target {checks.shown_path(path, False)}: its first stored frame, {first}, lies {near:.3g} spacings RMS from the "
                f"scene's initial positions (the data move up to {moved:.3g} spacings from them): it holds the start, "
                f"which is frame 0; each entry is fitted at its stored frame / fps, {first} frames late if the frames "
                "count from another start (a camera's frame counter): renumber them from 0 at the start")
    # The stored frames that hold the start, from the first: a rest the scene's run judges.
    held = 0
    while held < len(order) and (away[held] is None or away[held] <= START_TOLERANCE):
        held += 1
    kept = max(k for k in range(held) if away[k] is not None)  # the last of them that observes a marker
    last = int(t.frames[order[kept]])
    x = None if run is None else run(last)
    if x is None:
        return None
    seen = np.isfinite(data[order[kept]]).all(axis=1)
    scene = rms(x, seen)
    if scene is None or scene < SCENE_MOTION:
        return None
    stored = f"its one stored frame, {first}," if len(order) == 1 else (
        f"its first stored frame, {first}," if held == 1 else f"its stored frames {first} to {last}")
    return (f"warning: target {checks.shown_path(path, False)}: {stored} {'lies' if held == 1 else 'lie'} within {START_TOLERANCE:g} spacings RMS "
            f"of the scene's initial positions, where the scene's own run (its values now) has moved {scene:.3g} "
            f"spacings RMS from them by frame {last}: the data hold the start, frame 0, after the scene has left it; "
            "each entry is fitted at its stored frame / fps, late if the frames count from another start (a camera's "
            "frame counter): renumber them from 0 at the start, or start the scene as the data do")


def write_outputs(result, folder, meta: dict | None = None, json_path: str | None = None,
                  written: list | None = None) -> list[str]:
    """Write ``fit.json`` (or ``json_path``), ``history.csv``, ``loss.png`` and ``params.png``
    into ``folder`` (created), each whole or not at all; returns the paths written, appended
    to ``written`` (when given) as each is done, so a caller told of a failed write knows
    which came before."""
    written = [] if written is None else written
    os.makedirs(folder, exist_ok=True)
    json_path = json_path or os.path.join(folder, "fit.json")
    doc = {**(meta or {}), **result.to_dict()}
    # Each file whole or not at all (as every file here): a full disk or a second Ctrl-C left
    # fit.json.tmp beside it, and an empty or cut history.csv, loss.png or params.png.
    with checks.replaced_atomically(json_path) as part, open(part, "w") as f:
        json.dump(doc, f, indent=2)
    written.append(json_path)
    names = list(result.params)
    k = len(next(iter(result.params.values())))
    cols = [n if k == 1 else f"{n}[{j}]" for n in names for j in range(k)]
    csv_path = os.path.join(folder, "history.csv")
    with checks.replaced_atomically(csv_path) as part, open(part, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["evaluation", "stage", "loss", *cols, "seconds"])
        for h in result.history:
            vals = [x for n in names for x in h["params"][n]]
            w.writerow([h["iteration"], h.get("stage", "descent"), repr(h["loss"]), *[repr(v) for v in vals], f"{h['seconds']:.4f}"])
    written.append(csv_path)
    _plots(result, folder, names, cols, written)
    return written


def _save_figure(plt, fig, path: str) -> None:
    """Write ``fig`` to ``path`` whole or not at all (a full disk leaves no empty picture),
    and close it either way."""
    try:
        with checks.replaced_atomically(path) as part:
            fig.savefig(part, dpi=100, format="png")
    finally:
        plt.close(fig)


def _plots(result, folder, names, cols, written: list) -> None:
    try:
        import matplotlib  # noqa: PLC0415

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt  # noqa: PLC0415
    except ImportError:
        return
    hist = result.history
    it = [h["iteration"] for h in hist]
    loss = np.array([h["loss"] if h["loss"] is not None and math.isfinite(h["loss"]) else np.nan for h in hist])
    sample = np.array([h.get("stage") == "sample" for h in hist])
    fig, ax = plt.subplots(figsize=(6, 4))
    if sample.any():
        ax.plot(np.array(it)[sample], loss[sample], "o", color="0.6", label="global stage (loss only)")
    ax.plot(np.array(it)[~sample], loss[~sample], ".-", label=f"descent ({result.stopped})")
    if np.any(loss > 0):  # a loss of exactly 0 (a target the guess already matches) has no log scale
        ax.set_yscale("log")
    ax.set_xlabel("evaluation")
    ax.set_ylabel("loss")
    ax.legend()
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    loss_png = os.path.join(folder, "loss.png")
    _save_figure(plt, fig, loss_png)
    written.append(loss_png)
    vals = np.array([[x for n in names for x in h["params"][n]] for h in hist])
    fig, axes = plt.subplots(len(cols), 1, figsize=(6, 2.2 * len(cols)), sharex=True, squeeze=False)
    for j, (ax, col) in enumerate(zip(axes[:, 0], cols)):
        if sample.any():
            ax.plot(np.array(it)[sample], vals[sample, j], "o", color="0.6")
        ax.plot(np.array(it)[~sample], vals[~sample, j], ".-")
        if np.all(vals[:, j] > 0):
            ax.set_yscale("log")
        ax.set_ylabel(col)
        ax.grid(True, which="both", alpha=0.3)
    axes[-1, 0].set_xlabel("evaluation")
    fig.tight_layout()
    params_png = os.path.join(folder, "params.png")
    _save_figure(plt, fig, params_png)
    written.append(params_png)
