"""PyTorch interop: a ``Rollout`` as a ``torch.autograd.Function``.

::

    import torch
    from warp_esph.torch import rollout_positions, RolloutModule

    rollout = Rollout(model, steps=100, dt=1e-3, frames=[50, 100])   # float64 model
    mu = torch.tensor([1e3], dtype=torch.float64, requires_grad=True)
    v0 = torch.zeros(model.particle_count, 3, dtype=torch.float64, requires_grad=True)
    x = rollout_positions(rollout, {"mu": mu}, v0=v0)                # (frames, n, 3)
    loss = ((x - target) ** 2).mean()
    loss.backward()                                                  # mu.grad, v0.grad

Inputs: any of the model's per-material parameter arrays (one value per material, see
``warp_esph.rollout.PARAMETERS``) and the initial positions ``x0`` (``(n, 3)``) and
velocities ``v0`` (``(n, 3)``, or one ``(3,)`` velocity for every particle); inputs left out keep the model's values and get no gradient. Output: the
positions at the rollout's ``frames``. The forward pass sets the model's parameter
arrays to the given values (they keep them afterwards). The backward pass re-runs the
forward pass first when the rollout has been run with other inputs since (as
``torch.autograd.gradcheck`` does) or released (``Rollout.release``), so every output's
gradient is taken at its own inputs (the model's ``particle_x0`` / ``particle_v0``, the
tools' arrays, the rollout's ``dt`` and the model's gravity and contact ramp too, as that forward
read them; the solver's other settings changed since are refused), and leaves the model holding
the parameter values, start, tool arrays and settings it held before. The given tensors must be on one
device (two are refused by name); they are copied to and from the model's device, and the
positions come back on theirs, in their dtype promoted with the model's precision (float64
where no float tensor is given); use a float64 model with float64 tensors for ``gradcheck``. A forward whose run blows up to a non-finite position or velocity raises
``warp_esph.rollout.NonFiniteRollout`` (a ``FloatingPointError``; ``Rollout.forward``'s check),
the model keeping the values it held, instead of returning a tensor of NaN positions; one that
blows up while staying finite (past ``simulate.DivergenceMonitor``'s bounds, or with energy grown
past ``simulate.energy_growth``'s limit, which fails a ``sweep`` sample: the tests ``fit`` fails
its trials on, ``Rollout.bounds_hit``) raises ``warp_esph.rollout.DivergedRollout``, also
a ``FloatingPointError``, instead of positions 1e5 m out taken as a result.

``RolloutModule`` holds chosen parameters as ``torch.nn.Parameter`` in log space (for
positive ones) so ``torch.optim.Adam`` can drive a fit.

Second derivatives (a gradient taken with ``create_graph=True`` and differentiated again,
``torch.autograd.gradgradcheck``, a Hessian) are not supported: the backward is Warp's tape
adjoint, and differentiating through it raises a ``RuntimeError`` saying so
(``SECOND_DERIVATIVES``); the first derivatives such a call takes are right.

PyTorch is imported only when these functions are used; without it they raise an
``ImportError`` that says how to install it.
"""

import dataclasses
import functools
from collections.abc import Mapping

import numpy as np

from . import checks
from .model import Unpicklable
from .rollout import PARAMETERS, TOOL_GRADIENTS, Rollout, check_initial, initial_shapes

__all__ = ["rollout_positions", "RolloutModule", "require_torch"]  # noqa: F822 (RolloutModule: module __getattr__)

#: Why a second derivative through the bridge is refused.
SECOND_DERIVATIVES = ("a second derivative through warp_esph.torch is not supported: the rollout's gradient is Warp's tape "
                      "adjoint, which is not differentiable again (create_graph=True gives first derivatives only; for "
                      "curvature use finite differences of gradients, as warp_esph.diagnostics does)")

_INSTALL = "warp_esph.torch needs PyTorch: pip install torch==2.13.0 (or pip install 'warp-esph[torch]')"


def require_torch():
    """The ``torch`` module, or an ``ImportError`` with install instructions."""
    try:
        import torch  # noqa: PLC0415
    except ImportError as e:  # pragma: no cover - torch is installed in the test environment
        raise ImportError(_INSTALL) from e
    return torch


