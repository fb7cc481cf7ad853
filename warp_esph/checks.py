"""Input checks that run before any kernel does.

Every failure is a ``ValueError`` whose message names the parameter, the value given
and what is allowed, so a user can fix the input without reading code.
"""

from __future__ import annotations

import codecs
import contextlib
import json
import math
import os
import re
import stat
import struct
import sys
import unicodedata
import zipfile
import zlib
from collections.abc import Mapping, Sequence

import numpy as np


def _fail(name: str, value, allowed: str):
    raise ValueError(f"{name} = {shorten(value)!r} is not allowed: {allowed}")


class _Shown:
    """A value shortened for a message (``repr`` of an int with 400 digits is not helpful)."""

    def __init__(self, text: str):
        self.text = text

    def __repr__(self):
        return self.text


def shorten(value):
    """``value`` for a message: a 400-digit int as ``1.234e+399``, long text cut, on one line."""
    if isinstance(value, _Shown):
        return value
    try:
        text = repr(value)
    except Exception:  # noqa: BLE001 (a repr that fails must not hide the real error)
        text = f"<{type(value).__name__}>"
    # numpy writes an array's rows on lines of their own (a str's repr escapes its newlines):
    # a list of two arrays was a message of twenty lines.
    text = re.sub(r"\s*\n\s*", " ", text)
    if len(text) > 60:
        if isinstance(value, int) and not isinstance(value, bool) and value != 0:
            text = f"{'-' if value < 0 else ''}{text.lstrip('-')[0]}.{text.lstrip('-')[1:4]}e+{len(text.lstrip('-')) - 1}"
        else:
            text = text[:57] + "..."
    return _Shown(text)


#: A path a message shows whole up to this many characters (``shown_path``): one to copy from
#: the line; a longer one by its first and last ``PATH_ENDS``.
PATH_SHOWN_WHOLE = 160
PATH_ENDS = 40


def _ends(text: str, length: int | None = None) -> str:
    """``text`` whole where ``length`` (the path's own, without what a message writes around it;
    default ``text``'s) is at most ``PATH_SHOWN_WHOLE``, else its first and last ``PATH_ENDS``."""
    long = len(text) if length is None else length
    return text if long <= PATH_SHOWN_WHOLE else f"{text[:PATH_ENDS]}...{text[-PATH_ENDS:]}"


#: What a message writes around a path (quotes, '=', a ':' or ',' after it): not counted in
#: the path's length, so that a path of PATH_SHOWN_WHOLE characters is shown whole however it
#: is written; counted, one of 159 or 160 characters was cut by its quotes or a ':' after it.
_AROUND_PATH = "'\"=(),:;"


def shown_path(path, quote: bool = True) -> _Shown:
    """A path the user gave (an option's, a scene file's ``file``, a target), for a message: as
    ``repr`` writes it (``quote=False``: as written), and where that is longer than
    ``PATH_SHOWN_WHOLE`` only its first and last ``PATH_ENDS`` characters with '...' between,
    so that the file's name, at the end, stays readable: a 5000-character ``-o`` wrote a 5 kB
    refusal line (``shorten`` keeps the start alone). Format it with ``{}`` or ``{!r}``: both
    show this text."""
    if isinstance(path, _Shown):
        return path
    try:
        text = os.fsdecode(os.fspath(path))
    except TypeError:  # not a path (None, a number): as any value is shown
        return shorten(path)
    # Whole by the path's length, not its repr's: a path of 159 or 160 characters was cut by its quotes.
    return _Shown(_ends(repr(text) if quote else text, len(text)))


def tilde_note(path) -> str:
    """'; '~' is not expanded' where ``path`` starts with '~' (a shell leaves it as written after
    '--target=' or in quotes, and no reader here expands it), else ''."""
    try:
        return "; '~' is not expanded" if os.fsdecode(os.fspath(path)).startswith("~") else ""
    except TypeError:
        return ""


def long_words_cut(text: str) -> str:
    """``text`` with each word (a run without spaces) longer than ``PATH_SHOWN_WHOLE`` characters
    cut to its ends, as ``shown_path`` cuts a path: the commands' one-line messages pass
    through it, so that a path a refusal names whole (an ``OSError``'s file name, another
    library's message) is not a line of kilobytes."""
    return re.sub(r"\S{%d,}" % (PATH_SHOWN_WHOLE + 1),
                  lambda m: _ends(m.group(0), len(m.group(0).strip(_AROUND_PATH))), text)


def shorten_text(text, limit: int = 300) -> str:
    """``text`` (another library's message, which may quote a huge value) on one line, cut to
    ``limit`` characters."""
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[:limit - 3] + "..."


def plural(n: int, word: str) -> str:
    """``n word`` or ``n words``: a count in a message ('1 evaluations' read wrong)."""
    return f"{n} {word}" if n == 1 else f"{n} {word}s"


#: Default upper bound of ``positive_int``: Warp indexes arrays with int32.
MAX_INT = 2**31 - 1


class TypedNumber(float):
    """A number read from text that no float holds (``1e400`` reads as inf, ``1e-400`` as 0.0):
    it computes as that float, and a message shows it as typed. A refusal said
    ``--scale = inf`` to a command line that typed ``--scale 1e400``."""

    def __new__(cls, value: float, text: str):
        self = super().__new__(cls, value)
        self.text = text
        return self

    def __getnewargs__(self):
        return float(self), self.text

    def __repr__(self):
        return self.text

    __str__ = __repr__

    def __format__(self, spec):
        return self.text


def read_number(text: str) -> float:
    """``float(text)``, or a ``TypedNumber`` where the text names a finite number other than
    zero that the float overflows to inf or rounds to 0.0 (a ``ValueError`` where it is no
    number)."""
    import decimal  # noqa: PLC0415

    v = float(text)
    if math.isinf(v) or v == 0.0:
        try:
            exact = decimal.Decimal(str(text).strip())
        except decimal.InvalidOperation:
            return v
        if exact.is_finite() and exact != 0:
            return TypedNumber(v, str(text).strip())
    return v


def unheld(value) -> str | None:
    """Why a number ``read_number`` read is not the number typed (a ``TypedNumber``: ``1e-400``
    reads as 0.0, ``1e400`` as inf); None where a float holds it."""
    if not isinstance(value, TypedNumber):
        return None
    if value == 0.0:
        return "it is not 0, but no float holds this number: it reads as 0.0 (the smallest float above 0 is 5e-324)"
    return f"no float holds this number: it reads as {float(value)} (the largest float is {sys.float_info.max:.4g})"


#: The parameters whose 0 is off, by name (the commands' ``--hourglass`` and ``--jitter``, a
#: scene file's ``[solver] hourglass``), and what 0 is: a number typed that is not 0 but reads
#: as 0.0 (``1e-400``) turned them off without a word.
ZERO_IS_OFF = {"hourglass": "off (no hourglass control)", "jitter": "off (the lattice as written)"}


