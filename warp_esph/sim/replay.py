"""Replayed launches: the step's Python cost at small particle counts.

``wp.launch`` packs every argument into a C struct on every call, 5-10 us each on the CPU,
and the step's kernels take 10-35 arguments, most of them the same arrays step after step.
At a few thousand particles that packing costs more than the kernels themselves
(docs/performance.md, "Launch overhead"). ``Launches`` records a kernel's launch the first
time (``wp.launch(..., record_cmd=True)``) and afterwards repacks only the arguments that
are not the very objects of the launch it replays, then replays it.

On the CPU, ``Launch.launch`` itself builds the kernel's argument struct again, field by
field, at every call (about 20 us at 20 arguments; an adjoint launch two of them). A replayed
launch keeps them filled (``_packed_arguments``), updates the fields of the arguments it
repacks, and calls the kernel's forward (or backward) entry point with them, as
``Launch.launch`` would; where Warp's layout is not
the one this was written against, or a command capture records, it calls ``cmd.launch()``.
``tests/test_determinism.py`` compares the states with ``wp.launch``'s, bit for bit.

What counts as unchanged: the same array object (an array's data and shape never move), or
an equal number, Warp scalar, vector or matrix of the same type. A struct, vector or matrix
passed again as the same object is copied again at every call, so one changed in place is
never replayed stale. A few recorded launches
per kernel (``SLOTS``) keep double-buffered states (``state_in`` and ``state_out``
swapping roles every step) from repacking every step.

Under a recording ``wp.Tape`` a replayed launch is recorded on the tape as ``wp.launch``
records it (kernel, launch size, inputs, outputs), so the backward pass launches the same
adjoints. An adjoint launch made by hand (``adjoint=True`` with its ``adj_inputs``,
``adj_outputs``: a generated adjoint a backward pass runs in place of the tape's) is replayed
likewise, both halves of its arguments compared and repacked, and on the CPU its two
argument structs kept filled as below (the tape's own ``wp.launch`` of it packed and checked
every argument of both halves at every step: 0.075 ms a step of the fit example's backward
against 0.01 ms for the same kernel's replayed forward). It steps aside, calling ``wp.launch`` itself, wherever replaying could
change what Warp does: on a stream, under ``wp.config.verify_fp``, ``verify_cuda`` or
``print_launches``, and under a tape or for an adjoint with
``wp.config.verify_autograd_array_access``. An
empty launch (size 0) runs nothing and is only recorded on the tape. The replayed launches
hold their last arguments, so the owner keeps up to ``SLOTS`` sets of the arrays it launched
on alive until it is itself released.

A taped run steps between new states at every step, so its launches' arrays were never the
very objects of the few kept slots: every state array was repacked at every step, forward and
backward (51 and 65 arguments a step of the fit example's star, about a tenth of its
gradient's time). ``keep_in(records(owner))`` keeps the launches made until ``keep_in(None)``
apart, in records of their own that live as long as ``owner`` (a taped step's ``state_out``,
to which its rollout steps from the same state at every forward): the next forward's step and
its backward find their launches there on the very arrays, and repack only the numbers.

A launch no tape records runs the kernel's forward-only twin (``forward_only``): the same
function compiled without its generated adjoint, which Warp otherwise compiles with every
kernel. The forward code is the same, so is every bit it computes
(``tests/test_determinism.py``); it compiles in about a third of the time
(docs/performance.md, "Where a cold run's time goes"), and a run that records no tape never
compiles an adjoint.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import itertools
import operator
import sys
import weakref

import warp as wp
from warp._src import context as _context  # the runtime: looked up at every launch, so imported once


def _runtime():
    """Warp's runtime, Warp started first where it has not been: a loss's ``value`` (or a
    tape's bookkeeping) is the first Warp call of a script that built its positions in numpy,
    and the runtime was still None there ("module 'warp' has no attribute 'context'" came
    from looking it up in Warp's older layout). Warp starts quietly, as ``init_warp`` starts
    it, and the caller's log level comes back afterwards."""
    if _context.runtime is None:
        from ..startup import init_warp  # noqa: PLC0415

        level = wp.config.log_level
        try:
            init_warp(log_level=max(level, wp.LOG_WARNING))
        finally:
            wp.config.log_level = level
    return _context.runtime


def recording_tape():
    """The ``wp.Tape`` recording launches now, or None."""
    return getattr(_runtime(), "tape", None)


def weak_tape(tape):
    """A function that returns ``tape``, for an adjoint recorded on it to reach it by: the tape
    holds that adjoint, and an adjoint holding the tape back made every dropped tape a
    reference cycle with all its steps' records, left to Python's cyclic collector. Called
    after the tape was freed (its ``launches`` kept and run without it), it refuses: that
    backward would register its gradients on no tape for ``zero()``."""
    ref = weakref.ref(tape)

    def live():
        held = ref()
        if held is None:
            raise RuntimeError("a backward pass of a step recorded on a wp.Tape is not allowed after that tape was freed: "
                               "the step's recorded adjoints hold their tape weakly; keep the tape until its backward "
                               "pass is done, and run it with tape.backward()")
        return held

    return live


@contextlib.contextmanager
def outside_recording_tape():
    """Runs its block with no ``wp.Tape`` recording, the caller's (if any) recording again
    after it, also where the block raises. For work that keeps a tape of its own and whose
    launches are no part of the caller's: Warp refuses a tape entered inside another
    ("entering a tape while one is already active"), and the launches before it would have
    been recorded on the caller's tape, whose backward pass then replayed them."""
    runtime = _runtime()
    outer = getattr(runtime, "tape", None)
    runtime.tape = None
    try:
        yield
    finally:
        runtime.tape = outer


@contextlib.contextmanager
def kept_through_backward(*arrays):
    """Around a launch the tape records with Warp's generated adjoint whose forces are
    scattered inside ``wp.func``s (``forces.paper_forces``, the fits' variational forces):
    that adjoint replays each func's forward, scatter included, so the backward pass added
    the step's forces to ``arrays`` once more (``State.force`` 2.5-93 % off after
    ``tape.backward()``, measured; the gradients were right). The tape restores them after
    that adjoint to what they held when the backward pass reached it, the forward's."""
    tape = recording_tape()
    if tape is None:
        yield
        return
    saved = []

    def restore():
        for a, copy in zip(arrays, saved):
            wp.copy(a, copy)
        saved.clear()

    # The backward pass runs the tape in reverse: save, the launch's adjoint, restore.
    tape.record_func(restore, [])
    yield
    tape.record_func(lambda: saved.extend(wp.clone(a) for a in arrays), [])


#: Recorded launches kept per kernel and launch size: two for the states' double buffer,
#: two more for the arrays of an occasional other state (a rollout's, a fit's).
SLOTS = 4
#: The same in the records of one owner (``Launches.records``): a kernel launched twice in
#: one step on other arrays keeps both.
KEPT_SLOTS = 2

_NUMBERS = frozenset((int, float, bool))
_ARRAY = wp.array
_RELAXED = getattr(getattr(wp.config, "LaunchArrayAccessMode", None), "RELAXED", None)
_WARP_SCALARS = frozenset((wp.int8, wp.uint8, wp.int16, wp.uint16, wp.int32, wp.uint32, wp.int64, wp.uint64, wp.float16,
                           wp.float32, wp.float64))


def _same(a, b) -> bool:
    """Whether ``b`` packs to the bytes ``a`` packed to (``a is not b``)."""
    t = type(a)
    # Two array objects are different arrays: the common case, answered first (a rollout's
    # states are new arrays at every step).
    if t is wp.array or t is not type(b):
        return False
    if t in _NUMBERS:
        return a == b
    if t in _WARP_SCALARS:
        return a.value == b.value
    if issubclass(t, ctypes.Array):  # Warp's vectors and matrices
        return bytes(a) == bytes(b)
    return False


def pointer_key(arrays) -> tuple:
    """What a ``wp.struct`` copies of each of ``arrays`` when it is filled, the data pointers of
    the array and of its gradient, as the array and gradient objects themselves: an array's
    data never moves, and the key keeps them alive, so an equal key (compared by identity:
    a ``wp.array`` has no ``__eq__``) is the same allocations. A filled struct may be reused
    while this key holds (``Model.material_arrays``, ``integrate.static_collider_struct``, and
    ``Model._read_parameters``' views); it costs half of a key of ids and pointers."""
    arrays = tuple(arrays)
    return arrays + tuple(a.grad for a in arrays)


# Cached per kernel for the process: a kernel is compiled code, never changed after it is
# made, and the kernels come from the factories' own caches (sim/__init__.py), so the cache
# stays as small as they are and holds no array.
@functools.cache
def forward_only(kernel):
    """``kernel`` itself where it has no generated adjoint, else the same function as a kernel
    without one (its own module), made once per kernel. Returned as they are: generic kernels
    and their overloads, and kernels with any other option of their own or of their module (a
    twin would not carry it)."""
    if (kernel.is_generic or getattr(kernel, "generic_parent", None) is not None
            or set(kernel.options) - {"enable_backward"}
            or kernel.options.get("enable_backward", wp.config.enable_backward) is False):
        return kernel
    twin = wp.kernel(enable_backward=False, module="unique")(kernel.func)
    theirs, ours = dict(kernel.module.options), dict(twin.module.options)
    theirs.pop("enable_backward", None)
    ours.pop("enable_backward", None)
    return twin if theirs == ours else kernel


class Launches:
    """Call as ``wp.launch`` (same arguments); one per owner of launches (a ``Model``, a
    neighbour search), never shared between threads."""

    def __init__(self):
        #: False: every launch through ``wp.launch`` (the baseline ``benchmarks.launches`` times).
        self.enabled = True
        #: False: untaped launches run the kernel as given, with its adjoint compiled.
        self.forward_only = True
        #: False: a replayed CPU launch goes through ``cmd.launch()``, which fills the kernel's
        #: argument struct again (the other baseline ``benchmarks.launches`` times).
        self.keep_struct = True
        self._recorded: dict = {}
        #: ``records``, by owner, each dropped with its owner.
        self._kept_by = weakref.WeakKeyDictionary()
        #: The records launches are kept in now (``keep_in``); None: the shared slots.
        self._kept = None

    def records(self, owner) -> dict:
        """``owner``'s own records of launches (``keep_in``), made on first use and dropped
        with ``owner``."""
        records = self._kept_by.get(owner)
        if records is None:
            records = self._kept_by[owner] = {}
        return records

    def keep_in(self, records: dict | None):
        """From now on, launches are replayed from and recorded in ``records`` (``records(owner)``)
        instead of the slots every launch shares; None: the shared slots again. A call, not a
        ``with`` block: a tape's backward pass switches between steps' records in functions it
        runs."""
        self._kept = records

    def __call__(self, kernel, dim, inputs=(), outputs=(), adj_inputs=(), adj_outputs=(), device=None, stream=None,
                 adjoint=False, record_tape=True, max_blocks=0, block_dim=None):
        # An adjoint launch is never recorded on a tape (wp.launch records forward launches only).
        tape = recording_tape() if record_tape and not adjoint else None
        if tape is None and self.forward_only and not adjoint:
            kernel = forward_only(kernel)
        if (not self.enabled or (not adjoint and (adj_inputs or adj_outputs)) or stream is not None
                or wp.config.verify_fp or wp.config.verify_cuda or wp.config.print_launches
                or ((tape is not None or adjoint) and wp.config.verify_autograd_array_access)):
            wp.launch(kernel, dim, inputs, outputs, adj_inputs, adj_outputs, device=device, stream=stream,
                      adjoint=adjoint, record_tape=record_tape, max_blocks=max_blocks, block_dim=block_dim)
            return
        if adjoint:
            self._replay(kernel, dim, inputs, outputs, device, max_blocks, block_dim, adj_inputs, adj_outputs)
            return
        self._replay(kernel, dim, inputs, outputs, device, max_blocks, block_dim)
        if tape is not None:
            f = sys._getframe(1)  # the launcher, as wp.launch names its caller
            tape.record_launch(kernel, dim, max_blocks, inputs, outputs, device, block_dim,
                               metadata={"caller": {"file": f.f_code.co_filename, "lineno": f.f_lineno,
                                                    "func": f.f_code.co_name}})

    def _replay(self, kernel, dim, inputs, outputs, device, max_blocks, block_dim, adj_inputs=None, adj_outputs=None):
        """``adj_inputs`` and ``adj_outputs`` given: the adjoint launch, its arguments the forward
        ones followed by theirs (the layout of Warp's launch parameters)."""
        adjoint = adj_inputs is not None
        args = [*inputs, *outputs, *adj_inputs, *adj_outputs] if adjoint else [*inputs, *outputs]
        key = (kernel, dim if isinstance(dim, int) else tuple(dim), str(device), max_blocks, block_dim, len(args), adjoint)
        kept = self._kept
        slots = (self._recorded if kept is None else kept).setdefault(key, [])
        room = SLOTS if kept is None else KEPT_SLOTS
        best, changed = None, None
        # Least recently used first: with double-buffered states the launch before last
        # was on the same objects, so the first slot usually matches and ends the search.
        count = range(len(args))
        for slot in slots:
            held = slot[1]
            # Identity first, in C (a rollout's states are new arrays at every step, so every
            # slot is compared in full); an array that is not the very object differs.
            diff = [i for i in itertools.compress(count, map(operator.is_not, args, held))
                    if type(args[i]) is _ARRAY or not _same(args[i], held[i])]
            if changed is None or len(diff) < len(changed):
                best, changed = slot, diff
                if not diff:
                    break
        if best is None or (changed and len(slots) < room):
            # Record it beside the others: the next launch on these objects replays it as is.
            cmd = wp.launch(kernel, dim, inputs, outputs, adj_inputs or [], adj_outputs or [], device=device,
                            adjoint=adjoint, max_blocks=max_blocks, block_dim=block_dim, record_tape=False,
                            record_cmd=True)
            if cmd is None:  # an empty launch: nothing to run or replay (a tape is told by the caller)
                return
            slots.append([cmd, args, None])
            cmd.launch()
            return
        cmd, held, packed = best
        if packed is None:
            packed = best[2] = _packed_arguments(cmd)
        forward_args = len(args) // 2 if adjoint else len(args)
        for i in changed:
            if not _repack_array(cmd, i, args[i], held[i], forward_args):
                # The adjoint half is packed after the forward arguments.
                if i >= forward_args:
                    cmd.set_param_at_index(i - forward_args, args[i], adjoint=True)
                else:
                    cmd.set_param_at_index(i, args[i])
            held[i] = args[i]
            if packed:
                setattr(packed[0][i], packed[1][i], cmd.params[1 + i])
        if best is not slots[-1]:
            slots.remove(best)
            slots.append(best)
        if packed and self.keep_struct and _no_capture():
            for i in packed[3]:
                # A struct, vector or matrix passed again as the same object may have
                # changed in place: copied at every call, as Launch.launch copies it.
                setattr(packed[0][i], packed[1][i], cmd.params[1 + i])
            packed[2](ctypes.byref(cmd.params[0]), *packed[4])
        else:
            cmd.launch()


def _repack_array(cmd, i: int, value, old, forward_args: int) -> bool:
    """``cmd.set_param_at_index(i, value)`` where a ``wp.array`` takes the place of the
    ``wp.array`` ``old`` of the same dtype and dimension that the launch holds, which Warp
    checked when it packed it: Warp's ``pack_arg`` would check the same again (10 checks,
    about half the Python cost of a taped step's repacking, where a rollout's states are
    new arrays every step) and then pack ``value.__ctype__()``, the very descriptor packed
    here. False (nothing done) for anything else, or where Warp checks more (a launch array
    access mode other than relaxed) or its launch object is not the one this was written
    against."""
    if (type(value) is not _ARRAY or type(old) is not _ARRAY or value.dtype is not old.dtype or value.ndim != old.ndim
            or getattr(wp.config, "launch_array_access_mode", None) is not _RELAXED or _RELAXED is None):
        return False
    try:
        params, addr, fwd = cmd.params, cmd.params_addr, cmd.fwd_args
    except AttributeError:  # pragma: no cover (another Warp)
        return False
    carg = value.__ctype__()
    params[1 + i] = carg
    if addr:
        addr[1 + i] = ctypes.c_void_p(ctypes.addressof(carg))
    # Warp keeps its unpacked arguments in step with the packed ones (a capture reads them);
    # argument ``i`` of an adjoint launch from ``forward_args`` on is of its adjoint half.
    if i >= forward_args:
        adj = getattr(cmd, "adj_args", None)
        if adj is not None:
            adj[i - forward_args] = value
    elif fwd is not None:
        fwd[i] = value
    return True


def _packed_arguments(cmd):
    """What ``Launch.launch`` builds again at every call on the CPU (``invoke``: the kernel's
    argument struct filled field by field, about 20 us at 20 arguments; an adjoint launch's
    two, the forward arguments' and their adjoints'), built once for this recorded launch:
    ``(the struct of each argument, field names, entry point, the indices of the arguments
    copied at every call, the structs passed by reference)``, kept in step with ``cmd.params``
    by the caller: a repacked argument's field is updated when it is repacked, and a struct,
    vector or matrix argument (packed as the caller's live object, which may change in place)
    at every call. False where the launch does not take that path (a device, tiles) or Warp's
    layout is not the one this was written against: the launch then goes through
    ``cmd.launch()``."""
    try:
        if not cmd.device.is_cpu or cmd.block_dim > 1:
            return False
        cached = cmd.kernel._invoke_cache.get((tuple(type(p) for p in cmd.params[1:]), bool(cmd.adjoint)))
        if cmd.adjoint:
            if cached is None or len(cached) != 4:
                return False
            struct_type, adj_type, fields, adj_fields = cached
            structs = (struct_type(), adj_type())
            entry = cmd.hooks.backward
        else:
            if cached is None or len(cached) != 2:
                return False
            (struct_type, fields), adj_fields = cached, []
            structs = (struct_type(),)
            entry = cmd.hooks.forward
        names = [name for name, _ in fields] + [name for name, _ in adj_fields]
        if len(names) != len(cmd.params) - 1:
            return False
        owners = [structs[0]] * len(fields) + [structs[-1]] * len(adj_fields)
        for owner, name, value in zip(owners, names, cmd.params[1:]):
            setattr(owner, name, value)
        arrays = tuple(t for t in (getattr(wp._src.types, n, None) for n in ("array_t", "indexedarray_t", "fabricarray_t",
                                                                              "indexedfabricarray_t")) if t is not None)
        live = tuple(i for i, value in enumerate(cmd.params[1:])
                     if isinstance(value, (ctypes.Structure, ctypes.Array)) and not isinstance(value, arrays))
        return owners, names, entry, live, tuple(ctypes.byref(st) for st in structs)
    except (AttributeError, TypeError):  # pragma: no cover (another Warp)
        return False


def _no_capture() -> bool:
    """No CPU command capture is recording (``Launch.launch`` records into one)."""
    return getattr(_runtime(), "_apic_capture", None) is None