# Made once, when first asked for (it subclasses torch's Function, and torch loads only
# then): a class, shared as any class is, holding no state of a rollout.
@functools.cache
def _function():
    torch = require_torch()

    class _SecondDerivative(torch.autograd.Function):
        """Stands in the graph of a gradient taken with ``create_graph=True``: the rollout's
        adjoint is Warp's tape, which has no derivative of its own."""

        @staticmethod
        def forward(ctx, value, *inputs):
            return value.clone()

        @staticmethod
        def backward(ctx, *grads):
            raise RuntimeError(SECOND_DERIVATIVES)

    def _first_derivatives_only(backward):
        """``torch.autograd.function.once_differentiable`` with this bridge's reason: a gradient
        taken with ``create_graph=True`` is the rollout's first derivative, and differentiating
        it again raises ``SECOND_DERIVATIVES`` (torch's own said only that the function 'was
        marked with @once_differentiable')."""

        @functools.wraps(backward)
        def wrapper(ctx, *args):
            with torch.no_grad():
                outputs = backward(ctx, *args)
            # The forward's inputs too: a loss linear in the positions hands on an upstream
            # gradient of constants, and with those alone the result carried no graph, so
            # torch.autograd.functional.hessian read it as independent of mu and returned 0.
            graphed = [a for a in (*args, *ctx.graph_inputs) if isinstance(a, torch.Tensor) and a.requires_grad]
            if not (torch.is_grad_enabled() and graphed):
                return outputs
            return tuple(None if o is None else _SecondDerivative.apply(o, *graphed) for o in outputs)

        return wrapper

    def _numpy(t, dtype):
        # Through float64: numpy has no bfloat16, and float16 would round the values first.
        # resolve_neg: numpy() refused a lazily negated view (x.conj().imag) with torch's error.
        return t.detach().to(device="cpu", dtype=torch.float64).resolve_neg().numpy().astype(dtype, copy=True)

    class RolloutFunction(torch.autograd.Function):
        """``(rollout, names, starts, taped, out, x0, v0, *values) -> positions (frames, n, 3)``;
        ``starts``: ``{name: array}`` of ``x0``/``v0`` as ``check_initial`` answered them;
        ``taped``: whether the run is recorded for a backward; ``out``: the output's
        ``(dtype, device)``."""

        @staticmethod
        def forward(ctx, rollout, names, starts, taped, out_as, x0, v0, *values):
            # In float64: the rollout checks the values as given before it casts them to the
            # model's precision (1e39 Pa cast to float32 here was refused as inf, 'not finite').
            given = {name: _numpy(v, np.float64) for name, v in zip(names, values)}
            # One read of the arrays, and writes of the values that change only: the values it
            # held were read again after the writes, and every given value written, changed or not.
            before = rollout.get_parameters()
            ctx.params = rollout._set_parameters(given, before)
            ctx.rollout = rollout
            ctx.names = names
            ctx.starts = starts
            try:
                out = rollout._forward_checked(starts, taped=taped)
                # A finite blow-up too (fit's test of its trials): its loss is no result.
                rollout._check_bounds()
            except BaseException:
                # A forward that fails (a step's refusal) left the model running the new values.
                rollout._set_parameters(before, ctx.params)
                raise
            ctx.forward_count = rollout.forward_count
            ctx.materials = tuple(rollout.model.materials)
            # What a re-run of this forward reads besides the parameters, as it read them: the
            # model's own start (particle_x0 is the rest configuration too, where x0 is given)
            # and the tools' arrays (the rollout's copies of this forward's).
            ctx.model_start = {name: getattr(rollout.model, name).copy() for name in _MODEL_STARTS}
            ctx.tools = rollout._forward_inputs[2]
            # dt, gravity and the solver's settings as this forward ran them (Rollout.run_settings):
            # a re-run after one was set since ran at the new one, the gradient of another run.
            ctx.settings = rollout._forward_inputs[3]
            ctx.scripted = rollout._scripted_poses  # a Scripted motion's poses: a Python callable is no array to put back
            ctx.tensor_dtype, ctx.device = dtype, device = out_as
            # Held (not saved: an in-place change before the backward is no error of this one) for
            # a gradient taken with create_graph=True, which depends on them (_first_derivatives_only).
            ctx.graph_inputs = tuple(t for t in (x0, v0, *values) if isinstance(t, torch.Tensor) and t.requires_grad)
            return torch.from_numpy(out).to(dtype=dtype, device=device)

        @staticmethod
        @_first_derivatives_only
        def backward(ctx, grad_out):
            rollout: Rollout = ctx.rollout
            # What set_parameters cannot put back (a material's force, clamp or plastic model
            # set since): the forward's point cannot be re-run, as Rollout.backward refuses it.
            others = [f"materials[{k}].{field.name}" for k, (a, b) in enumerate(zip(ctx.materials, rollout.model.materials))
                      for field in dataclasses.fields(a) if field.name not in PARAMETERS
                      and getattr(a, field.name) != getattr(b, field.name)]
            if others:
                raise RuntimeError(f"backward is not allowed: {', '.join(others)} changed since this forward, and the "
                                   "gradient at its point cannot be taken; run the forward again")
            current = rollout.get_parameters()
            changed = not all(np.array_equal(current[k], ctx.params[k]) for k in PARAMETERS)
            if changed:
                rollout._set_parameters(ctx.params, current)
            held = None
            try:
                now = rollout.run_settings()  # at this forward's parameters: the automatic fit follows them
                fixed = [f"{name} ({ctx.settings[name]!r}, now {now[name]!r})" for name in ctx.settings
                         if name not in _SETTINGS_PUT_BACK and now[name] != ctx.settings[name]]
                if fixed:
                    raise RuntimeError(f"backward is not allowed: the solver's {', '.join(fixed)} changed since this "
                                       "forward, and its run cannot be re-run; set it back, or run the forward again")
                # rollout.release() since freed its run (backward said 'run forward() first', a
                # call the torch user never makes): re-run as after another forward.
                redo = rollout.forward_count != ctx.forward_count or not rollout._forward_done
                if not redo:
                    try:  # set_material since: the point is not this forward's, whatever the arrays say
                        rollout._check_inputs_unchanged()
                    except RuntimeError:
                        redo = True
                if redo:
                    # The rollout ran with other inputs since: redo this forward first, from
                    # its own start and tools (a model's particle_v0 or a tool's velocity set
                    # since for a later forward were re-run here: the gradient of another point).
                    held = _put_back(rollout, ctx.model_start, ctx.tools, ctx.settings)
                    rollout._forward_checked(ctx.starts)
                    # Checked before this run is taken as the forward's: a second backward
                    # (retain_graph) after a refusal went through the refused run's tape.
                    rollout._check_scripted(rollout._scripted_poses, ctx.scripted, "backward", "this forward")
                    ctx.forward_count = rollout.forward_count
                _, grads = rollout.backward(_numpy(grad_out, rollout.model.types.np_dtype))
            finally:
                if held is not None:
                    _put_back(rollout, *held)  # what was set since, as the parameters below
                if changed:
                    # The model keeps the values it held (a later forward's, or set_parameters'
                    # since): this forward's had replaced them without a word.
                    rollout._set_parameters(current, ctx.params)

            def tensor(a):
                return torch.from_numpy(np.ascontiguousarray(a)).to(dtype=ctx.tensor_dtype, device=ctx.device)

            need = ctx.needs_input_grad
            gx0 = tensor(grads["x0"]) if need[5] else None
            gv0 = tensor(grads["v0"]) if need[6] else None
            gvals = [tensor(grads[name]) if need[7 + k] else None for k, name in enumerate(ctx.names)]
            return (None, None, None, None, None, gx0, gv0, *gvals)

    return RolloutFunction