def unheld_refusal(value, param: str = "", *, zero: str = "", inf: str = "") -> str | None:
    """What follows 'is not allowed: ' in the refusal of ``value`` where it is a number typed
    that no float holds (``unheld``), else None: why, and the advice. For a number read as 0.0
    of a parameter ``ZERO_IS_OFF`` names (``param`` as the user wrote it: ``--hourglass`` on a
    command line, ``hourglass`` in a scene file), what 0 is and to give it; else ``zero`` (read
    as 0.0) or ``inf`` (read as inf), where 0 or inf is a value of its own ('' for none)."""
    why = unheld(value)
    if why is None:
        return None
    if value != 0.0:
        return why + (f"; {inf}" if inf else "")
    off = ZERO_IS_OFF.get(param.lstrip("-").replace("-", "_"))
    if off:
        # As the user writes the parameter: '--hourglass 0' on a command line, 'hourglass = 0' in a file.
        option = param.startswith("-")
        zero = f"{param}{' ' if option else ' = '}0 is {off}: {'give' if option else 'write'} 0 for that"
    return why + (f"; {zero}" if zero else "")


def number(name: str, value, *, allow_inf: bool = False) -> float:
    """A real number (bools, strings and NaN rejected); ``inf`` only when ``allow_inf``."""
    if type(value) is float:
        # The common case, asked several times a step (dt, the time, a scripted pose): a
        # plain float is none of what the checks below look for, only NaN or inf may be refused.
        if value - value == 0.0:
            return value
        if math.isnan(value) or not allow_inf:
            _fail(name, value, "must be a finite number")
        return value
    # numpy's text scalars (np.str_, np.bytes_) have __float__: '0.1' was parsed where a
    # Python string is refused.
    if isinstance(value, (bool, str, bytes)) or not isinstance(value, (int, float)) and not hasattr(value, "__float__"):
        _fail(name, value, "must be a number")
    dtype = getattr(value, "dtype", None)
    is_complex = getattr(value, "is_complex", None)  # torch's tensors, every complex dtype
    if isinstance(value, np.bool_) or getattr(dtype, "kind", None) in ("b", "c") or str(dtype) == "torch.bool" \
            or (callable(is_complex) and is_complex()) or type(value).__name__ == "bool" and type(value) is not bool:
        # numpy's and torch's bools read as 1 and 0 (Python's True is refused above), a complex
        # value as its real part with only a ComplexWarning.
        _fail(name, shorten(value), "must be a real number (not a bool or a complex)")
    if getattr(value, "requires_grad", False):
        # A torch tensor that carries a gradient: float() cuts it off without a word.
        _fail(name, shorten(value), "must be a plain number: float() would drop its gradient (to fit a parameter "
                                    "through torch, use warp_esph.torch)")
    try:
        v = float(value)
    except OverflowError:  # an int like 10**400
        _fail(name, shorten(value), "must be a finite number (it overflows a float)")
    except (TypeError, ValueError):
        _fail(name, value, "must be a number")
    if math.isnan(v) or (math.isinf(v) and not allow_inf):
        _fail(name, value, "must be a finite number" + (" (it overflows a float)" if isinstance(value, TypedNumber) else ""))
    return v


def positive(name: str, value, **kw) -> float:
    v = number(name, value, **kw)
    if not v > 0.0:
        _fail(name, value, "must be > 0")
    return v


#: The largest Courant number the step bound is measured to hold at (docs/method.md §8).
MAX_COURANT = 0.3


def courant(value) -> float:
    """A Courant number in ``(0, MAX_COURANT]``: above it ``stable_dt`` would return a step
    the bound was never measured to hold at (some presets blow up from 1.5 x)."""
    v = positive("courant", value)
    if v > MAX_COURANT:
        _fail("courant", value, f"must be in (0, {MAX_COURANT}]: the step bound is measured to hold up to "
                                f"{MAX_COURANT} (docs/method.md §8); give a longer dt directly to go beyond it")
    return v


def non_negative(name: str, value, **kw) -> float:
    v = number(name, value, **kw)
    if not v >= 0.0:
        _fail(name, value, "must be >= 0")
    return v


#: The range of an observation noise (a standard deviation): its square enters the
#: chi-square, and 1e-200 divided by zero, 1e200 overflowed, after the whole fit had run.
NOISE_RANGE = (1e-150, 1e150)


def noise(name: str, value) -> float:
    """An observation noise: a number in ``NOISE_RANGE``."""
    return in_range(name, value, *NOISE_RANGE)


def in_range(name: str, value, lo: float, hi: float) -> float:
    v = number(name, value)
    if not lo <= v <= hi:
        _fail(name, value, f"must be in [{lo}, {hi}]")
    return v


def greater_than(name: str, value, bound: float, bound_text: str) -> float:
    v = number(name, value)
    if not v > bound:
        # "> -2 mu / 3 = -6.67e+03"; a bare number is not written twice ("> 1").
        same = bound_text.strip() == f"{bound:g}"
        _fail(name, value, f"must be > {bound_text}" if same else f"must be > {bound_text} = {bound:g}")
    return v


def squarable_coordinates(what: str, a, precision: str, place, quantity: str = "coordinate", unit: str = "m",
                          hint: str = "give positions in metres, of this scene") -> None:
    """Refuse, before any rollout, a target coordinate whose square a loss cannot hold in
    ``precision`` ('float32' or 'float64', the model's): the losses sum squared distances
    there, so a position of 1e300 (inf in float32) made the first evaluation's loss inf,
    and the fit failed after its first rollout as 'not finite at the initial guess'. The
    bound is sqrt(max) / 10, a tenth leaving the sum of squares room. ``place(index)``
    says where the first such coordinate of ``a`` is (its index into ``a``). A measured force
    or height, squared by its loss the same way, names itself with ``quantity``, ``unit`` and
    ``hint``."""
    a = np.asarray(a, dtype=np.float64)
    largest = float(np.finfo(precision).max)
    bound = math.sqrt(largest) / 10.0
    bad = np.flatnonzero(~(np.abs(a) <= bound).reshape(-1))
    if not bad.size:
        return
    where = np.unravel_index(bad[0], a.shape)
    raise ValueError(f"{what} is not allowed: it holds the {quantity} {float(a[where]):g} ({place(where)}), past what "
                     f"the {precision} loss can square (at most {bound:.2g} {unit}; the {precision} max is {largest:.2g}): "
                     f"{hint}")


def _is_tensor(value) -> bool:
    return type(value).__module__.split(".")[0] == "torch" and callable(getattr(value, "detach", None))