#: The model's start, which a forward reads where ``x0`` / ``v0`` are not given.
_MODEL_STARTS = ("particle_x0", "particle_v0")

#: The settings (``Rollout.run_settings``) a backward's re-run puts back as its forward ran
#: them, and where each is set (the others, the solver's fit, hourglass and guards, are
#: refused when changed: they are set in several places, some with side effects).
_SETTINGS_PUT_BACK = {"dt": "rollout", "gravity": "model", "contact_ramp": "model"}


def _put_back(rollout: Rollout, start: dict, tools: dict, settings: dict | None = None) -> tuple[dict, dict, dict]:
    """Give the model ``start`` (``{name: array}`` of ``_MODEL_STARTS``), the tools' arrays
    ``tools`` (``{name: values}``) and the ``_SETTINGS_PUT_BACK`` of ``settings`` where they
    differ; returns what it replaced, for the same call to put back."""
    model = rollout.model
    held_settings = {}
    for name, owner in _SETTINGS_PUT_BACK.items():
        if settings is not None and name in settings:
            target = rollout if owner == "rollout" else model
            now = getattr(target, name)
            if now != settings[name]:
                held_settings[name] = now
                setattr(target, name, settings[name])
    held_start = {name: getattr(model, name) for name, v in start.items() if not np.array_equal(getattr(model, name), v)}
    for name in held_start:
        setattr(model, name, start[name])
    held_tools = {}
    for name, a in rollout._tool_arrays().items():
        if name in tools:
            now = a.numpy()
            if not np.array_equal(now, tools[name]):
                held_tools[name] = now.copy()
                a.assign(tools[name])
    return held_start, held_tools, held_settings


def rollout_positions(rollout: Rollout, params=None, x0=None, v0=None):
    """Positions at ``rollout.frames`` as a differentiable torch tensor ``(frames, n, 3)``.

    ``params``: ``{name: tensor of one value per material}`` (a scalar tensor is
    broadcast to every material); ``x0``: an ``(n, 3)`` tensor or None; ``v0``: an ``(n, 3)``
    tensor, a ``(3,)`` one (one velocity for every particle, its gradient the particles'
    sum) or None. Each is
    checked before the parameters are set or anything runs (``Rollout.forward``'s checks,
    ``rollout.check_initial``): finite real numbers, and ``x0`` with no two particles at one
    place (``SceneBuilder`` refuses those). Under ``torch.no_grad()``, or where no input
    requires grad, the run records no tape (``Rollout.forward(taped=False)``: the same
    positions), so a ``Rollout(taped=False)`` serves there; one is refused where an input
    requires grad.
    """
    torch = require_torch()
    if not isinstance(rollout, Rollout):
        raise ValueError(f"rollout = {checks.shorten(rollout)!r} is not allowed: must be a warp_esph.rollout.Rollout")
    if params is not None and not isinstance(params, Mapping):
        # A list of names was read as pairs of characters ("parameter 'm' is not allowed").
        raise ValueError(f"params = {checks.shorten(params)!r} is not allowed: must be a mapping {{name: tensor of one "
                         "value per material}")
    params = dict(params or {})
    names, values = [], []
    given_tensors = {}  # name: tensor, of those given as tensors (plain numbers have no device of their own)
    n_mat = len(rollout.model.materials)
    n = rollout.model.particle_count
    for name, value in params.items():
        _check_name(name)
        if isinstance(value, (list, tuple)) and any(isinstance(v, torch.Tensor) for v in value):
            # One tensor per material: stacked, so each keeps its gradient (numpy refused a
            # tensor that requires one with a RuntimeError); each checked as a number first.
            if any(v.dtype == torch.bool or v.is_complex() if isinstance(v, torch.Tensor)
                   else np.asarray(v).dtype.kind not in "iuf" for v in value):
                raise ValueError(f"{name} = {checks.shorten(value)!r} is not allowed: must be numbers, one per material")
            try:
                value = torch.stack([torch.as_tensor(v).to(torch.float64).reshape(()) for v in value])
            except (RuntimeError, TypeError, ValueError):
                raise ValueError(f"{name} = {checks.shorten(value)!r} is not allowed: must be numbers, one per "
                                 "material") from None
        kind = ("b" if value.dtype == torch.bool else "c" if value.is_complex() else "f") if isinstance(value, torch.Tensor) \
            else np.asarray(value).dtype.kind
        if kind not in "iuf":  # a bool ran as 1 Pa
            # The dtype named: complex64 and complex128 values print alike, and a long tensor is shortened past it.
            typed = f" (dtype {value.dtype})" if isinstance(value, (torch.Tensor, np.ndarray, np.generic)) else ""
            raise ValueError(f"{name} = {checks.shorten(value)!r}{typed} is not allowed: must be numbers, one per material")
        if isinstance(value, torch.Tensor):
            given_tensors[name] = value
        else:
            value = torch.as_tensor(value, dtype=torch.float64)
        _check_dense(torch, name, value)
        if value.dim() == 0:
            value = value.expand(n_mat)
        if value.shape != (n_mat,):
            raise ValueError(f"{name} with shape {tuple(value.shape)} is not allowed: must be ({n_mat},), one value per material")
        names.append(name)
        values.append(value)
    start = {"x0": x0, "v0": v0}
    checked = {}
    for label, t in start.items():
        if t is None:
            continue
        shapes = initial_shapes(label, n)
        if not isinstance(t, torch.Tensor):
            raise ValueError(f"{label} = {checks.shorten(t)!r} is not allowed: must be a torch tensor of shape {shapes}")
        given = given_tensors[label] = t  # checked as given, so that a refusal of one velocity for every particle says so
        if label == "v0" and tuple(t.shape) == (3,):
            # One velocity for every particle, as Rollout.forward takes it; expanded here so
            # autograd sums the particles' gradients into its own.
            t = start[label] = t.expand(n, 3)
        if tuple(t.shape) != (n, 3):
            raise ValueError(f"{label} with shape {tuple(t.shape)} is not allowed: must be a torch tensor of shape {shapes}")
        if t.dtype == torch.bool or t.is_complex():  # True ran as 1 m/s, 1j was dropped
            raise ValueError(f"{label} of dtype {t.dtype} is not allowed: must be real numbers")
        _check_dense(torch, label, t)
        # Here, before the parameters are set and any kernel runs, by the rollout's own checks:
        # x0 with every particle at one point (which SceneBuilder refuses) returned the start
        # moved only by gravity; a NaN ran to NaN positions. Its answer, in the model's precision,
        # is what the forward (and a backward's re-run of it) starts from, not checked again.
        host = given.detach().to(device="cpu", dtype=torch.float64).resolve_neg().numpy()  # numpy has no bfloat16
        # check_initial returns its own copy (in the model's precision), so a tensor changed in
        # place after the forward does not change the start of a backward's re-run.
        checked[label] = check_initial(rollout.model, label, host)
    # A tape only where a backward can follow: under torch.no_grad(), or with no input that
    # requires grad, every step was recorded for nothing (and a Rollout(taped=False), made for
    # such runs, was refused as 'taped = True is not allowed', a value nobody gave).
    taped = torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in (x0, v0, *values))
    if taped and not rollout.taped:
        raise ValueError("rollout is not allowed with inputs that require grad: it was made with taped = False (for "
                         "loss values alone), so nothing can go back through it; make it with taped = True, or run "
                         "under torch.no_grad()")
    return _function().apply(rollout, tuple(names), checked, taped, _output_as(torch, rollout, given_tensors),
                             start["x0"], start["v0"], *values)