def host_values(name: str, value):
    """``value`` as numpy reads it: a torch tensor copied to the host (floating point in
    float64), a list or tuple holding tensors as a list of such copies, anything else
    unchanged. numpy read a tensor that requires a gradient, one on a GPU or a bfloat16 one
    with torch's own error, naming no parameter; the first is refused here instead, since
    reading its values cuts the gradient off without a word, and so is a tensor with no values
    to read (on the meta device, or sparse)."""
    if isinstance(value, (list, tuple)) and any(_is_tensor(v) for v in value):
        # One tensor per material or frame: numpy's asarray of the list met each tensor with
        # torch's own error ('Can't call numpy() on Tensor that requires grad').
        return [host_values(name, v) for v in value]
    if not _is_tensor(value):
        return value
    if value.requires_grad:
        _fail(name, value, "it is a torch tensor that requires grad, and reading its values would drop its gradient "
                           "(pass .detach(), or fit through torch with warp_esph.torch)")
    if value.is_meta or str(value.layout) != "torch.strided":
        # torch's 'Cannot copy out of meta tensor' and 'can't convert Sparse layout tensor'
        # named no input (the torch bridge refuses these as well: warp_esph.torch).
        where = "on the meta device (no values)" if value.is_meta else f"of layout {value.layout}"
        _fail(name, value, f"it is a torch tensor {where}; give a dense tensor with values (.to_dense(), or made on a "
                           "real device)")
    # A lazy negation or conjugation (x.conj().imag is a float64 tensor with its negative bit
    # set) is made real first: numpy() refused it with torch's own error.
    t = value.detach().cpu().resolve_conj().resolve_neg()
    return (t.double() if t.is_floating_point() else t).numpy()


#: What ``np.asarray(value, dtype=np.float64)`` raises for a value that is no array of
#: numbers: text or ragged rows (TypeError, ValueError), and an integer past the floats
#: (OverflowError: Python's, TOML's and JSON's integers are unbounded; 10**400 given as a
#: velocity, a target or a camera's R ended in numpy's 'int too large to convert to float').
ARRAY_ERRORS = (TypeError, ValueError, OverflowError)

#: The dtype kinds numpy casts to float64 without holding real numbers, as a refusal names
#: them: text (numpy parsed '0.5' as 0.5), booleans (True as 1) and complex numbers (the
#: imaginary part dropped with only a ComplexWarning).
NOT_REAL = {"U": "text", "S": "text", "b": "booleans", "c": "complex numbers"}


def real_numbers(name: str, value, allowed: str) -> None:
    """Refuses ``value`` naming ``name`` where numpy would read text, booleans or complex
    numbers as float64 (``NOT_REAL``); ``allowed`` says what is. What numpy cannot read as
    float64 (text that is no number, ragged rows, an int past the floats) is left to the
    caller's conversion and its refusal."""
    try:
        kind = np.asarray(value).dtype.kind
        if kind in "US":
            np.asarray(value, dtype=np.float64)
    except ARRAY_ERRORS:
        return
    if kind in NOT_REAL:
        _fail(name, value, f"it holds {NOT_REAL[kind]}; {allowed}")


def vector(name: str, value, length: int = 3) -> tuple[float, ...]:
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence) and not hasattr(value, "__len__"):
        _fail(name, value, f"must be a sequence of {length} numbers")
    if isinstance(value, (set, frozenset, Mapping)):  # no order: a set of (2, 1, 0) came back as (0, 1, 2)
        _fail(name, value, f"must be a sequence of {length} numbers in order (not a set or a mapping)")
    try:
        size = len(value)
    except TypeError:  # a 0-d numpy array has __len__ but no length: Python's 'len() of unsized object'
        _fail(name, value, f"must be a sequence of {length} numbers")
    if size != length:
        _fail(name, value, f"must be a sequence of {length} numbers")
    return tuple(number(f"{name}[{k}]", c) for k, c in enumerate(value))


#: The largest hourglass-control strength (``Solver(hourglass=)``): ``Model.stable_dt``'s
#: bound for the control is measured up to it (docs/physics.md, "Hourglass modes").
MAX_HOURGLASS = 1000.0


def hourglass(name: str, value) -> float:
    """An hourglass-control strength: a number in [0, ``MAX_HOURGLASS``] (0: off)."""
    c = non_negative(name, value)
    if not c <= MAX_HOURGLASS:
        _fail(name, value, HOURGLASS_LIMIT)
    return c


#: What ``hourglass`` says of a strength above ``MAX_HOURGLASS``.
HOURGLASS_LIMIT = f"must be at most {MAX_HOURGLASS:g} (0: off; the step bound is measured up to it)"


def unit_vector(name: str, value, length: int = 3, what: str = "vector") -> tuple[float, ...]:
    """``value`` (``length`` finite numbers, not all zero) scaled to length 1; scaled by its
    largest component first, so that components near the float range do not overflow its
    norm (which would read as a zero vector, or divide by infinity)."""
    c = vector(name, value, length)
    big = max(abs(x) for x in c)
    if big == 0.0:
        _fail(name, value, f"must be a non-zero {what}")
    v = np.array(c) / big
    # np.linalg.norm's own formula for a vector, without its dispatch (a scripted tool's
    # quaternion is checked here twice a step): the same bits.
    return tuple(float(x) for x in v / math.sqrt(v.dot(v)))


def positive_vector(name: str, value, length: int = 3) -> tuple[float, ...]:
    v = vector(name, value, length)
    if not all(c > 0.0 for c in v):
        _fail(name, value, "every component must be > 0")
    return v


def positive_int(name: str, value, maximum: int = MAX_INT, minimum: int = 1) -> int:
    """An integer in ``[minimum, maximum]`` (bools and floats rejected; ``minimum`` >= 1)."""
    # Below 1 "an integer >= 1" (its maximum is for the rare value above it); a larger minimum is said with the range.
    allowed = "must be an integer >= 1" if minimum == 1 else f"must be an integer in [{minimum}, {maximum}]"
    if isinstance(value, bool) or not isinstance(value, int) and not (hasattr(value, "__index__")):
        _fail(name, value, allowed)
    try:
        v = int(value.__index__())
    except TypeError:  # a float or empty numpy array has __index__ too, and said only numpy's 'only integer scalar arrays'
        _fail(name, value, allowed)
    if v < minimum:
        _fail(name, value, allowed)
    if v > maximum:
        _fail(name, value, f"must be an integer in [{minimum}, {maximum}]")
    return v


def boolean(name: str, value) -> bool:
    """``True`` or ``False`` (numpy bools too); not 1, not ``"yes"``."""
    if not isinstance(value, (bool, np.bool_)):
        _fail(name, value, "must be True or False")
    return bool(value)


def selection(name: str, fn, points, what: str = "rest positions"):
    """The boolean mask a user's predicate ``fn(points) -> bool (N,)`` returns, checked: an
    exception it raises, a result of another length, or one that is not boolean (floats
    were cast, ``x[:, 0]`` pinning every particle off x = 0 and NaN every particle) is a
    ``ValueError`` naming ``name``."""
    if not callable(fn):
        raise ValueError(f"{name} = {shorten(fn)!r} is not allowed: must be callable as {name}({what}) -> bool array")
    try:
        out = fn(points.copy())
    except Exception as e:  # noqa: BLE001 (the user's code: its error, named)
        raise ValueError(f"{name} is not allowed: {name}({what}) raised {type(e).__name__}: {e}") from e
    a = np.asarray(out)
    if a.dtype != np.bool_:
        raise ValueError(f"{name} is not allowed: it returned {a.dtype} values; it must return a bool array, one per "
                         f"position ({len(points)})")
    if a.shape != (len(points),):
        raise ValueError(f"{name} is not allowed: it returned shape {a.shape}; it must return one bool per position "
                         f"({len(points)})")
    return a


def coincident_points(pts: np.ndarray, spacing: float):
    """``(count, first)``: how many of the points ``pts`` (n, 3) lie within a millionth of
    ``spacing`` of an earlier one, and the first such place's index; ``(0, None)`` when none
    do (or the points spread too far for the cells, beyond 1e12 spacings). Two particles at
    one place never separate: the pressure's gradient has no direction at r = 0, and every fit
    sees a zero offset."""
    if len(pts) == 0 or not np.abs(pts).max() < 1e12 * spacing:
        return 0, None
    cells = np.floor(pts / (1e-6 * spacing)).astype(np.int64)
    _, first, counts = np.unique(cells, axis=0, return_index=True, return_counts=True)
    if not (counts > 1).any():
        return 0, None
    return int((counts - 1).sum()), int(first[np.argmax(counts > 1)])


def same_state(model, name: str, state) -> None:
    """``state`` is a ``State`` whose every array fits ``model``: size, precision and device.

    A step launched on arrays of another size reads and writes out of bounds (on the
    CPU: a crash), so this runs before every step. It is cheap: a state remembers the
    model it was last checked against, and forgets it when one of its arrays is replaced
    (``State.__setattr__``), so the full check runs once per state and model.
    """
    if getattr(state, "_checked_for", None) is model:
        return
    import warp as wp  # noqa: PLC0415 (checks stays light for the CLI's first checks)

    from .model import State  # noqa: PLC0415

    if not isinstance(state, State):
        _fail(name, state, "must be a warp_esph.State made by model.state()")
    n, K, T, dev = model.particle_count, model.max_neighbors, model.types, model.device
    want = {
        "x": ((n,), T.vec3), "v": ((n,), T.vec3), "F": ((n,), T.mat33), "alpha": ((n,), T.scalar),
        "F_p": ((n,), T.mat33), "x_lo": ((n,), T.vec3), "F_lo": ((n,), T.mat33), "F_flowed_lo": ((n,), T.mat33), "neighbors": ((n, K), wp.int32),
        "neighbor_count": ((n,), wp.int32), "guard": ((n,), wp.int32), "density": ((n,), T.scalar),
        "F_flowed": ((n,), T.mat33), "stress": ((n,), T.mat33), "F_inv": ((n,), T.mat33), "force": ((n,), T.vec3),
        "F_image": ((n,), T.mat33), "alpha_image": ((n,), T.scalar), "image_share": ((n,), T.scalar),
    }
    if model.image_plane is not None:
        want["F_image_flowed"] = ((n,), T.mat33)
        want["alpha_image_flowed"] = ((n,), T.scalar)
        want["image_stress"] = ((n,), T.mat33)
    # (Not neighbor_d2: the step keeps it in the solver's scratch, and reading it here would
    # allocate the state's own copy.) pressure_density: None unless a material is energy_spiky or isotropic.
    if getattr(state, "pressure_density", None) is not None:
        want["pressure_density"] = ((n,), T.scalar)
    # The rows of the colliders, tools and ghost floor: a state of a model with fewer static
    # colliders had the step write past its one-row collider_force.
    rows = max(1, model.world_count * (len(model.planes) + len(model.spheres) + len(model.boxes)))
    want["collider_force"] = want["collider_torque"] = ((rows,), T.vec3)
    tools = getattr(model, "tools", None)
    if tools is not None:
        want["tool_pose_p"] = ((2 * tools.count,), T.vec3)
        want["tool_pose_q"] = ((2 * tools.count,), tools.quat)
        want["tool_pose_dp"] = want["tool_pose_dr"] = ((2 * tools.count,), T.vec3)
        want["reaction_force"] = want["reaction_torque"] = ((tools.count * tools.world_count,), T.vec3)
    if getattr(model, "ghost_floor", None) is not None:
        nf, rows = model.ghost_floor.count, model.ghost_floor.rows
        want.update({"ghost_y": ((n,), T.vec3), "ghost_y_lo": ((n,), T.vec3), "ghost_weights": ((nf, rows), T.scalar),
                     "ghost_fill": ((nf, rows), T.scalar),
                     "ghost_rows": ((nf, rows), wp.int32), "ghost_count": ((nf,), wp.int32), "ghost_force": ((nf,), T.vec3)})
    for field, (shape, dtype) in want.items():
        arr = getattr(state, field, None)
        where = f"{name}.{field}"
        got_shape = getattr(arr, "shape", None)
        if arr is None:
            raise ValueError(f"{where} = None is not allowed: must be a Warp array of shape {shape}")
        if not isinstance(arr, wp.array):
            # Not by its attributes: a numpy array has shape, dtype and (numpy 2) device, and
            # 'state.x = positions' was refused as a state of another model.
            home = type(arr).__module__.split(".")[0]
            kind = type(arr).__qualname__ if home == "builtins" else f"{home}.{type(arr).__qualname__}"  # not 'builtins.list'
            raise ValueError(f"{where} = {shorten(arr)!r} is not allowed: it is a {kind}, not a Warp array; must be the Warp "
                             f"array of shape {shape} and dtype "
                             f"{getattr(dtype, '__name__', dtype)} the state was made with (write values into it with "
                             f"{where}.assign(...))")
        if tuple(got_shape) != shape:
            raise ValueError(
                f"{name} does not belong to this model: {field} has shape {tuple(got_shape)}, the model needs {shape} "
                f"({n} particles, max_neighbors = {K}); make states with model.state()"
            )
        if arr.dtype is not dtype:
            raise ValueError(
                f"{name} does not belong to this model: {field} is {getattr(arr.dtype, '__name__', arr.dtype)}, "
                f"the model is {T.scalar.__name__} (a state of a model of another precision?)"
            )
        if arr.device != dev:
            raise ValueError(f"{name} does not belong to this model: {field} is on {arr.device}, the model on {dev}")
    owner = getattr(state, "_model", None)
    if owner is not None and owner is not model:
        differ = _other_scene(state._made_of, model)
        if differ:
            # Of as many particles it passed every check above, and the step ran this model's rest
            # neighbourhoods on another body's positions (a 4 x 4 x 4 rubber block resting on the
            # ground, stepped by a 8 x 2 x 4 block's model: 16 m/s after 50 steps, 0.25 m/s by its own).
            raise ValueError(f"{name} does not belong to this model: it was made by another model, {differ}; make "
                             "states with model.state() (a model built again from the same builder takes them)")
    # Which arrays it holds, for step_states to see two states share none; forgotten with the
    # memo above when an array is replaced (State.__setattr__).
    state.__dict__["_arrays"] = {id(getattr(state, field)): field for field in want}
    state.__dict__["_checked_for"] = model