def _output_as(torch, rollout: Rollout, given: dict) -> tuple:
    """The output's ``(dtype, device)`` from the tensors given (``{name: tensor}``): real numbers
    in at least the model's precision, promoted over every given float tensor (it was the first
    input's dtype: a float32 model gave float32 positions for a float16 ``v0`` and a float64
    ``mu``, float64 for the two swapped), on their one device. Tensors on several devices are
    refused by name: the output went to the first one's, and torch refused the others' gradients
    there at the backward, naming no input."""
    devices = {}
    for name, t in given.items():
        devices.setdefault(t.device, name)
    if len(devices) > 1:
        (d0, a), (d1, b) = list(devices.items())[:2]
        raise ValueError(f"{a} on {d0} and {b} on {d1} are not allowed together: give every tensor on one device (the "
                         "positions and gradients are returned there; the rollout copies to its model's device itself)")
    # An integer input (a viscosity given as 0) made integer positions, each truncated to 0; a
    # float16 one rounded them (1.7 mm at 5 m from the origin).
    model_dtype = torch.float64 if rollout.model.types.np_dtype == np.float64 else torch.float32
    floats = [t.dtype for t in given.values() if t.is_floating_point()]
    dtype = functools.reduce(torch.promote_types, floats, model_dtype) if floats else torch.float64
    return dtype, next(iter(devices), torch.device("cpu"))