def _other_scene(made_of, model) -> str | None:
    """How the scene a state was made of (``Model.scene_snapshot`` of the model that made it,
    when it made it) differs from ``model`` now (its bodies, its rest positions), or None: one
    built again from the same builder is the same, and the model that made it edited since
    (``calibrate.jitter_model``) is not. Once per state and model (``same_state``'s memo)."""
    import numpy as np  # noqa: PLC0415

    theirs, x0 = made_of
    mine = [(b.name, b.start, b.count, b.world) for b in model.bodies]
    if mine != theirs:
        return f"whose bodies (name, first particle, count, world) are {shorten(theirs)}, this model's {shorten(mine)}"
    moved = np.flatnonzero(np.any(x0 != model.particle_x0, axis=1))
    if len(moved):
        k = int(moved[0])
        shown = [", ".join(f"{v:g}" for v in p[k]) for p in (x0, model.particle_x0)]
        if shown[0] == shown[1]:
            # Moved below :g's six digits (a jitter of 1e-7 m) both read alike: the shortest
            # digits of the precision that tell them apart.
            shown = [", ".join(str(v) for v in p[k]) for p in (x0, model.particle_x0)]
        return (f"whose rest positions differ at {plural(len(moved), 'particle')} (particle {k}: ({shown[0]}), this "
                f"model's ({shown[1]}))")
    return None


def step_states(model, state_in, state_out) -> None:
    """The checks of ``Solver.step``: two distinct states that both fit ``model`` and share no
    array."""
    same_state(model, "state_in", state_in)
    same_state(model, "state_out", state_out)
    if state_in is state_out:
        raise ValueError("state_out is state_in: the step reads state_in and writes state_out, pass two states")
    if not state_in._arrays.keys().isdisjoint(state_out._arrays):
        # A shallow copy (copy.copy(state_in)), or an array handed over (out.v = state_in.v):
        # the step wrote what it read, and state_in came back holding its result.
        shared = [field for key, field in state_in._arrays.items() if key in state_out._arrays]
        named = ", ".join(shared) if len(shared) <= 5 else f"{', '.join(shared[:5])}, ... ({len(shared)} arrays)"
        raise ValueError(f"state_out is not allowed: it shares state_in's {named}; the step reads state_in and writes "
                         "state_out, so each needs arrays of its own: make each with model.state() (out.assign(state_in) "
                         "copies one; copy.copy shares its arrays)")
    number("state_in.time", state_in.time)  # NaN ran on, a string failed deep in the step


def choice(name: str, value, allowed: Sequence[str]) -> str:
    # Text only: a numpy array of one allowed name compared equal and was kept as the array (a
    # later lookup failed with 'unhashable type'), an empty one raised numpy's truth-value error.
    if not isinstance(value, str) or value not in allowed:
        _fail(name, value, "must be one of " + ", ".join(repr(a) for a in allowed))
    return value


#: Unicode categories that break a line of text or act on a terminal: control characters
#: (newline, tab, NUL, ESC, DEL) and the line and paragraph separators.
LINE_BREAKING = ("Cc", "Zl", "Zp")


def breaks_line(text: str) -> bool:
    """Whether ``text`` holds a character of ``LINE_BREAKING``."""
    return any(unicodedata.category(c) in LINE_BREAKING for c in text)


#: Invisible format characters (Unicode category Cf): the bidirectional controls (U+202A-U+202E,
#: U+2066-U+2069) reorder the text shown around them, so a name holding one shows as another
#: ('evil\u202etxt.exe' as 'evilexe.txt'); the zero-width ones hide in it.
HIDDEN = ("Cf",)

#: What ``one_line`` allows, for its refusals.
ONE_LINE = ("one line of text (no control characters, no line breaks, no invisible format characters (Unicode "
            "category Cf, such as the bidirectional controls U+202A-U+202E and U+2066-U+2069))")


def hides_text(text: str) -> bool:
    """Whether ``text`` holds a character of ``HIDDEN``."""
    return any(unicodedata.category(c) in HIDDEN for c in text)


def escaped(text: str) -> str:
    """``text`` with each character of ``LINE_BREAKING`` or ``HIDDEN`` written as its
    ``\\uXXXX`` escape, for a message that shows a name outside ``repr`` (which escapes them
    itself): JSON's escapes leave a line separator (U+2028) and a C1 control (U+0085) as
    they are. Past U+FFFF as ``\\UXXXXXXXX`` (a tag character, U+E0020, was '\\ue0020', which
    TOML and Python read as U+E002 and a '0')."""
    return "".join((f"\\u{ord(c):04x}" if ord(c) <= 0xFFFF else f"\\U{ord(c):08x}")
                   if unicodedata.category(c) in LINE_BREAKING + HIDDEN else c for c in text)


def one_line(name: str, value: str, role: str) -> str:
    """``value``, a name that goes into one-line messages, log rows and file metadata
    (``role`` says where), refused when it is not one line of visible text: a newline in a
    body's name split every message naming it, a NUL went into the USD file's custom data,
    a right-to-left override made it show as another name."""
    if breaks_line(value) or hides_text(value):
        _fail(name, value, f"{role}, so it must be {ONE_LINE}")
    return value


#: The bidirectional embeddings, overrides and isolates: unlike the other format characters
#: (a zero-width joiner inside an emoji sequence, a zero-width non-joiner inside a Persian
#: word) they reorder the text shown after them, past the end of the text that holds them.
BIDI_CONTROLS = frozenset(chr(c) for c in [*range(0x202A, 0x202F), *range(0x2066, 0x206A)])


def one_line_text(name: str, value: str, role: str) -> str:
    """``value``, free text (not a name) that a caller may print on a line, refused when it is
    not one line or holds a character of ``BIDI_CONTROLS``. Its other format characters are
    text: '\U0001f469\u200d\U0001f52c' (an emoji sequence) was refused as a name is."""
    if breaks_line(value) or any(c in BIDI_CONTROLS for c in value):
        _fail(name, value, f"{role}, so it must be one line of text (no control characters, no line breaks, no "
                           "bidirectional embeddings, overrides or isolates, U+202A-U+202E and U+2066-U+2069)")
    return value


def one_line_label(text: str) -> str:
    """``text`` with each character of ``LINE_BREAKING`` or ``HIDDEN`` replaced by ``_``: for a
    name made from something the user did not write as a name (a mesh file's name), which
    only labels."""
    return "".join("_" if unicodedata.category(c) in LINE_BREAKING + HIDDEN else c for c in text)


# ---------------------------------------------------------------- files that cannot be read
#: What reading a damaged file raises besides ``ValueError``/``OSError``: a truncated or
#: garbled ``.npz`` (zip, zlib, struct), text that is not UTF-8. pxr raises
#: ``Tf.ErrorException`` (recognised by its module, so pxr need not be imported here).
READ_ERRORS = (zipfile.BadZipFile, zlib.error, EOFError, UnicodeDecodeError, struct.error)


def _raised_in_zipfile(exc: BaseException) -> bool:
    """Whether ``exc`` was raised inside the zipfile module: it raises RuntimeError (a
    damaged 'encrypted' flag) and NotImplementedError (a damaged compression method)."""
    tb = exc.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    return tb is not None and tb.tb_frame.f_globals.get("__name__", "").split(".")[0] == "zipfile"


def is_read_error(exc: BaseException) -> bool:
    """Whether ``exc`` is what a library raises on a damaged or foreign file."""
    if isinstance(exc, (RuntimeError, NotImplementedError)) and _raised_in_zipfile(exc):
        return True
    return isinstance(exc, READ_ERRORS) or type(exc).__module__.split(".")[0] == "pxr"


def read_reason(exc: BaseException) -> str:
    """One line from a reader's exception, in its words, not its class's name; pxr's C++
    location is dropped, its message kept."""
    text = re.sub(r"\s+", " ", str(exc)).strip()
    if isinstance(exc, OSError) and exc.strerror:
        # The system's reason alone: str() adds '[Errno 21]' and the path whole, which every
        # message names already, cut to its ends.
        text = exc.strerror
    # pxr wraps each message in "Error in '<C++ function>' at line N in file F : '<message>'".
    messages = re.findall(r" : '(.+?)'(?= Error in |$)", text)
    text = "; ".join(messages) or text
    if isinstance(exc, KeyError) and text:
        text = f"no {text}"  # a KeyError's words are the key alone: "'points'"
    elif not text:
        # Its class's name was said, the only words there were ('EOFError', 'KeyError: no details').
        text = "it ends early" if isinstance(exc, EOFError) else "its reader gave no reason"
    return text if len(text) <= 300 else text[:297] + "..."


#: How many bytes of a text input ``text_codec`` looks at for the NULs of UTF-16 without a mark.
TEXT_HEAD = 512


def text_codec(head: bytes) -> str:
    """The codec of text whose first bytes are ``head`` (``TEXT_HEAD`` of them, or all):
    ``utf-16`` past a UTF-16 byte-order mark; ``utf-16-le`` (``utf-16-be``) where ``head``'s
    byte pairs of that order hold at least two characters below U+0100, at least half of
    them, and no NUL or control character but tab, line breaks and form feed; else
    ``utf-8-sig`` (UTF-8, past a mark). UTF-8 text holds no NUL byte, and such a character
    is a NUL beside a byte of ASCII or Latin-1, so such a file is no UTF-8 whatever it is: it
    is UTF-16 saved without its mark ('iconv -t UTF-16LE'), which was refused by what its
    misread text lacked ('Invalid initial character for a key part', 'lacks the columns'),
    not a word of UTF-16."""
    if head[:2] in (codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE):
        return "utf-16"
    head = head[:TEXT_HEAD]
    codec, most = "utf-8-sig", 0
    for order in ("little", "big"):
        units = [int.from_bytes(head[i:i + 2], order) for i in range(0, len(head) - 1, 2)]
        latin = sum(u < 0x100 for u in units)
        # NULs on one side of the pairs alone was the test: a character U+xx00 ('一' U+4E00,
        # 'Ā') puts one on the other, and such text was read as UTF-8; a NUL or a control
        # character (an int16 .npy's '\x01\x00') is binary data, which was read as UTF-16
        # ('not valid JSON: Expecting value', not 'it is not text').
        # (two or more: three bytes of garbage are no text to guess a codec from)
        if latin >= max(2, most + 1) and 2 * latin >= len(units) and not any(u < 0x20 and u not in (9, 10, 12, 13) for u in units):
            codec, most = f"utf-16-{order[0]}e", latin
    return codec


def text_encoding(path) -> str:
    """The codec a text input (a scene file, a JSON file, a force log, a point cloud) is read
    with, ``text_codec`` of its first bytes: UTF-16 with a byte-order mark (Excel's 'Unicode
    Text', PowerShell 5's ``>``, which were read as UTF-8 and refused as garbage or 'not
    text') or without, else UTF-8. A file that cannot be opened is left to its reader's
    ``open``, which says why; so is one that is no regular file: a pipe (a shell's ``<(...)``)
    is not looked into, since the bytes read would be gone for its reader."""
    try:
        if not os.path.isfile(path):
            return "utf-8-sig"
        with open(path, "rb") as f:
            head = f.read(TEXT_HEAD)
    except (OSError, ValueError, TypeError):
        return "utf-8-sig"
    return text_codec(head)


def json_file(what: str, path):
    """The parsed JSON document of the file ``path``; a ``ValueError`` naming ``what`` and the
    file where it cannot be read or is not JSON."""
    p = os.fspath(path)

    def unique(pairs):
        # A key given twice kept its last value without a word (a scene file's repeated key
        # is refused, as TOML does).
        seen = set()
        for key, _ in pairs:
            if key in seen:
                raise ValueError(f"{what} {shown_path(p, False)} is not allowed: the key {key!r} appears twice in one object")
            seen.add(key)
        return dict(pairs)

    try:
        # utf-8-sig: Notepad's UTF-8 starts with a byte-order mark, which json refused with
        # advice for Python code ('decode using utf-8-sig'); JSON is UTF-8 whatever the locale.
        with open(p, encoding=text_encoding(p)) as f:
            return json.load(f, object_pairs_hook=unique)
    except OSError as e:
        # (strerror: the error's own text repeats the path)
        raise ValueError(f"{what} {shown_path(p, False)} cannot be read: {e.strerror or e}") from None
    except json.JSONDecodeError as e:
        raise ValueError(f"{what} {shown_path(p, False)} is not valid JSON: {e}") from None
    except UnicodeDecodeError:  # bytes that are not text: not the JSON file asked for
        raise ValueError(f"{what} {shown_path(p, False)} is not valid JSON: it is not text (a damaged or foreign file?)") from None
    except RecursionError:
        raise ValueError(f"{what} {shown_path(p, False)} cannot be read: arrays or objects nested too deeply") from None


#: Bytes a writer adds to an output's name for its working copies and side files
#: (``.NAME.wa.usdc``, ``.NAME.<pid>.publish.usdc``, ``NAME.checkpoint.npz``, ``NAME_tools.json``).
OUTPUT_NAME_SLACK = 40


def _name_max(folder: str) -> int:
    """The longest file name ``folder``'s file system takes (255 where it does not say, or
    says no limit)."""
    while folder and not os.path.isdir(folder):
        folder = os.path.dirname(folder)
    try:
        n = int(os.pathconf(folder or ".", "PC_NAME_MAX"))
    except (OSError, ValueError, AttributeError):
        n = -1
    return n if n > 0 else 255