def _check_name(name) -> None:
    """Refuse a name that is no input of the bridge (one of ``PARAMETERS``)."""
    if name in TOOL_GRADIENTS:
        # A tool's array is no input here ('must be one of mu, ...' did not say where it goes);
        # its gradient is on model.tools after a backward.
        raise ValueError(f"parameter {checks.shorten(name)!r} is not allowed: it is a tool parameter, not an input of the torch "
                         f"bridge (set model.tools.{name} before the forward; the backward leaves its gradient on "
                         f"model.tools.{name}.grad); the bridge takes {', '.join(PARAMETERS)}")
    if name not in PARAMETERS:
        raise ValueError(f"parameter {checks.shorten(name)!r} is not allowed: must be one of {', '.join(PARAMETERS)}")


def _check_dense(torch, name: str, t) -> None:
    """Refuse a tensor whose values cannot be read (torch's own 'Cannot copy out of meta
    tensor' or 'can't convert Sparse layout tensor to numpy' named no input)."""
    if t.is_meta or t.layout != torch.strided:
        where = "on the meta device (no values)" if t.is_meta else f"of layout {t.layout}"
        raise ValueError(f"{name} {where} is not allowed: must be a dense tensor with values (.to_dense(), or made on a "
                         "real device)")


# As ``_function``: the class once, when first asked for.
@functools.cache
def _module_class():
    torch = require_torch()

    class RolloutModule(Unpicklable, torch.nn.Module):
        """A ``torch.nn.Module`` with chosen material parameters as trainable ``nn.Parameter``.

        ``RolloutModule(rollout, ["yield_stress", "flow_rate"])``: each parameter is
        stored as ``log(value)`` (``log_space=True``, for positive parameters) with one
        entry per material, initialised from the model. ``module(x0=None, v0=None)``
        returns the positions at the rollout's frames; ``module.values()`` the current
        parameter values. ``torch.save(module)`` is refused (it holds the rollout's model);
        ``torch.save(module.state_dict())`` keeps the parameters.
        """

        UNPICKLABLE_NAME = "warp_esph.torch.RolloutModule"
        UNPICKLABLE = ("it holds a Rollout of a Model's Warp arrays; save its parameters with "
                       "torch.save(module.state_dict()) and load them with module.load_state_dict(torch.load(...)) "
                       "into a RolloutModule made anew of the same scene and parameters")

        def __init__(self, rollout: Rollout, params=("yield_stress", "flow_rate"), log_space: bool = True):
            super().__init__()
            if not isinstance(rollout, Rollout):
                raise ValueError(f"rollout = {checks.shorten(rollout)!r} is not allowed: must be a warp_esph.rollout.Rollout")
            self.rollout = rollout
            if not isinstance(params, str) and not (isinstance(params, (list, tuple)) and params
                                                    and all(isinstance(n, str) for n in params)):
                raise ValueError(f"params = {checks.shorten(params)!r} is not allowed: give a parameter name or a non-empty list of "
                                 f"them ({', '.join(PARAMETERS)})")
            self.names = [params] if isinstance(params, str) else list(params)
            if len(set(self.names)) != len(self.names):  # registered once, its second entry dropped
                raise ValueError(f"params = {checks.shorten(params)!r} is not allowed: a parameter is named twice")
            if not isinstance(log_space, bool):  # "no" read as True
                raise ValueError(f"log_space = {checks.shorten(log_space)!r} is not allowed: must be True or False")
            self.log_space = log_space
            current = rollout.get_parameters()
            for name in self.names:
                _check_name(name)
                v = torch.tensor(current[name], dtype=torch.float64)
                if self.log_space:
                    if not bool((v > 0).all() and torch.isfinite(v).all()):  # log(inf) failed only at forward()
                        raise ValueError(f"{name} = {current[name].tolist()} is not allowed in log space: values must be "
                                         "finite and > 0")
                    v = torch.log(v)
                self.register_parameter(name, torch.nn.Parameter(v))

        def values(self) -> dict:
            """The parameter values (exp of the stored logs in log space)."""
            return {n: (torch.exp(getattr(self, n)) if self.log_space else getattr(self, n)) for n in self.names}

        def forward(self, x0=None, v0=None):
            return rollout_positions(self.rollout, self.values(), x0=x0, v0=v0)

    return RolloutModule


def __getattr__(name):
    # ``RolloutModule`` subclasses torch.nn.Module, so it is made when first asked for.
    if name == "RolloutModule":
        return _module_class()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