class Rebuilt:
    """A base of an exception made of more than its message: pickle rebuilds an exception as
    ``cls(*args)``, which such an ``__init__`` refuses (``missing 2 required keyword-only
    arguments``), so one raised in a worker process (``concurrent.futures``,
    ``multiprocessing``) broke the pool (``BrokenProcessPool``; ``multiprocessing.Pool``
    hangs). It is rebuilt from its ``args`` and fields without ``__init__``; a field named in
    ``LOCAL`` comes back None."""

    #: Fields holding this process's objects (a Model's Warp arrays), which pickle refuses: the
    #: refusal replaced the exception in the parent (a fit's memory refusal read as the Model's).
    LOCAL: tuple[str, ...] = ()

    def __reduce__(self):
        return _rebuilt, (type(self), self.args), {k: None if k in self.LOCAL else v for k, v in self.__dict__.items()}


def _rebuilt(cls, args):
    e = cls.__new__(cls, *args)
    if isinstance(e, OSError):  # errno and strerror live in OSError's own slots, set by its __init__
        OSError.__init__(e, *args)
    e.args = args
    return e


class OutputWriteError(Rebuilt, OSError):
    """A command's output that could not be written once its work was done or under way (a full
    disk): the CLI exits 4 with its text, which names the file and what is kept (``cause``: the
    write's own error)."""

    def __init__(self, message: str, cause: OSError):
        super().__init__(cause.errno, cause.strerror or str(cause))
        self.message, self.cause = message, cause

    def __str__(self):
        return self.message


def interrupted(kept: str) -> KeyboardInterrupt:
    """A Ctrl-C (or SIGTERM) that stopped a command writing several files, with what its files
    keep (``kept``, e.g. '1 of the 3 frames are written whole in out'): the CLI's one line says
    it after 'interrupted', as an interrupted run names the frames its file keeps. A plain
    ``KeyboardInterrupt`` with ``kept`` set, not a subclass: Python ends a script on an
    uncaught ``KeyboardInterrupt`` with the SIGINT status (130) only for that exact type, and a
    script stopped in ``render_usd`` exited 1."""
    e = KeyboardInterrupt(kept)
    e.kept = kept
    return e


def stopped_writing(exc: BaseException, kept: str, frame: int | None = None) -> None:
    """Record on ``exc``, an error a writer of several files did not expect (not a write's
    ``OSError``, not an interrupt), raised once it began writing, what its files keep
    (``kept``, e.g. '2 of the 4 frames are written whole in out') and the frame it was at
    (``frame``; None: past the frames, while the file of them was written). The CLI says it
    in one line, naming the error and where it was raised, and exits 1 (it was a traceback,
    or for a ``ValueError`` exit 2, 'bad input', saying nothing of what was written)."""
    if not isinstance(exc, Exception) or isinstance(exc, OSError) or getattr(exc, "kept", None) is not None:
        return
    with contextlib.suppress(AttributeError):  # (an exception type without a __dict__)
        exc.kept, exc.stopped_frame = kept, frame


def special_file(path) -> str | None:
    """What ``path`` is where it exists and is neither a regular file nor a folder (a device,
    a named pipe, a socket; through a link too), else None. A writer renames its file over
    the path (``replaced_atomically``): ``fit -o /dev/null`` run as root replaced the device
    with a regular file holding the fit's JSON, and reported it written."""
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return None
    for test, kind in ((stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISFIFO, "a named pipe"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return kind
    return None


def _not_plain(p: str) -> tuple[str, str] | None:
    """``(what it is, the cure)`` where a file renamed over ``p`` would replace something that
    is not a plain file: a special file (``special_file``), or a symbolic link, which became
    a regular file and left its target as it was (``render -o link.png``); else None. A link
    is refused rather than written through: every output is renamed into place, and through
    a link the working copy, the checks of its folder and the rename would all be the
    target's, which the command line never named."""
    kind = special_file(p)
    if kind is not None:
        return kind, "give the name of a file"
    if os.path.islink(p):
        return (f"a symbolic link (to {os.readlink(p)!r})",
                "give the path of the file it links to, or another name")
    return None


def refuse_special(what: str, p: str) -> None:
    """Refuse an output ``p`` (the parameter or option ``what``) that a file renamed over it
    would replace although it is no plain file (``_not_plain``): every writer, the commands'
    and the Python API's, refuses it alike."""
    found = _not_plain(p)
    if found is not None:
        raise ValueError(f"{what} = {shown_path(p)} is not allowed: it is {found[0]}, not a file; the output is written beside it "
                         f"and renamed over it, which would replace it: {found[1]}")


def output_files(what: str, folder, names) -> None:
    """Refuse, before the work, a folder output ``folder`` (the option ``what``) in which a
    file of ``names`` the command writes is a special file or a symbolic link
    (``_not_plain``), naming the option and the file: ``export -o dir`` over a named pipe
    ``dir/frame_00001.vtu`` wrote frame 0 and then stopped, naming a ``path`` no option is. A
    folder there is refused too: met when its file came, it was 'Is a directory', exit 4 as a
    full disk, and ``run --export`` had run the whole simulation first."""
    folder = os.fspath(folder)
    if not os.path.isdir(folder):
        return
    for name in names:
        file = os.path.join(folder, name)
        found = _not_plain(file)
        if found is not None:
            raise ValueError(f"{what} = {shown_path(folder)} is not allowed: {shown_path(file)} in it is {found[0]}, not a file; the "
                             f"output is written beside it and renamed over it, which would replace it: remove it, "
                             f"or give another folder")
        if os.path.isdir(file):
            raise ValueError(f"{what} = {shown_path(folder)} is not allowed: {shown_path(file)} in it is a folder, where a file is "
                             "written: remove it, or give another folder")


def remove_frame_files(folder, ext: str, keep=()) -> None:
    """Remove from ``folder`` the frame files an earlier export or render left there, but for
    ``keep``: ``frame_NNNNN.<ext>``, and for ``vtu`` the ``frames.pvd`` that lists them; no
    other file. A new export of fewer frames left the earlier ones beside its own, as if they
    were (and its ``frames.pvd`` listed only the new)."""
    folder = os.fspath(folder)
    if not os.path.isdir(folder):
        return
    keep = {os.path.basename(f) for f in keep}
    for name in os.listdir(folder):
        stem, _, rest = name.partition(".")
        digits = stem[6:]
        # Only a name the writers give (frame_3.vtu, frame_00003.old.vtu are someone else's).
        frame = stem.startswith("frame_") and digits.isascii() and digits.isdigit() and stem == f"frame_{int(digits):05d}"
        ours = (frame and rest == ext) or (ext == "vtu" and name == "frames.pvd")
        if ours and name not in keep and os.path.isfile(os.path.join(folder, name)):
            os.remove(os.path.join(folder, name))


def usd_output(what: str, path, written=None) -> None:
    """Refuse ``path`` (where a USD file is written: ``written``, default ``path`` itself) where
    its absolute path is not UTF-8 text. USD takes file names as UTF-8 strings, so a name of
    other bytes (which Python holds as surrogate escapes) failed at the first save: a fit or a
    run's set-up done, then a bare UnicodeEncodeError naming no option."""
    full = not_utf8_path(path if written is None else written)
    if full is not None:
        raise ValueError(f"{what} = {shown_path(path)} is not allowed: USD names its files in UTF-8 text, "
                         f"and {shown_path(full)} is not; give a path of UTF-8 text")


def usd_input(path, verb: str = "read") -> None:
    """Refuse a USD file to read at ``path`` where its absolute path is not UTF-8 text, as
    ``usd_output`` refuses one to write: pxr's failure was "cannot read '\\udcfb.usdc': 'utf-8'
    codec can't encode ...", which said neither what was wrong nor what is allowed."""
    full = not_utf8_path(path)
    if full is not None:
        raise ValueError(f"cannot {verb} {shown_path(path)}: USD names its files in UTF-8 text, and "
                         f"{shown_path(full)} is not; give a path of UTF-8 text (rename the file or its folder)")


def not_utf8_path(path) -> str | None:
    """``path`` made absolute where it is not UTF-8 text (bytes Python holds as surrogate
    escapes), else None."""
    full = os.path.abspath(os.fsdecode(os.fspath(path)))
    try:
        full.encode("utf-8")
    except UnicodeEncodeError:
        return full
    return None


@contextlib.contextmanager
def replaced_atomically(path):
    """Yields a working name beside ``path`` for a writer to fill; once it returns, that file
    is renamed over ``path`` (``os.replace``: the file appears whole or not at all, and an
    older ``path`` stays intact until then). On an error or an interrupt the working file is
    removed and ``path`` is as it was. The working name keeps ``path``'s extension, so
    writers that read the format from it still can."""
    p = os.fspath(path)
    # ("path" is save_state's own parameter; the commands refuse it by option first:
    # output_place, output_files.)
    refuse_special("path", p)
    head, name = os.path.split(p)
    stem, ext = os.path.splitext(name)
    tmp = os.path.join(head, f".{stem}.{os.getpid()}.part{ext}")  # two processes writing one name keep apart
    try:
        yield tmp
        os.replace(tmp, p)
    except BaseException as e:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(e, OSError) and e.errno is not None and e.filename in (None, tmp):
            # A failed write names no file (a full disk met by write() or close()) or the hidden
            # working name: the one line said '[Errno 28] No space left on device' and no more.
            raise OSError(e.errno, e.strerror, p) from e
        raise


def bare_path(p: str) -> str:
    """``p`` without the separators it ends in (``'taken/'``: ``'taken'``; ``'/'`` stays)."""
    return p.rstrip(os.sep + (os.altsep or "")) or p


def file_identity(path):
    """What makes two paths one file: its device and inode where it exists, so that a hard
    link is the file it links (its real path is another), as a symbolic link or another
    spelling of the path is; else its real path, as where the file system numbers no inode
    (``st_ino`` 0, which Python promises identifies a file only where it is not 0)."""
    try:
        st = os.stat(path)
    except OSError:
        return os.path.realpath(path)
    except ValueError:  # a NUL in it: no file, which its reader refuses by name ('embedded null byte' named none)
        return os.fspath(path)
    if st.st_ino == 0:
        # Every file of such a system reads inode 0: two distinct files were one (a target
        # refused as given twice, an output as an input).
        return os.path.realpath(path)
    return st.st_dev, st.st_ino


def output_place(what: str, path, folder: bool = False) -> str:
    """``path`` where a command will write a file (``folder``: a folder of files), checked
    before the work that fills it: a ``ValueError`` naming ``what`` where something of the
    other kind is in the way, its folder (a folder output's parent) does not exist, or it
    cannot take a new file, or where ``path`` is not one line of text (``breaks_line``).
    Creates nothing."""
    if not isinstance(path, (str, os.PathLike)):  # None, 123: a TypeError from os.fspath before
        raise ValueError(f"{what} = {shorten(path)!r} is not allowed: must be a path")
    p = os.fspath(path)
    if not p or "\0" in p:
        raise ValueError(f"{what} = {shown_path(p)} is not allowed: must be a path (not empty, no NUL character)")
    if breaks_line(p) or any(c in BIDI_CONTROLS for c in p):
        # As a scene's name, which names its default output: a newline split the commands'
        # one-line reports ('wrote a<newline>b.usdc: ...', the reaction log's), a tab or an
        # escape acted on the terminal, a bidi override showed the rest of the line reversed.
        raise ValueError(f"{what} = {shown_path(p)} is not allowed: the commands name their outputs in one-line messages, so it "
                         "must be one line of text (no control characters, no line breaks, no bidirectional "
                         "embeddings, overrides or isolates, U+202A-U+202E and U+2066-U+2069)")
    try:
        name = os.fsencode(os.path.basename(os.path.normpath(p)))
    except UnicodeError:
        raise ValueError(f"{what} = {shown_path(p)} is not allowed: it is not a name this file system can hold") from None
    # The writers keep a working copy beside the file, its name the file's and up to
    # OUTPUT_NAME_SLACK more bytes: a longer name failed mid-run with a bare 'File name too long'.
    longest = _name_max(os.path.dirname(os.path.abspath(p)) or ".") - OUTPUT_NAME_SLACK
    if len(name) > longest:
        raise ValueError(f"{what} = {shown_path(p)} is not allowed: its name is {len(name)} bytes long, more than the {longest} "
                         "this folder's file names leave room for")
    # 'taken/' does not exist where 'taken' is a file (ENOTDIR), and passed: the sweep or fit
    # ran to its end, then os.makedirs failed with a bare '[Errno 17] File exists'.
    bare = bare_path(p)
    if os.path.exists(bare) and os.path.isdir(bare) != folder:
        # A device or a named pipe said as what it is: '/dev/null' was 'a file'.
        raise ValueError(f"{what} = {shown_path(p)} is not allowed: it is {(special_file(bare) or 'a file') if folder else 'a folder'}; "
                         f"a {'folder' if folder else 'file'} is written there")
    if not folder:
        refuse_special(what, p)
    # A folder output is created itself, but never its parents: a typo in a parent's name
    # ('/data/rsults/sweep') built a whole tree of folders nobody meant, where a file output
    # (run -o, render -o a.png) was refused; every command now refuses it alike.
    parent = p if folder and os.path.isdir(p) else (os.path.dirname(os.path.abspath(p)) or ".")
    if not os.path.isdir(parent):
        raise ValueError(f"{what} = {shown_path(p)} is not allowed: its folder {shown_path(parent)} does not exist or is not a "
                         f"folder{tilde_note(p)}")
    try:  # the one reliable test that a file can be created there
        import tempfile  # noqa: PLC0415

        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError as e:
        raise ValueError(f"{what} = {shown_path(p)} is not allowed: {shown_path(parent)} cannot take a new file "
                         f"({e.strerror or e})") from None
    return p


def file_error(path, exc: BaseException, verb: str = "read") -> ValueError:
    """``ValueError("cannot <verb> '<path>': <reason>")`` for a damaged or foreign file."""
    return ValueError(f"cannot {verb} {shown_path(str(path))}: {read_reason(exc)}")
