"""Parameter sweeps: run a scene for many material values, one summary row per sample.

::

    table = sweep("dough_drop", ["yield_stress=100:1000:log:8", "flow_rate=50:500:lin:4"],
                  frames=30, workers=2)
    table.column("max_height")      # numpy array, one value per sample (NaN where it failed)
    table.to_csv("sweep.csv")

A parameter is a material field of ``Model.MATERIAL_FIELDS`` (the names ``fit`` uses):
``yield_stress`` sets it in every material (an elastic particle floor's is left as built, as
in ``fit``), ``dough.yield_stress`` in the materials of the body ``dough``,
``0.yield_stress`` in material 0. A spec is ``NAME=LO:HI:SCALE:N``
(``SCALE`` is ``lin`` or ``log``; ``N`` levels on the grid), ``NAME=LO:HI[:SCALE]`` for
``random``/``lhs`` sampling (``samples`` draws in all), ``NAME=A,B,C`` (these values) or
``NAME=V`` (one value for every sample).

Samples run one per process (``workers``, default every core; spawned processes, each
with its own Warp context) or as Ray tasks (``ray=ADDRESS``, the optional extra
``warp-esph[ray]``). Every sample is a deterministic CPU run of its own model, and the
sample values are drawn in the calling process from ``seed``, so the table does not
depend on where or in which order the samples ran; only ``wall_s`` (the seconds one
sample took) varies from run to run. Rows are sorted by sample index.

A sample that diverges (``SimulationError``; also a body the scene shows blowing up,
``Scene.diverges``, found past the run monitor's bounds at its end) or whose values make an invalid material is
a row with ``status = "failed"`` and the one-line ``reason`` (an invalid material's names
it: ``ValueError: material 1 (body 'blob'): Material.lam = ...``); the sweep goes on. A sweep
the material refuses in every sample, or one of a flow parameter (``yield_stress``,
``flow_rate``, ``hardening``) whose materials can flow in no sample (it changes nothing), is
refused (``ValueError``) before any sample. A reason
is the stop's, or ``StepRefusal: `` and the refusal's, without a run's advice, which names one caller's options
(``dt=`` or ``--dt``): the table is the same for ``sweep()`` and ``warp-esph sweep``; a
divergence adds the sample's stable step. A value the precision does not hold is advised
in both spellings, ``use dtype=float64 (--dtype float64)``.

A sweep that stopped goes on with ``resume=`` (the CLI's ``--resume``): the rows of its
table are kept and only the samples it lacks run, after a check that the table is of this
same sweep (``SweepTable.identity``, recorded in ``sweep.json`` and the Parquet table).

``parallel_map`` is the executor underneath, for other per-sample jobs (e.g. one fit per
starting point of a multi-start fit, with the starting points from ``sample_points``).
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import itertools
import json
import math
import multiprocessing
import os
import re
import sys
import time
import warnings
from collections.abc import Callable, Mapping, Sequence

import numpy as np

from . import checks

__all__ = ["Param", "SweepTable", "sweep", "parse_param", "sample_points", "parallel_map", "ItemError", "write_outputs", "SAMPLINGS",
           "MAX_SAMPLES", "SUMMARY_COLUMNS"]

SAMPLINGS = ("grid", "random", "lhs")
SCALES = ("lin", "log")
#: Default cap on the number of samples: a grid of 8 levels in 6 parameters already has 262144.
MAX_SAMPLES = 10000
#: The summary quantities of every row (``y`` is up), in table order.
SUMMARY_COLUMNS = ("centroid_height", "max_height", "radial_spread", "max_radius", "kinetic_energy")

# Lower limits the Material checks impose (Material.__post_init__), checked before any
# sample runs so a range that cannot work is reported as bad input, not as N failures.
_MINIMUM = {"mu": (0.0, False), "yield_stress": (0.0, True), "flow_rate": (0.0, True),
            "pressure_stiffness": (0.0, True), "viscosity": (0.0, True)}


def _own_words(name: str) -> str:
    """How a refusal names ``sweep``'s parameter ``name`` to a Python caller: itself, and a
    spec of ``params`` as its entry (``warp-esph sweep`` passes ``cli.option_flag``: ``--param``)."""
    return "params entry" if name == "param" else name


def _cli(flag) -> bool:
    """Whether ``flag`` names the command's options."""
    return flag("sample").startswith("--")


def _set(flag, name: str, value: str) -> str:
    """``name`` set to ``value`` in the caller's words: ``--sample lhs``, ``sample = 'lhs'``."""
    return f"{flag(name)} {value}" if _cli(flag) else f"{name} = {value!r}"


def _either(flag, conj: str) -> str:
    """The two samplings that draw, in the caller's words: ``--sample random or lhs``,
    ``sample = 'random' or 'lhs'``."""
    return f"{flag('sample')} random{conj}lhs" if _cli(flag) else f"sample = 'random'{conj}'lhs'"


def _fields() -> tuple[str, ...]:
    from .model import Model  # noqa: PLC0415

    return Model.MATERIAL_FIELDS


@dataclasses.dataclass(frozen=True)
class Param:
    """One swept parameter: ``name`` (``field``, ``body.field`` or ``index.field``) and either
    a range ``lo..hi`` on a ``lin``/``log`` scale with ``n`` grid levels (``None``: only for
    random/LHS sampling), or explicit ``values``."""

    name: str
    lo: float | None = None
    hi: float | None = None
    scale: str = "lin"
    n: int | None = None
    values: tuple[float, ...] | None = None

    @property
    def field(self) -> str:
        return self.name.rsplit(".", 1)[-1]

    @property
    def target(self) -> str | None:
        """The body name or material index before the dot; ``None``: every material."""
        return self.name.rsplit(".", 1)[0] if "." in self.name else None

    def levels(self, flag=None) -> np.ndarray:
        """The grid levels. ``flag``: as ``sample_points``'."""
        flag = flag or _own_words
        if self.values is not None:
            return np.asarray(self.values, dtype=np.float64)
        if self.n is None:
            raise ValueError(f"{flag('param')} {self.name}: no level count is not allowed with grid sampling: "
                             f"give NAME=LO:HI:SCALE:N (e.g. {self.name}={self.lo:g}:{self.hi:g}:{self.scale}:4), "
                             f"or use {_either(flag, '|' if _cli(flag) else ' or ')} with {flag('samples')} N")
        if self.n == 1:
            if self.scale == "lin":
                return np.array([self.lo])
            product = self.lo * self.hi
            # sqrt(LO) sqrt(HI) where LO HI leaves the floats: 1e-200 x 1e-150 was 0 (a sample
            # outside its range), 1e200 x 1e300 inf; sqrt(LO HI) elsewhere, exact as 1e2:1e4 -> 1e3.
            exact = sys.float_info.min <= product <= sys.float_info.max
            return np.array([math.sqrt(product) if exact else math.sqrt(self.lo) * math.sqrt(self.hi)])
        if self.scale == "log":
            return np.geomspace(self.lo, self.hi, self.n)
        return np.linspace(self.lo, self.hi, self.n)

    def from_unit(self, u: np.ndarray) -> np.ndarray:
        """Map ``u`` in [0, 1) onto the range (random and LHS sampling)."""
        if self.values is not None:
            v = np.asarray(self.values, dtype=np.float64)
            return v[np.minimum((u * len(v)).astype(np.int64), len(v) - 1)]
        if self.scale == "log":
            return np.exp(math.log(self.lo) + u * (math.log(self.hi) - math.log(self.lo)))
        return self.lo + u * (self.hi - self.lo)


def _number(name: str, spec: str, text: str, what: str, flag) -> float:
    try:
        v = checks.read_number(text)
    except ValueError:
        raise ValueError(f"{flag('param')} {checks.shorten(spec)!r}: {what} = {checks.shorten(text)!r} is not allowed: must be a number") from None
    why = checks.unheld_refusal(v)
    if why:  # 1e-400 was swept as 0
        raise ValueError(f"{flag('param')} {checks.shorten(spec)!r}: {what} = {checks.shorten(v)} is not allowed: {why}")
    if not math.isfinite(v):
        raise ValueError(f"{flag('param')} {checks.shorten(spec)!r}: {what} = {checks.shorten(text)!r} is not allowed: must be finite")
    return v


def parse_param(spec, *, flag=None) -> Param:
    """A ``Param`` from ``NAME=LO:HI:SCALE:N``, ``NAME=LO:HI[:SCALE]``, ``NAME=A,B,C`` or ``NAME=V``.

    Checks the syntax, the field name and the range (``lo < hi``, ``lo > 0`` on a log
    scale, ``N >= 1``, values the material allows); the body or material index is checked
    against the scene by ``sweep``. ``flag``: as ``sample_points``'.
    """
    flag = flag or _own_words
    if isinstance(spec, Param):
        p = spec
    else:
        text = str(spec).strip()
        name, sep, rng = text.partition("=")
        name = name.strip()
        if not sep or not name or not rng.strip():
            raise ValueError(f"{flag('param')} {checks.shorten(text)!r} is not allowed: use NAME=LO:HI:SCALE:N (e.g. yield_stress=100:1000:log:8), "
                             f"NAME=LO:HI:SCALE for random/lhs sampling, NAME=A,B,C or NAME=V")
        rng = rng.strip()
        if ":" in rng:
            parts = [s.strip() for s in rng.split(":")]
            if len(parts) not in (2, 3, 4):
                raise ValueError(f"{flag('param')} {checks.shorten(text)!r} is not allowed: a range is LO:HI, LO:HI:SCALE or LO:HI:SCALE:N "
                                 f"(SCALE lin or log), not {len(parts)} fields")
            lo = _number(name, text, parts[0], "LO", flag)
            hi = _number(name, text, parts[1], "HI", flag)
            scale = parts[2] if len(parts) > 2 else "lin"
            if scale not in SCALES:
                raise ValueError(f"{flag('param')} {checks.shorten(text)!r}: SCALE = {checks.shorten(scale)!r} is not allowed: must be lin or log")
            n = None
            if len(parts) == 4:
                try:
                    n = int(parts[3])
                except ValueError:
                    raise ValueError(f"{flag('param')} {checks.shorten(text)!r}: N = {checks.shorten(parts[3])!r} is not allowed: must be an integer >= 1") from None
            p = Param(name, lo, hi, scale, n)
        else:
            values = tuple(_number(name, text, s.strip(), "value", flag) for s in rng.split(","))
            p = Param(name, values=values)
    fields = _fields()
    if not isinstance(p.name, str) or p.field not in fields or (p.target is not None and not p.target):
        from .material import LAB_QUANTITIES, lab_value_note, material_setting_note  # noqa: PLC0415

        lab = (f"{lab_value_note(p.field, 'parameter')} (sweep {LAB_QUANTITIES[p.field][0]})"
               if isinstance(p.name, str) and p.field in LAB_QUANTITIES else "")
        setting = material_setting_note(p.field, "swept", _cli(flag)) if isinstance(p.name, str) else ""
        raise ValueError(f"{flag('param')} {checks.shorten(p.name)!r} is not allowed: unknown parameter; name one of {', '.join(fields)}, "
                         f"optionally prefixed by a body name, a material index or a scene file's material name (e.g. dough.yield_stress, "
                         f"0.yield_stress)"
                         f"{lab}{setting}")
    if p.values is not None:
        if not p.values:
            raise ValueError(f"{flag('param')} {p.name}: values = () is not allowed: give at least one value")
        for v in p.values:  # None, 'x' and NaN failed in numpy or ran as failed samples
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not math.isfinite(v):
                raise ValueError(f"{flag('param')} {p.name}: value {checks.shorten(v)!r} is not allowed: must be a finite number")
        twice = next((v for k, v in enumerate(p.values) if v in p.values[:k]), None)
        if twice is not None:
            # Each value is a sample (a grid's level): 1,1 ran the same sample twice.
            raise ValueError(f"{flag('param')} {p.name}: value {checks.shorten(twice)!r} is not allowed twice: each value is a sample; give it once")
        lows = list(p.values)
    else:
        if p.scale not in SCALES:
            raise ValueError(f"{flag('param')} {p.name}: scale = {checks.shorten(p.scale)!r} is not allowed: must be lin or log")
        real = (int, float, np.integer, np.floating)
        if isinstance(p.lo, bool) or isinstance(p.hi, bool) or not (isinstance(p.lo, real) and isinstance(p.hi, real)):
            # np.int64(1) and np.float32(10) were refused as 'need LO < HI'.
            raise ValueError(f"{flag('param')} {p.name}: LO = {checks.shorten(p.lo)!r}, HI = {checks.shorten(p.hi)!r} is not allowed: LO and HI must be numbers")
        p = dataclasses.replace(p, lo=float(p.lo), hi=float(p.hi))
        if not p.lo < p.hi:
            raise ValueError(f"{flag('param')} {p.name}: LO = {checks.shorten(p.lo)!r}, HI = {checks.shorten(p.hi)!r} is not allowed: need LO < HI")
        if p.scale == "log" and p.lo <= 0.0:
            raise ValueError(f"{flag('param')} {p.name}: LO = {checks.shorten(p.lo)!r} is not allowed on a log scale: need LO > 0 (or use lin)")
        if not (math.isfinite(p.lo) and math.isfinite(p.hi)) or (p.scale == "log" and p.lo < sys.float_info.min):
            # 1e-320 ran every sample, then its log axis failed to draw (and no table was kept).
            raise ValueError(f"{flag('param')} {p.name}: LO = {checks.shorten(p.lo)!r}, HI = {checks.shorten(p.hi)!r} is not allowed: need finite bounds, and on a "
                             f"log scale LO >= {sys.float_info.min:.3g}")
        if p.scale == "lin" and not math.isfinite(p.hi - p.lo):
            # Every value drawn from -1.7e308:1.7e308 was inf (lo + u (hi - lo)), the grid's nan and inf.
            raise ValueError(f"{flag('param')} {p.name}: LO = {checks.shorten(p.lo)!r}, HI = {checks.shorten(p.hi)!r} is not allowed: on a lin scale HI - LO must "
                             f"be a finite number (at most {sys.float_info.max:.3g})")
        if p.n is not None and (isinstance(p.n, bool) or not isinstance(p.n, (int, np.integer)) or p.n < 1):
            raise ValueError(f"{flag('param')} {p.name}: N = {checks.shorten(p.n)!r} is not allowed: must be an integer >= 1")
        lows = [p.lo]
    if p.field in _MINIMUM:
        bound, inclusive = _MINIMUM[p.field]
        bad = [v for v in lows if v < bound or (v == bound and not inclusive)]
        if bad:
            op = ">=" if inclusive else ">"
            raise ValueError(f"{flag('param')} {p.name}: value {checks.shorten(bad[0])!r} is not allowed: {p.field} must be {op} {bound:g}")
    return p


def _as_params(params, flag) -> list[Param]:
    if isinstance(params, (str, Param)):
        params = [params]
    if params is None or not hasattr(params, "__iter__"):  # None, 123: a TypeError before
        raise ValueError(f"params = {checks.shorten(params)!r} is not allowed: give specs ('yield_stress=100:1000:log:8'), Params "
                         "or a mapping {name: values}")
    if isinstance(params, Mapping):
        params = [Param(k, values=tuple(np.atleast_1d(np.asarray(v, dtype=object)).tolist())) if not isinstance(v, str)
                  else f"{k}={v}" for k, v in params.items()]
    out = [parse_param(p, flag=flag) for p in params]
    if not out:
        raise ValueError(f"{'--param' if _cli(flag) else 'params = []'} is not allowed: give at least one "
                         f"{flag('param')} NAME=LO:HI:SCALE:N")
    names = [p.name for p in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"{flag('param')} {dup[0]} is not allowed twice: give each parameter once")
    return out


def sample_points(params, sample: str = "grid", samples: int | None = None, seed: int | None = None,
                  max_samples: int = MAX_SAMPLES, *, flag=None) -> list[dict[str, float]]:
    """The sample values, ``[{name: value}]`` in sample order.

    ``grid``: every combination of the levels, the last parameter varying fastest.
    ``random``: ``samples`` independent uniform draws (uniform in log for ``log``).
    ``lhs``: a Latin hypercube of ``samples`` points: each parameter's range is cut into
    ``samples`` equal strata (equal in log for ``log``) and each stratum holds exactly one
    sample. Draws come from ``numpy.random.default_rng(seed)`` (default 0): the same seed, the
    same points; a ``seed`` with ``grid``, which draws nothing, is refused. Parameters with
    explicit values (``NAME=A,B,C``) pick among them. ``flag(name)``: how a refusal names the
    parameter ``name`` (default: as this function and ``sweep`` do, ``samples``, ``params entry``;
    ``warp-esph sweep`` passes ``cli.option_flag``, ``--samples``, ``--param``).
    """
    flag = flag or _own_words
    params = _as_params(params, flag)
    sample = checks.choice(flag('sample'), sample, SAMPLINGS)
    max_samples = checks.positive_int(flag('max_samples'), max_samples)  # named as the other sweep options are
    names = [p.name for p in params]
    if sample == "grid":
        if samples is not None:
            raise ValueError(f"{flag('samples')} = {checks.shorten(samples)!r} is not allowed with {_set(flag, 'sample', 'grid')}: the grid has the product of "
                             f"the levels of each {flag('param')}; use {_either(flag, ' or ')} to choose the count")
        if seed is not None:
            # Refused, not ignored, as --seed with --sample grid is: the points were the grid's whatever it was.
            raise ValueError(f"{flag('seed')} = {checks.shorten(seed)!r} is not allowed with {_set(flag, 'sample', 'grid')}: it seeds the draws of "
                             f"{_either(flag, ' and ')}, and a grid draws nothing")
        # The count before the levels: N = 1e9 allocated 7.5 GiB before it was compared.
        counts = [len(p.values) if p.values is not None else p.n if p.n is not None else len(p.levels(flag))
                  for p in params]
        total = math.prod(counts)
        if total > max_samples:
            sizes = " x ".join(f"{n} ({p.name})" for p, n in zip(params, counts))
            raise ValueError(f"the grid has {sizes} = {total} samples, more than {flag('max_samples')} = {max_samples} allows: "
                             f"use fewer levels, {_set(flag, 'sample', 'lhs')}{' ' if _cli(flag) else ' with '}{flag('samples')} N, or raise {flag('max_samples')}")
        levels = [p.levels(flag) for p in params]
        return [dict(zip(names, (float(x) for x in combo))) for combo in itertools.product(*levels)]
    if samples is None:
        raise ValueError(f"{flag('samples')} is required with {_set(flag, 'sample', sample)}: the number of samples to draw")
    if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or samples < 1:
        raise ValueError(f"{flag('samples')} = {checks.shorten(samples)!r} is not allowed: must be an integer >= 1")
    if samples > max_samples:
        raise ValueError(f"{flag('samples')} = {samples} is not allowed: more than {flag('max_samples')} = {max_samples}")
    for p in params:
        if p.values is None and p.n is not None:
            raise ValueError(f"{flag('param')} {p.name}: N = {p.n} levels is not allowed with {_set(flag, 'sample', sample)}: the count is "
                             f"{flag('samples')}; write {p.name}={p.lo:g}:{p.hi:g}:{p.scale}")
    seed = 0 if seed is None else seed
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"{flag('seed')} = {checks.shorten(seed)!r} is not allowed: must be an integer >= 0")
    rng = np.random.default_rng(int(seed))
    n = int(samples)
    cols = []
    for p in params:
        if sample == "random":
            u = rng.random(n)
        else:
            u = (rng.permutation(n) + rng.random(n)) / n
        cols.append(p.from_unit(u))
    return [{name: float(col[i]) for name, col in zip(names, cols)} for i in range(n)]


def _sample_seed(seed: int, index: int) -> int:
    """A per-sample seed from the sweep's seed and the sample index (independent streams)."""
    return int(np.random.SeedSequence(int(seed), spawn_key=(int(index),)).generate_state(1, np.uint32)[0])


# ------------------------------------------------------------------ the table
@dataclasses.dataclass
class SweepTable:
    """The sweep's rows (one dict per sample, sorted by ``sample``) and their column order.

    ``identity``: what made the rows (the scene, the parameters and their sampling, the
    frames and settings; ``sweep`` sets it), which a resumed sweep must match (``resume=``);
    ``None`` for a table read from a CSV file, which has no place for it (``sweep.json``
    beside it keeps it; a Parquet table keeps it in its own metadata)."""

    columns: list[str]
    rows: list[dict]
    params: list[str]
    identity: dict | None = None

    def __len__(self):
        return len(self.rows)

    def column(self, name: str) -> np.ndarray:
        """A column as an array: floats (NaN where empty) for numeric columns, else objects."""
        if name not in self.columns:
            raise ValueError(f"column {name!r} is not allowed: the table has {', '.join(self.columns)}")
        values = [r.get(name) for r in self.rows]
        if all(v is None or isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
            return np.array([np.nan if v is None else v for v in values], dtype=np.float64)
        return np.array(values, dtype=object)

    def _ints(self, name: str) -> bool:
        """Whether column ``name`` is whole numbers: its values are ints (an ``extra``'s count as
        the table's own ``steps``), or it has none and is one of the table's integer columns."""
        return self.types()[name] == "int"

    def types(self) -> dict[str, str]:
        """Each column's type, ``"int"``, ``"float"`` or ``"text"`` (``_column_type``), as the
        Parquet table's schema holds it and ``sweep.json`` beside a CSV table (``column_types``),
        which ``read_csv(path, types)`` reads back by: an ``extra``'s text "101" reads back from
        the CSV alone as the number 101 (a "007" beside it makes the column text)."""
        return {c: _column_type(c, [r.get(c) for r in self.rows]) for c in self.columns}

    @property
    def failed(self) -> list[dict]:
        return [r for r in self.rows if r["status"] != "ok"]

    @property
    def all_ok(self) -> bool:
        return not self.failed

    def to_csv(self, path) -> str:
        """Write the table as CSV (floats round-trip exactly; empty cell = no value)."""
        path = os.fspath(path)
        # Whole or not at all, and no working file left where the write fails: a full disk
        # left an empty sweep.csv.tmp beside the table (sweep.parquet.tmp, sweep.json.tmp too).
        with checks.replaced_atomically(path) as tmp, open(tmp, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(self.columns)
            types = self.types()
            for r in self.rows:
                w.writerow([_cell(_as_type(r.get(c), types[c])) for c in self.columns])
        return path

    def to_parquet(self, path) -> str:
        """Write the table as Parquet; ``ImportError`` without pyarrow. A cell the CSV leaves
        empty (no value: a failed sample's summary, a NaN) is a null, as the CSV reads back."""
        import pyarrow as pa  # noqa: PLC0415
        import pyarrow.parquet as pq  # noqa: PLC0415

        data = {}
        types = self.types()
        for c in self.columns:
            if types[c] == "int":
                data[c] = pa.array([None if r.get(c) is None else int(r[c]) for r in self.rows], type=pa.int64())
                continue
            col = self.column(c)
            if types[c] == "float":
                # from_pandas: NaN (a cell with no value, empty in the CSV) is a null, not a number: a
                # failed sample's NaN summary made a Parquet column's mean NaN, where the CSV's skipped it.
                data[c] = pa.array(col, type=pa.float64(), from_pandas=True)
            else:
                # The rows' values, not the column's: a text column with no value in any row (no
                # sample failed) reads as NaNs, which were written as the text 'nan'.
                data[c] = pa.array([_as_type(r.get(c), "text") for r in self.rows], type=pa.string())
        path = os.fspath(path)
        table = pa.table(data)
        if self.identity is not None:
            # In the file itself, so that the Parquet table alone can be resumed.
            table = table.replace_schema_metadata({_IDENTITY_KEY: json.dumps(self.identity)})
        # An open file, not its name: pyarrow reads a name as a UTF-8 URI, so a folder named in other
        # bytes failed the table after every sample had run (sweep.csv beside it written).
        with checks.replaced_atomically(path) as tmp, open(tmp, "wb") as fh:
            pq.write_table(table, fh)
        return path

    @classmethod
    def read_csv(cls, path, types: Mapping[str, str] | None = None) -> "SweepTable":
        """Read a table written by ``to_csv`` (empty cells as None), each column as one type
        (``SweepTable.types``), so that a text "007" stays text. ``types``: the columns' types,
        ``"int"``, ``"float"`` or ``"text"`` (``sweep.json``'s ``column_types``); without them,
        those of the ``sweep.json`` that ``write_outputs`` wrote beside a ``sweep.csv`` (where it
        names the same columns), else each column's by all its cells: text where any cell is
        no number as ``to_csv`` writes one ("007", "n/a"), else int where every cell is an int,
        else float. A text column whose every cell reads as such a number ("42") is told from
        numbers by the record alone."""
        path = os.fspath(path)
        columns, cells = cls._csv_cells(path)
        if types is None:
            types = _recorded_types(path, columns) or {c: _cells_type(c, [line[j] for line in cells if j < len(line)])
                                                       for j, c in enumerate(columns)}
        else:
            types = dict(types)
            for c, kind in types.items():
                if kind not in _TYPES:
                    raise ValueError(f"types[{c!r}] = {checks.shorten(kind)!r} is not allowed: must be one of {', '.join(map(repr, _TYPES))}")
        return cls._from_cells(path, columns, cells, types)

    @classmethod
    def _read_csv_kept(cls, path, types: Mapping[str, str] | None) -> "SweepTable":
        """A resumed sweep's reading of its CSV (``_resume_table``): by the record's types where
        it has them, else by each cell as it reads (digits alone an int), as every resume did."""
        path = os.fspath(path)
        columns, cells = cls._csv_cells(path)
        return cls._from_cells(path, columns, cells, dict(types or {}))

    @staticmethod
    def _csv_cells(path: str) -> tuple[list[str], list[list[str]]]:
        wanted = "must be a sweep table written by SweepTable.to_csv (a header with sample, status, the parameters, seed)"
        try:
            with open(path, newline="", encoding="utf-8") as f:
                reader = csv.reader(f)
                columns = next(reader, [])
                cells = [line for line in reader if line]  # (a blank line holds no row)
        except (UnicodeDecodeError, csv.Error) as e:
            raise ValueError(f"path = {checks.shown_path(path)} is not allowed: {wanted}; it is not CSV text ({e})") from None
        for k, line in enumerate(cells):
            if len(line) != len(columns):
                # A row cut short was read with its missing cells empty: resumed as an 'ok' row
                # with no summary and its last number cut to the digits left.
                raise ValueError(f"path = {checks.shown_path(path)} is not allowed: {wanted}; its row {k + 1} below the header has "
                                 f"{len(line)} cells where the header has {len(columns)} (a row cut short or run together: the "
                                 "file is damaged)")
        return columns, cells

    @classmethod
    def _from_cells(cls, path: str, columns: list[str], cells: list[list[str]], types: dict) -> "SweepTable":
        rows = [{c: _parse_cell(c, v, types.get(c)) for c, v in zip(columns, line)} for line in cells]
        return cls._checked(path, columns, rows, None)

    @classmethod
    def read_parquet(cls, path) -> "SweepTable":
        """Read a table written by ``to_parquet`` (nulls as None, its ``identity`` from the
        file's metadata); ``ImportError`` without pyarrow."""
        import pyarrow.parquet as pq  # noqa: PLC0415

        path = os.fspath(path)
        try:
            with open(path, "rb") as fh:
                table = pq.read_table(fh)
        except (OSError, ValueError) as e:  # pyarrow's ArrowInvalid is a ValueError
            if not os.path.isfile(path):
                raise
            raise ValueError(f"path = {checks.shown_path(path)} is not allowed: must be a sweep table written by SweepTable.to_parquet; "
                             f"it is not a Parquet file ({_one_line(e)})") from None
        columns = list(table.column_names)
        data = table.to_pydict()
        rows = [{c: data[c][k] for c in columns} for k in range(table.num_rows)]
        meta = table.schema.metadata or {}
        identity = json.loads(meta[_IDENTITY_KEY.encode()]) if _IDENTITY_KEY.encode() in meta else None
        return cls._checked(path, columns, rows, identity, "to_parquet")

    @classmethod
    def _checked(cls, path, columns, rows, identity, writer: str = "to_csv") -> "SweepTable":
        wanted = f"must be a sweep table written by SweepTable.{writer} (a header with sample, status, the parameters, seed)"
        # An empty file raised StopIteration; another CSV "'status' is not in list".
        if columns[:2] != ["sample", "status"] or "seed" not in columns:
            raise ValueError(f"path = {checks.shown_path(path)} is not allowed: {wanted}; its header is {checks.shorten(columns)!r}")
        start, end = columns.index("status") + 1, columns.index("seed")
        return cls(columns, rows, columns[start:end], identity)


#: The key of a Parquet table's metadata that holds its sweep's identity.
_IDENTITY_KEY = "warp_esph.sweep"
_TEXT_COLUMNS = ("status", "reason", "warnings", "solver")


def _cell(v) -> str:
    if v is None or isinstance(v, float) and math.isnan(v):
        return ""
    if isinstance(v, float):
        return repr(v)
    return str(v)


_INTEGER = re.compile(r"[+-]?[0-9]+")


def _column_type(column: str, values: Sequence) -> str:
    """``"text"`` for a column holding any text (a number beside it is its text, as the CSV
    and Parquet tables write it), ``"int"`` for one of ints alone, else ``"float"`` (an int
    beside floats is a float); a column with no value by its name."""
    if column in _TEXT_COLUMNS:
        return "text"
    values = [v for v in values if v is not None]
    if any(isinstance(v, str) for v in values):
        return "text"
    if not values:
        return "int" if _is_int_column(column) else "float"
    return "int" if all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in values) else "float"


def _as_type(v, kind: str):
    """``v`` as a value of a column of type ``kind``: a number in a text column is the text
    ``to_csv`` writes of it, an int in a float column a float; None stays None."""
    if v is None:
        return None
    if kind == "text" and not isinstance(v, str):
        return _cell(v) or None
    if kind == "float" and isinstance(v, (int, np.integer)) and not isinstance(v, bool):
        return float(v)
    return v


_TYPES = ("int", "float", "text")
# A number as ``to_csv`` writes one: an int by str (no leading zero, no '+'), a float by repr.
_WRITTEN_INT = re.compile(r"-?(?:0|[1-9][0-9]*)")
_WRITTEN_FLOAT = re.compile(r"-?(?:(?:0|[1-9][0-9]*)\.[0-9]+(?:e[+-][0-9]+)?|[1-9](?:\.[0-9]+)?e[+-][0-9]+|inf|nan)")


def _cells_type(column: str, texts: Sequence[str]) -> str:
    """The type of a column read without a record, from all its cells, as ``_column_type``
    decides a table's: reading each cell alone gave an extra's codes "007" and "abc" the int 7
    beside the text "abc", one column of two types."""
    if column in _TEXT_COLUMNS:
        return "text"
    texts = [t for t in texts if t != ""]
    if any(not (_WRITTEN_INT.fullmatch(t) or _WRITTEN_FLOAT.fullmatch(t)) for t in texts):
        return "text"
    if all(_WRITTEN_INT.fullmatch(t) for t in texts):
        return "int" if texts or _is_int_column(column) else "float"
    return "float"


def _recorded_types(path: str, columns: list[str]) -> dict | None:
    """The ``column_types`` of the ``sweep.json`` beside ``path`` where ``path`` is a
    ``sweep.csv`` and the record names its columns, each with a known type; else None."""
    if os.path.basename(path) != "sweep.csv":
        return None
    try:
        with open(os.path.join(os.path.dirname(path), "sweep.json"), encoding="utf-8") as f:
            types = json.load(f).get("column_types")
    except (OSError, ValueError, AttributeError):
        return None
    if not isinstance(types, dict) or set(types) != set(columns) or not set(types.values()) <= set(_TYPES):
        return None
    return types


def _parse_cell(column: str, text: str, kind: str | None = None):
    if text == "":
        return None
    if column in _TEXT_COLUMNS or kind == "text":
        return text
    if kind == "float":
        with contextlib.suppress(ValueError):  # a record older than the table (a kill between the two)
            return float(text)
    if _INTEGER.fullmatch(text):
        # A float is written by repr, with '.', 'e', 'inf' or 'nan': digits alone were an int
        # (an extra's count read back as a float).
        return int(text)
    try:
        v = float(text)
    except ValueError:  # a text column of an ``extra`` function
        return text
    return int(v) if _is_int_column(column) and v.is_integer() else v


def _is_int_column(column: str) -> bool:
    return column in ("sample", "seed", "steps", "particles") or column.startswith("guard_")


# ------------------------------------------------------------------ one sample
def _assignments(scene, params: list[Param], flag=None) -> list[tuple[str, str, list[int]]]:
    """``(param name, field, material indices)`` per parameter, checked against the scene;
    ``flag``: as ``sample_points``'."""
    flag = flag or _own_words
    from .fit import _material_indices  # noqa: PLC0415 (the names fit uses for bodies and materials)

    b = scene.builder
    # fit's resolver reads these three attributes; the builder has them before finalize,
    # so names are checked without building the model.
    view = _BuilderView(bodies=list(b._bodies), materials=list(b._materials),
                        particle_material_np=np.concatenate(b._material_ids) if b._material_ids else np.zeros(0, np.int32))
    out, seen = [], {}
    for p in params:
        target = p.target
        if target is None:
            # fit's selection of every material: an elastic particle floor's is left as built.
            # It was set too, so a swept yield stress made the floor under the body flow.
            idx = _material_indices(view, None)
        else:
            if target.isdigit() and target in [body.name for body in view.bodies]:
                # It set material 1 while body '1' is of material 0, without a word.
                raise ValueError(f"{flag('param')} {p.name} is not allowed: {target!r} names both material {target} and body "
                                 f"{target!r}; rename the body")
            key = int(target) if target.isdigit() else target
            if isinstance(key, str) and scene.material_index(key) is not None:
                key = scene.material_index(key)  # a scene file's material, as the file names it
            # Named in the refusal of the material, which says 'is not allowed' itself: wrapped in
            # one of the parameter, it was said twice.
            idx = _material_indices(view, [key], what=f"{flag('param')} {p.name}: material",
                                    material_names=getattr(scene, "material_names", ()))
        for k in idx:
            if (k, p.field) in seen:
                raise ValueError(f"{flag('param')} {p.name} is not allowed: it sets {p.field} of material {k}, "
                                 f"which {flag('param')} {seen[(k, p.field)]} sets already")
            seen[(k, p.field)] = p.name
        out.append((p.name, p.field, idx))
    return out


@dataclasses.dataclass
class _BuilderView:
    bodies: list
    materials: list
    particle_material_np: np.ndarray


@dataclasses.dataclass(frozen=True)
class _Task:
    index: int
    seed: int
    values: dict
    assignments: list
    frames: int
    fps: float
    dt: float | None
    dtype: str
    device: str
    extra: Callable | None


def _apply(model, assignments, values):
    """Set the sample's values in the model's materials (through ``Material`` checks).

    A material whose pressure stiffness follows its moduli (the default ``k_p``,
    ``Material.default_pressure_stiffness``) keeps following them when ``mu`` or ``lam``
    change, as in ``fit``.
    """
    changes: dict[int, dict] = {}
    for name, field, idx in assignments:
        for k in idx:
            changes.setdefault(k, {})[field] = values[name]
    for k, ch in changes.items():
        m = model.materials[k]
        if ({"mu", "lam"} & ch.keys()) and "pressure_stiffness" not in ch and m.has_default_pressure_stiffness:
            ch["pressure_stiffness"] = None
        try:
            new = m.replace(**ch)
            # The row's reason serves sweep() and warp-esph sweep alike: its advice names both
            # precisions' spellings (it said only dtype=float64, which the command does not take).
            from .model import check_material_precision  # noqa: PLC0415 (as the module's other model imports)
            check_material_precision(new, model.scalar, cli=True)
            model.set_material(k, new)
        except ValueError as e:
            # Which material refused: 'Material.lam = ...' alone did not say which of two
            # materials whose lam is swept, and the sweep's refusal named both parameters.
            # A ValueError still, as the row's reason names it; ``index`` for the sweep's own refusal.
            refused = ValueError(f"{_material_shown(model.bodies, k)}: {e}")
            refused.index = k
            raise refused from None


def _material_shown(bodies, k: int) -> str:
    """``material 1 (body 'blob')``: the index and the bodies made of it (``bodies``: a model's
    or a builder's, each with ``name`` and ``material``), as refusals name it; the sample's
    refusal and the flow parameters' one name a material alike."""
    of = [b.name for b in bodies if b.material == k]
    return f"material {k}" + (f" (body {', '.join(map(repr, of))})" if of else "")


def _summary(model, state, solver) -> dict:
    """The summary quantities of the final state (``y`` up): mass-weighted centroid height,
    highest particle, RMS and largest horizontal distance from the centroid's vertical axis,
    kinetic energy, and the guard counts."""
    x = state.x.numpy().astype(np.float64)
    v = state.v.numpy().astype(np.float64)
    m = model.particle_mass.numpy().astype(np.float64)
    c = (m[:, None] * x).sum(axis=0) / m.sum()
    r = np.hypot(x[:, 0] - c[0], x[:, 2] - c[2])
    out = {"centroid_height": float(c[1]), "max_height": float(x[:, 1].max()),
           "radial_spread": float(math.sqrt((m * r * r).sum() / m.sum())), "max_radius": float(r.max()),
           "kinetic_energy": float(0.5 * (m * (v * v).sum(axis=1)).sum())}
    out.update({f"guard_{k}": int(n) for k, n in solver.guard_counts().items()})
    return out


def _exempt_blew_up(model, state, bounds, exempt: tuple[str, ...], seconds: float) -> str | None:
    """Why a body the scene shows blowing up (``Scene.diverges``, which the run's monitor leaves
    out so that the run goes on) has blown up by the run's end, or ``None``: the monitor's
    bounds ``bounds`` (made from the run's first state with no body left out) read the final
    state. A row's summary is of every particle, so a sample whose exempt body blew up, finite
    (``fig8_comparison``'s plastic rest-configuration cube reaches 1.8e5 m/s), is no ok row: its
    force fields keep ``simulate.energy_growth`` off, and it was one, its summary that of the debris."""
    if bounds is None or not exempt or not bounds.enabled:
        return None
    hit = bounds.check(state.x.numpy(), state.v.numpy(), seconds)
    if hit is None:
        return None
    what, p = hit
    body = model.bodies[int(model.particle_body_np[p])].name if 0 <= p < model.particle_count else None
    names = [body] if body in exempt else list(exempt)
    shown = ", ".join(repr(n) for n in names)
    return (f"body {shown}, which the scene shows blowing up (left out of the run's divergence monitor), "
            f"blew up: at the run's end, {what}; the row's summary would be of its blown-up state")


def _one_line(text) -> str:
    return " ".join(str(text).split())


def _run_sample(scene, task: _Task) -> dict:
    """Run one sample in this process; never raises for a failed sample (it is a row)."""
    from .startup import init_warp  # noqa: PLC0415 (quiet Warp start, shared with the CLI)

    init_warp(task.device)
    from .simulate import (DivergenceMonitor, SimulationError, StepRefusal, divergence_advice, energy_growth,  # noqa: PLC0415
                           resolve_timestep, rest_inversions, simulate)
    from .sim.solver import Solver  # noqa: PLC0415

    row = {"sample": task.index, "status": "ok", **task.values, "seed": task.seed}
    t0 = time.perf_counter()
    caught = []
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            model = scene.builder.finalize(device=task.device, dtype=task.dtype)
            _apply(model, task.assignments, task.values)
            substeps, dt = resolve_timestep(model, task.fps, dt=task.dt)
            row.update({"particles": model.particle_count, "steps": task.frames * substeps, "dt": dt})
            solver = Solver(model)
            row["solver"] = solver_label(solver)
            # The bodies a scene shows blowing up are left out of the monitor, as in warp-esph run,
            # so that the run goes on; the row is checked with them in at its end (_exempt_blew_up).
            # A sweep's scene is resolved by its scale (sweep(scale=), --scale) or its builder's spacing.
            exempt = tuple(getattr(scene, "diverges", ()) or ())
            bounds = DivergenceMonitor(model, model.state(requires_grad=False), solver=solver) if exempt else None
            solver.tool_work_done = None
            state = simulate(model, task.frames, fps=task.fps, dt=dt, progress=False, solver=solver,
                             monitor_exempt=exempt, _finer="a larger scale, or a smaller spacing")
            summary = _summary(model, state, solver)
            why = _exempt_blew_up(model, state, bounds, exempt, task.frames / task.fps)
            if why is None:
                steps = task.frames * substeps
                grew = energy_growth(model, model.particle_x0, model.particle_v0, state.x.numpy(), state.v.numpy(),
                                     t0=float(state.time) - steps * dt, dt=dt, steps=steps,
                                     work=solver.tool_work_done, solver=solver)
                why = None if grew is None else grew[0]
            if why is not None:
                # The guard counts alone: the blown-up state's summary (a particle at 1.4e17 m) and
                # extra columns were numbers in a failed row, which column() hands on as measured.
                row.update({k: v for k, v in summary.items() if k.startswith("guard_")})
                row.update(status="failed", reason=why)
            else:
                row.update(summary)
            if task.extra is not None and why is None:
                more = task.extra(model, state, task.seed)
                taken = sorted(set(more) & (set(row) | {"wall_s", "reason", "warnings"})) if isinstance(more, Mapping) \
                    else None
                if taken is None or taken:  # a key 'status' or a parameter's name overwrote the row's own
                    raise ValueError(f"extra returned {checks.shorten(more)!r}: it must return a dict of new columns"
                                     + (f", not {taken} (the table's own)" if taken else ""))
                # numpy's numbers as Python's (a float32 max, an int64 count): as they were, the
                # Parquet column was text and the CSV's float32 text read back as another float.
                more = {k: v.item() if isinstance(v, np.generic) else v for k, v in more.items()}
                # A bool as the count it is (1 or 0): the CSV wrote 'True', read back as text, where
                # the Parquet column held 1.0, and a resumed table held the text.
                more = {k: int(v) if isinstance(v, bool) else v for k, v in more.items()}
                odd = next(((k, v) for k, v in more.items() if v is not None and not isinstance(v, (int, float, str))), None)
                if odd is not None:
                    # A table cell: an object (a function) was an ok row holding it in this process
                    # and a failed one with pickle's words where a worker process sent it back.
                    # Its type, not its repr: an address made the reason another in every process.
                    raise ValueError(f"extra returned {odd[0]} = a {type(odd[1]).__name__}: a column's value must be "
                                     "a number, text or None")
                row.update(more)
    except SimulationError as e:
        # The reason alone, as for a StepRefusal: the advice named a Python caller's parameters
        # ('a smaller dt=', 'use dtype=float64'), and the table is the command's too. A
        # divergence keeps the advice's one fact, the stable step, to read the row's dt against.
        why = e.reason
        if e.advice and e.advice == f"; {divergence_advice(model, solver.hourglass)}":
            why += f"; the sample's stable step is {solver.stable_dt():.3g} s"
        elif e.advice and rest_inversions(solver) and e.advice == f"; {divergence_advice(model, solver.hourglass, solver=solver)}":
            # Its fact without the caller's options ('a smaller dt=', 'fit=').
            why += f"; the rest-configuration model's fit inverted in {rest_inversions(solver)} particle-steps"
        # What the guards did up to the stop, as a run that blew up by its end keeps it: since
        # simulate stops a run at the frame its energy grows past energy_growth's limit, the
        # rows the end-of-run check failed with their counts came here without them.
        row.update({f"guard_{k}": int(n) for k, n in solver.guard_counts().items()})
        row.update(status="failed", reason=_one_line(why))
    except StepRefusal as e:
        # The reason without a run's advice ('give dt= or substeps=', 'fewer frames=, or a larger
        # dt=', 'a smaller dt=', 'a higher fps='): a sweep has no substeps, a dt above a sample's
        # stable step blows it up, and the table is the command's too. The sweep's own options are
        # said where no sample can run (_check_some_sample_steps).
        row.update(status="failed", reason=_one_line(f"{type(e).__name__}: {e.reason}"))
    except (ValueError, ArithmeticError, RuntimeError) as e:
        row.update(status="failed", reason=_one_line(f"{type(e).__name__}: {e}"))
    row["wall_s"] = time.perf_counter() - t0
    notes = sorted({_one_line(w.message) for w in caught})
    if notes:
        row["warnings"] = "; ".join(notes)
    return row


def solver_label(solver) -> str:
    """The ``solver`` column: what the sample's solver ran (``Solver.label``): ``fit="auto"``
    resolves by the sample's values, so a sweep of ``flow_rate`` through 0 switches models
    there."""
    return solver.label()


class ItemError(Exception):
    """An item's exception that its worker process could not send back as it is (pickle
    cannot rebuild it in the parent), or its ``sys.exit``, as its one line
    ``'TypeName: message'``; ``parallel_map`` without ``on_error`` raises it as
    ``'item N: TypeName: message'``."""


def _call(fn, item):
    return _call_star(fn, *item)


def _named(i: int, e: BaseException) -> ItemError:
    """The ``ItemError`` that ``parallel_map`` without ``on_error`` raises for item ``i``."""
    return ItemError(f"item {i}: {_words(e)}")


def _words(e: BaseException) -> str:
    """An item's exception as one line, the same wherever the item ran: ``'TypeName: message'``."""
    return str(e) if isinstance(e, ItemError) else _one_line(f"{type(e).__name__}: {e}")


def _start_worker(parent: int):
    """A pool worker's start: SIGINT ignored, and ended once ``parent``, the pid of the process
    that made the pool, is gone."""
    # Ctrl-C reaches every process of the terminal's group: the parent cancels the sweep
    # and stops the workers, so they need not print a traceback each.
    import signal  # noqa: PLC0415
    import threading  # noqa: PLC0415
    import time  # noqa: PLC0415

    signal.signal(signal.SIGINT, signal.SIG_IGN)

    def watch():
        # A parent killed outright (SIGKILL, out of memory) or ended at once by a second
        # signal before it stopped its workers left them running: their samples finished for
        # no one, then each waited forever for another (its own end of the task queue keeps
        # the queue open), holding its memory and the terminal's pipes. (Warp's CPU launches
        # release the GIL, so this runs during a sample too.) The pid is the pool's, not this
        # start's os.getppid(): a parent killed while the worker imported Warp (seconds) had
        # left it watching its new parent, init, for good.
        while os.getppid() == parent:
            time.sleep(0.25)
        os._exit(1)

    threading.Thread(target=watch, name="warp_esph-parent-watch", daemon=True).start()


def _cores() -> int:
    """The cores this process may run on (its affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _call_star(fn, *args):
    # Ray resolves object references only among a task's top-level arguments.
    try:
        return fn(*args)
    except SystemExit as e:
        # An item's sys.exit is its failure: it ended the whole run here and in a process pool (the
        # items finished lost with it), and on Ray its worker exited, a row saying it crashed.
        raise ItemError(_words(e)) from None
    except Exception as e:
        import pickle  # noqa: PLC0415

        try:
            pickle.loads(pickle.dumps(e))
        except Exception:  # noqa: BLE001 (whatever pickle raises: the parent would fail the same way)
            # Sent as it is, the parent failed to read it back: that broke a process pool (the item
            # ran again alone, broke it again, and its row said its worker process died, a crash or
            # out of memory), and on Ray its row was Ray's words, with the worker's pid and colours.
            raise ItemError(_words(e)) from None
        raise


# ------------------------------------------------------------------ executors
def _unguarded_main_script() -> str | None:
    """The path of the script this process runs when its source has no ``__main__`` guard,
    else None. A spawned worker starts by importing that script (``multiprocessing``'s spawn),
    so without the guard it runs the script's parallel call again and dies starting.

    A package's ``__main__.py`` (``python -m warp_esph``) is never run in a worker: spawn
    skips a main module named ``*.__main__``, as its source needs no guard. It was taken for
    an unguarded script, so one worker that died failed every sample left as unstartable. A
    module run with ``-m`` is imported there as ``__mp_main__``, and its guard is checked."""
    main = sys.modules.get("__main__")
    name = getattr(getattr(main, "__spec__", None), "name", None)
    if name is not None and (name == "__main__" or name.endswith(".__main__")):
        return None
    path = getattr(main, "__file__", None)
    if not path or not str(path).endswith(".py"):
        return None
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            source = f.read()
    except OSError:
        return None
    return None if "__main__" in source else str(path)


#: An item whose worker process died while it ran alone: the reason of its row, the same from
#: a process pool and from Ray (whose own words named the worker's pid and ip, colour codes
#: among them, another reason for the same sample on every run).
_DIED_ALONE = ("a worker process died running this item alone (a crash in native code or out of memory); "
               "it may run with more memory or fewer workers")


def _refuse_workers_with_ray(workers, ray, workers_name: str, ray_name: str) -> None:
    """Refuse a worker count given with a Ray address: Ray places the items, one task each, on
    the cluster's cores, and the count was ignored without a word."""
    if workers is not None and ray is not None:
        raise ValueError(f"{workers_name} = {checks.shorten(workers)!r} is not allowed with {ray_name} = "
                         f"{checks.shorten(ray)!r}: the Ray cluster runs one task per item on its own cores, and "
                         f"{workers_name} counts the processes on this machine; give one of them")


def parallel_map(fn: Callable, items: Sequence[tuple], *, workers: int | None = None, ray: str | None = None,
                 on_result: Callable | None = None, on_error: Callable | None = None,
                 ray_resources: Mapping | None = None) -> list:
    """``[fn(*item) for item in items]``, run in parallel; results in the order of ``items``.

    - ``workers=1`` (and no ``ray``): in this process, one after the other.
    - ``workers=N``: N spawned processes (``concurrent.futures.ProcessPoolExecutor``; each
      its own interpreter and Warp context, so Warp's one-thread CPU launches use N cores).
      Default: every core this process may use, at most one per item.
    - ``ray=ADDRESS``: one Ray task per item (``num_cpus=1``) on the cluster at ``ADDRESS``
      (``"auto"``, ``"ray://host:10001"``, ...); a Ray session already started in this
      process (``ray.init``) is used as it is and left running; one started here is shut
      down at the end. Needs ``pip install warp-esph[ray]`` and warp-esph on every node.
      ``workers`` with ``ray`` is refused, and so is ``ray_resources`` without it (each was ignored).

    ``fn`` must be importable by name (a module-level function) and ``items`` picklable
    (with worker processes: one that is not is refused before any item runs); each item is
    a tuple of ``fn``'s arguments.
    ``on_result(index, result)`` is called in this process as each item finishes.

    An item fails when ``fn`` raises, its worker process dies (a crash in native code, out
    of memory: the items running beside it, which the broken pool fails with it, run again
    alone, so only an item that kills its worker alone fails; those not yet started go on in
    a fresh pool, since each worker is handed one item at a time) or its Ray task or
    worker fails (a Ray task whose worker died is not retried: ``ray_resources`` may set
    ``max_retries``; its message is a pool's of an item that kills its worker alone). With ``on_error(index, message)`` its return value is that item's result
    (``message``: ``'TypeError: ...'`` where ``fn`` raised, the same words wherever it ran; an
    exception pickle cannot rebuild, or a ``SystemExit``, comes back from a worker process or Ray
    task as an ``ItemError`` of those words; a ``sys.exit`` in ``fn`` fails its item, not the run)
    and the others go on; without, the first failure raises: ``fn``'s exception as it is,
    except a ``sys.exit`` (in this process, in a worker process and on Ray alike) and, from a
    worker process or Ray, an exception pickle cannot rebuild, which raise ``ItemError``
    naming the item, ``'item 1: SystemExit: 5'``; an item that kills its worker alone raises
    ``RuntimeError`` naming it (the items beside it run again alone first, as above). Ctrl-C
    stops the workers and raises ``KeyboardInterrupt``.
    """
    if not callable(fn):
        raise ValueError(f"fn = {checks.shorten(fn)!r} is not allowed: must be callable as fn(*item)")
    items = list(items)
    for i, item in enumerate(items):
        # fn(*item): an int was a TypeError from the first worker, a string spread into letters.
        if isinstance(item, (str, bytes)) or not isinstance(item, (tuple, list)):
            raise ValueError(f"items[{i}] = {checks.shorten(item)!r} is not allowed: each item must be a tuple of "
                             f"fn's arguments (e.g. ({checks.shorten(item)!r},))")
    _refuse_workers_with_ray(workers, ray, "workers", "ray")
    if ray_resources is not None and ray is None:
        # Read only by the Ray tasks: the items ran in processes here as without it.
        raise ValueError(f"ray_resources = {checks.shorten(ray_resources)!r} is not allowed without ray: it is what each "
                         "Ray task asks the cluster for, and without ray the items run in processes here")
    if ray is not None:
        return _ray_map(fn, items, ray, on_result, on_error, ray_resources)
    if workers is None:
        workers = _cores()
    # Named as this function's parameter: sweep() and the command check theirs before it.
    workers = checks.positive_int("workers", workers)
    workers = min(workers, max(len(items), 1))
    results: list = [None] * len(items)
    if workers == 1:
        for i, item in enumerate(items):
            try:
                results[i] = fn(*item)
            except (Exception, SystemExit) as e:  # an item's sys.exit is its failure, as in a worker process
                if on_error is None:
                    if isinstance(e, SystemExit):
                        # Raised as it is, the caller's program ended as if it had exited itself.
                        raise _named(i, e) from None
                    raise
                results[i] = on_error(i, _words(e))
            if on_result is not None:
                on_result(i, results[i])
        return results
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait  # noqa: PLC0415
    from concurrent.futures.process import BrokenProcessPool  # noqa: PLC0415

    # A function the workers cannot be sent (a lambda, a local function) failed every item
    # with pickle's message, as if each had failed on its own.
    _check_sendable("fn", fn, workers)

    # spawn, not fork: a forked child would inherit this process's Warp runtime (and any
    # threads), which Warp does not support; a spawned one initialises its own.
    def new_pool():
        return ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=_start_worker, initargs=(os.getpid(),))

    def finish(i, result):
        results[i] = result
        if on_result is not None:
            on_result(i, result)

    def why_dead(alone: bool = False) -> str:
        script = _unguarded_main_script()
        if script is not None:
            return (f"the worker processes could not start: each one first imports the script {script}, which runs "
                    "its parallel call again at import; put the script's top-level code under "
                    "'if __name__ == \"__main__\":'")
        if alone:
            return _DIED_ALONE
        return ("a worker process died before this item finished (a crash in native code or out of memory, in this "
                "item or another one running at the time); run it again")

    def settle(fut, i) -> bool:
        """Take item ``i``'s outcome; False where its worker died (the outcome is not taken)."""
        try:
            result = fut.result()
        except BrokenProcessPool:
            return False
        except Exception as e:
            if on_error is None:
                if isinstance(e, ItemError):
                    raise _named(i, e) from None
                raise
            result = on_error(i, _words(e))
        finish(i, result)
        return True

    # At most one item per worker is handed to the pool: a worker that dies breaks the pool and
    # fails every item in it, and with every item handed over at once that was the whole rest of
    # the run. The items not handed over go on in a fresh pool; those in flight when it broke
    # cannot be told apart (any of them may have killed its worker, or a queued one was never
    # started), so each runs again alone, and only one that dies alone fails.
    todo = list(range(len(items)))[::-1]
    alone_next: list = []
    pool = new_pool()
    pending: dict = {}
    try:
        while todo or pending or alone_next:
            if alone_next:
                if not pending:
                    i = alone_next.pop(0)
                    pending[pool.submit(_call, fn, items[i])] = i
            else:
                while todo and len(pending) < workers:
                    i = todo.pop()
                    pending[pool.submit(_call, fn, items[i])] = i
            in_flight = len(pending)
            done, _ = wait(pending, return_when=FIRST_COMPLETED)
            dead = []
            for fut in done:
                i = pending.pop(fut)
                if not settle(fut, i):
                    dead.append(i)
            if not dead:
                continue
            for fut, i in list(pending.items()):  # the items it ran beside, each as it ended
                wait([fut])
                if not settle(fut, pending.pop(fut)):
                    dead.append(i)
            pool.shutdown(wait=True)
            unstartable = _unguarded_main_script() is not None
            if on_error is None and (in_flight == 1 or unstartable):
                # Only now is the item known: raised at the first death, the error named the
                # lowest item in flight, which was whichever happened to run beside the one
                # that killed its worker.
                raise RuntimeError(f"item {min(dead)}: {why_dead(in_flight == 1 and not unstartable)}")
            if in_flight == 1 or unstartable:
                for i in dead:
                    finish(i, on_error(i, why_dead(alone=in_flight == 1 and not unstartable)))
            else:
                alone_next.extend(sorted(dead))
            if unstartable:
                # Its workers cannot start: a fresh pool would die as this one did.
                for i in todo[::-1] + alone_next:
                    finish(i, on_error(i, why_dead()))
                todo, alone_next = [], []
            if todo or alone_next:
                pool = new_pool()
    except BaseException:
        # Running samples would otherwise finish before the interpreter can exit.
        for proc in list((getattr(pool, "_processes", None) or {}).values()):
            proc.terminate()
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown(wait=True)
    return results


def _check_sendable(name: str, value, workers: int) -> None:
    """Refuse ``value`` (a function the worker processes call) that pickle cannot send them."""
    import pickle  # noqa: PLC0415

    try:
        pickle.dumps(value)
    except Exception as e:  # noqa: BLE001 (pickle raises AttributeError, TypeError, PicklingError)
        raise ValueError(f"{name} = {checks.shorten(value)!r} is not allowed with {workers} worker processes: it must "
                         f"be importable by name (a module-level function) to reach them ({_one_line(e)}); define it "
                         f"at the top level of a module, or run with workers=1") from None


def _check_reachable(address: str, timeout: float = 5.0, name: str = "ray") -> None:
    """A ``host:port`` (or ``ray://host:port``) address must answer within ``timeout`` s:
    ``ray.init`` retries an address where nothing listens for minutes, printing as it goes.
    ``name``: how a refusal names it (the CLI's ``--ray``, Python's ``ray``)."""
    text = str(address)
    if text in ("auto", "local"):
        return
    hostport = text.split("://", 1)[1] if "://" in text else text
    host, _, port = hostport.rpartition(":")
    if not host or not port.isdigit():
        raise ValueError(f"{name} = {checks.shorten(text)!r} is not allowed: give 'auto', HOST:PORT or ray://HOST:PORT")
    import socket  # noqa: PLC0415

    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except OSError as e:
        raise ValueError(f"{name} = {checks.shorten(text)!r} is not allowed: nothing answers at {host}:{port} ({e.strerror or e})") from None


@contextlib.contextmanager
def _ray_session(address, name: str = "ray"):
    """Ray, connected to the cluster at ``address`` for the ``with`` block: a session already
    started in this process is used as it is and left running; one started here is shut down
    as the block ends. A cluster that cannot be reached is a ``ValueError`` naming ``name``
    (``parallel_map``'s and ``sweep``'s ``ray``; ``warp-esph sweep``'s ``--ray``, which it
    names: '--ray = ...' reached a Python caller, who has no such option)."""
    cli = name.startswith("--")
    try:
        import ray  # noqa: PLC0415
    except ModuleNotFoundError:
        raise ValueError(f"{name} = {checks.shorten(str(address))!r} is not allowed: Ray is not installed; pip install 'warp-esph[ray]'") from None
    if ray.is_initialized():
        yield ray
        return
    _check_reachable(address, name=name)
    try:
        ray.init(address=address, include_dashboard=False, log_to_driver=False)
    except (ConnectionError, ValueError, RuntimeError) as e:
        why = _one_line(e)
        if "--address" in why:
            # Ray's advice is for its own command line ('the `--address` flag or RAY_ADDRESS'):
            # warp-esph has no --address; say what the command takes instead.
            why = re.sub(r"\s*[^.]*--address[^.]*\.?", "", why).strip()
            give, auto = ("--ray HOST:PORT or ray://HOST:PORT", "--ray auto") if cli else \
                ("ray = 'HOST:PORT' or 'ray://HOST:PORT'", "ray = 'auto'")
            why = (f"{why.rstrip('.')}; give {give} of a running cluster, or with {auto} start one on this machine "
                   "first ('ray start --head') or name its address in the RAY_ADDRESS environment variable")
        raise ValueError(f"{name} = {checks.shorten(str(address))!r} is not allowed: cannot connect to a Ray cluster there: {why}") from None
    try:
        yield ray
    finally:
        ray.shutdown()


def _ray_map(fn, items, address, on_result, on_error, resources):
    with _ray_session(address) as ray:
        return _ray_tasks(ray, fn, items, on_result, on_error, resources)


def _ray_tasks(ray, fn, items, on_result, on_error, resources):
    try:
        # Not retried: Ray ran a sample whose worker died (a crash in native code, out of memory)
        # three more times, each dying the same way, before its row said it failed.
        remote = ray.remote(**{"num_cpus": 1, "max_retries": 0, **dict(resources or {})})(_call_star)
        fn_ref = ray.put(fn)
        # Large shared arguments (the scene) are put once, not once per task.
        shared: dict[int, object] = {}
        refs = {}
        for i, item in enumerate(items):
            args = []
            for a in item:
                if not isinstance(a, (_Task, int, float, str)) and a is not None:
                    if id(a) not in shared:
                        shared[id(a)] = ray.put(a)
                    a = shared[id(a)]
                args.append(a)
            refs[remote.remote(fn_ref, *args)] = i
        results: list = [None] * len(items)
        pending = list(refs)
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            for ref in done:
                i = refs[ref]
                try:
                    results[i] = ray.get(ref)
                except ray.exceptions.RayError as e:
                    cause = getattr(e, "cause", None) if isinstance(e, ray.exceptions.RayTaskError) else None
                    if on_error is None:
                        if isinstance(cause, ItemError):
                            raise _named(i, cause) from None
                        raise
                    if isinstance(cause, Exception) and not isinstance(cause, ray.exceptions.RayError):
                        # The item's own exception, worded as the other executors word it: Ray's text
                        # (colour codes, the worker's pid and ip, its traceback) made the same failed
                        # sample another reason on every run, and another than the local table's.
                        why = _words(cause)
                    elif isinstance(e, (ray.exceptions.WorkerCrashedError, ray.exceptions.OutOfMemoryError)):
                        # Its worker died under it (each task runs alone in its worker): a
                        # pool's item that dies alone, as the pool words it.
                        why = _DIED_ALONE
                    else:  # the task or its node failed, not the item
                        why = _one_line(f"Ray: {type(e).__name__}: {e}")[:2000]
                    results[i] = on_error(i, why)
                if on_result is not None:
                    on_result(i, results[i])
        return results
    except BaseException:
        for ref in refs if "refs" in locals() else ():
            try:
                ray.cancel(ref)
            except Exception:  # noqa: BLE001 (finished tasks cannot be cancelled)
                pass
        raise


# ------------------------------------------------------------------ the sweep
def _load(scene, scale, flag=None):
    flag = flag or _own_words
    from .builder import SceneBuilder  # noqa: PLC0415
    from .scenes import Scene, load_scaled_scene  # noqa: PLC0415

    if isinstance(scene, Scene):
        return scene
    if isinstance(scene, SceneBuilder):
        return Scene("scene", "a SceneBuilder", scene)
    if isinstance(scene, (str, os.PathLike)) or scene is None:
        return load_scaled_scene(scene, checks.positive(flag('scale'), scale), flag('scale'))
    raise ValueError(f"scene = {checks.shorten(scene)!r} is not allowed: give a built-in scene name, a .toml scene file, a Scene or a SceneBuilder")


def _table(rows: list[dict], names: list[str], identity: dict | None = None) -> SweepTable:
    rows = sorted(rows, key=lambda r: r["sample"])
    head = ["sample", "status", *names, "seed", "particles", "steps", "dt", "solver", *SUMMARY_COLUMNS]
    tail = ["wall_s", "reason", "warnings"]
    guards = sorted({k for r in rows for k in r if k.startswith("guard_")})
    extra = sorted({k for r in rows for k in r} - set(head) - set(tail) - set(guards))
    columns = head + guards + extra + tail
    # Every row has every column (None: no value), as read back from the CSV. A column has one
    # type, as the tables keep it: a resumed table's rows, read back from them, are then its own.
    types = {c: _column_type(c, [r.get(c) for r in rows]) for c in columns}
    rows = [{c: _as_type(r.get(c), types[c]) for c in columns} for r in rows]
    return SweepTable(columns, rows, list(names), identity)


def sweep(
    scene,
    params,
    *,
    sample: str = "grid",
    samples: int | None = None,
    seed: int | None = None,
    frames: int | None = None,
    duration: float | None = None,
    fps: float | None = None,
    dt: float | None = None,
    scale: float = 1.0,
    dtype: str = "float32",
    device: str = "cpu",
    workers: int | None = None,
    ray: str | None = None,
    max_samples: int = MAX_SAMPLES,
    extra: Callable | None = None,
    on_result: Callable | None = None,
    resume=None,
    retry_failed: bool = False,
) -> SweepTable:
    """Run ``scene`` once per sample of ``params``; returns the table (see the module doc).

    - ``scene``: a built-in scene name or a ``.toml`` scene file (as ``warp-esph run``
      takes, at ``scale``), a ``Scene`` or a ``SceneBuilder``.
    - ``params``: specs (``"yield_stress=100:1000:log:8"``), ``Param``s, or
      ``{name: values}``. ``sample``: ``grid`` (default), ``random`` or ``lhs`` with
      ``samples`` draws from ``seed`` (default 0). More than ``max_samples`` samples is an
      error. A ``seed`` with a grid and no ``extra`` is refused, as ``--seed`` with
      ``--sample grid`` is: nothing reads it.
    - ``frames`` or ``duration`` (s): how long each sample runs (default the scene's
      frames) at ``fps`` (default the scene's). ``dt``: the time step (must divide
      ``1/fps``); default the scene's, else each sample's own stable step (it depends on
      the swept moduli).
    - ``dtype``: the precision, in any spelling ``SceneBuilder.finalize`` takes
      (``'float64'``, ``'f8'``, ``np.float64``, ``wp.float64``, ...); default float32.
    - ``workers``/``ray``: where the samples run (``parallel_map``).
    - ``extra(model, state, seed) -> dict``: more columns per sample, from the final
      state (a module-level function, so it can be sent to the workers); ``seed`` is the
      sample's own seed, the same wherever it runs. numpy numbers (``x.max()``, a float32)
      are kept as Python's, so the CSV and Parquet tables hold the same numbers; a bool as
      1 or 0. A column has one type (``SweepTable.types``): text beside numbers makes it text. A value
      that is no number, text or None (a function, a list) fails the sample, naming its column.
    - ``on_result(row)``: called as each sample finishes (in finishing order).
    - ``resume``: the table of an earlier run of the same sweep that did not finish: a
      ``SweepTable`` (a Ctrl-C's ``KeyboardInterrupt`` carries the samples finished as its
      ``table``), a Parquet table, or a folder ``write_outputs`` (or ``warp-esph sweep``)
      wrote, or its ``sweep.csv`` (the identity is in ``sweep.json`` beside it). Its rows
      are kept and only the samples it lacks run (with ``retry_failed``, its failed ones
      too); the table returned is the whole sweep's, as one run straight through gives
      (``wall_s`` aside). A table of another sweep (scene: its particles, materials, floors,
      colliders, tools and fields; parameters, sampling, seed, frames or settings) is
      refused, naming what differs, and so is one another version of the package wrote (its
      record format or version named: another version may compute other results); to start
      afresh, run without ``resume``.

    Raises ``ValueError`` for bad input before any sample runs. Ctrl-C raises
    ``KeyboardInterrupt`` with ``table``: the samples finished, to give as ``resume``.
    """
    if seed is not None and sample == "grid" and extra is None:
        # Refused, not ignored, as the command refuses --seed with --sample grid: the samples
        # ran exactly as without it, only the table's seed column differed. With extra it
        # seeds the sample seeds extra is handed.
        raise ValueError(f"seed = {checks.shorten(seed)!r} is not allowed with sample = 'grid' and no extra: it seeds "
                         "the draws of sample = 'random' and 'lhs' and the sample seeds handed to extra, and a grid "
                         "without extra reads neither")
    seed = 0 if seed is None else seed
    _refuse_workers_with_ray(workers, ray, "workers", "ray")
    # Before the plan, which builds the scene: a flag needs no model to be refused.
    retry_failed = checks.boolean("retry_failed", retry_failed)
    plan = _plan(scene, params, sample, samples, seed, frames, duration, fps, dt, scale, dtype, device, workers,
                 max_samples, extra, ray)
    kept = _resumed_rows(resume, plan, retry_failed, "resume", "retry_failed")
    done = list(kept)

    def record(row):
        done.append(row)
        if on_result is not None:
            on_result(row)

    try:
        return _execute(plan, workers, ray, record, kept)
    except KeyboardInterrupt as e:
        # What ran is not lost with the exception: it resumes as resume=e.table.
        e.table = _table(done, [p.name for p in plan.params], plan.identity)
        raise


@dataclasses.dataclass
class _Plan:
    scene: object
    params: list
    tasks: list
    identity: dict
    #: The identity as each earlier fingerprint version of the same record format recorded it
    #: (``_identity``'s ``version``), which a table of that version is compared with, as a
    #: checkpoint of an earlier version is with that version's fingerprint.
    earlier: dict
    #: The Tresca ground's ``shear_cap`` and every hardening a sample runs
    #: (``checkpoint.older_hold``: whether a table of an earlier version can be resumed).
    hold: tuple


def _plan(scene, params, sample, samples, seed, frames, duration, fps, dt, scale, dtype, device, workers, max_samples,
          extra, ray=None, options=None, flag=None) -> _Plan:
    """Every check of ``sweep``'s input, and one task per sample. ``options``: solver options
    (the CLI's ``--hourglass``, ...) set on the scene's builder before anything is built.
    ``flag``: as ``sample_points``'."""
    flag = flag or _own_words
    plist = _as_params(params, flag)
    # A grid's seed is read only by extra's sample seeds (below), never by the points.
    points = sample_points(plist, sample, samples, None if sample == "grid" else seed, max_samples, flag=flag)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"{flag('seed')} = {checks.shorten(seed)!r} is not allowed: must be an integer >= 0")
    if frames is not None and duration is not None:
        raise ValueError(f"{flag('frames')} = {frames!r} and {flag('duration')} = {duration!r} are not allowed together: give one")
    if frames is not None:
        frames = checks.positive_int(flag('frames'), frames)
    if duration is not None:
        duration = checks.positive(flag('duration'), duration)
    if fps is not None:
        from .simulate import check_fps  # noqa: PLC0415

        # Before --duration is read in frames of it, and before any sample is built.
        fps = check_fps(flag('fps'), fps)
    if dt is not None:
        dt = checks.positive(flag('dt'), dt)
    # The normaliser SceneBuilder.finalize and fit use, so the sweep takes the same spellings ('f8',
    # np.float64, np.dtype('f8'), wp.float64) and refuses the same ones ('float', None) in the same
    # words; the task keeps the name, which pickles to the workers.
    from ._types import scalar_type  # noqa: PLC0415 (Warp is loaded only once a sweep is planned)

    dtype = scalar_type(dtype).__name__
    device = checks.choice(flag('device'), device, ("cpu", "cuda"))
    if workers is not None:
        workers = checks.positive_int(flag('workers'), workers)
    if extra is not None and not callable(extra):
        raise ValueError(f"extra = {checks.shorten(extra)!r} is not allowed: must be callable as extra(model, state, seed)")
    sc = _load(scene, scale, flag)
    if options:
        from .cli import _apply_solver_options  # noqa: PLC0415

        # Before the check of the steps below: the hourglass control shortens the stable step.
        _apply_solver_options(sc.builder, options)
    # What the refusals below name: an option given, else the scene's value.
    rate = f"{flag('fps')} = {fps:g}" if fps is not None else f"the scene's fps = {sc.fps:g} ({flag('fps')})"
    length = f"{flag('frames')} = {frames}" if frames is not None else f"{flag('duration')} = {duration:g}" if duration is not None \
        else f"the scene's frames = {sc.frames} ({flag('frames')})"
    given = {"fps": fps is not None, "dt": dt is not None}
    fps = fps if fps is not None else sc.fps
    if duration is not None:
        from .simulate import MAX_STEPS  # noqa: PLC0415

        # Checked here, before any sample runs: 1e300 s failed every sample and then the table.
        if not duration * fps <= MAX_STEPS:
            # A frame is at least one step: more frames than a run may take steps is too long.
            raise ValueError(f"{flag('duration')} = {checks.shorten(duration)!r} is not allowed: at {fps:g} fps it is {duration * fps:.3g} frames "
                             f"of at least one step each, more than the {MAX_STEPS:.0e} steps a run may take")
        frames = max(1, round(duration * fps))
    frames = frames if frames is not None else sc.frames
    dt = dt if dt is not None else sc.dt
    if dt is not None:
        from .simulate import resolve_timestep  # noqa: PLC0415

        # With dt given only its ratio to 1/fps is checked; named as the caller gave it (a Python
        # caller was told '--dt', an option it has not).
        resolve_timestep(None, fps, dt=dt, flag=lambda name: flag(name) if given.get(name) else f"the scene's {name}")
    assignments = _assignments(sc, plist, flag)
    _check_flow_parameters_act(sc, assignments, points, flag)
    # Built once here, so that what the scene itself refuses (a body inside a collider, a device
    # this machine lacks) is bad input before any sample, not the same failure in every row;
    # on the CPU where the samples run on a Ray cluster, whose nodes have the device.
    from .startup import init_warp  # noqa: PLC0415 (quiet Warp start, shared with the CLI)

    here = "cpu" if ray is not None else device
    init_warp(here)
    model = sc.builder.finalize(device=here, dtype=dtype)
    # Before the check of the steps below, which sets sample values in the model's materials.
    record = (scene, sc, scale, plist, sample, len(points), seed, frames, fps, dt, dtype, device, extra, model)
    identity = _identity(*record)
    earlier = {v: _identity(*record, version=v) for v in range(FIRST_FINGERPRINT_OF_FORMAT, identity["fingerprint_version"])}
    # The scene's hardening where no parameter sets it, each sample's where one does.
    swept = {k: name for name, field, idx in assignments if field == "hardening" for k in idx}
    hold = (model.shear_cap, [m.hardening for k, m in enumerate(model.materials) if k not in swept]
            + [values[name] for name in set(swept.values()) for values in points])
    _check_some_sample_material(model, assignments, points, flag)
    if dt is None:
        _check_some_sample_steps(model, assignments, points, frames, fps, rate, length, flag)
    if extra is not None and ray is None and min(workers or _cores(), len(points)) > 1:
        _check_sendable("extra", extra, min(workers or _cores(), len(points)))
    tasks = [(sc, _Task(i, _sample_seed(seed, i), values, assignments, frames, fps, dt, dtype, device, extra))
             for i, values in enumerate(points)]
    return _Plan(sc, plist, tasks, identity, earlier, hold)


def _spec(p: Param) -> str:
    """``p`` as a spec ``parse_param`` reads, every number as a float's repr (100 and 100.0 are one level)."""
    if p.values is not None:
        return f"{p.name}={','.join(repr(float(v)) for v in p.values)}"
    return f"{p.name}={p.lo!r}:{p.hi!r}:{p.scale}" + (f":{p.n}" if p.n is not None else "")


def _model_digest(model, version: int | None = None) -> str:
    """A digest of what a scene puts in the model: the particles, their materials (every field,
    an elastic particle floor's too) and bodies, and all a checkpoint's fingerprint holds beside
    them (``checkpoint.scene_record``: the lattice, colliders, ghost floors, force fields, moving
    tools and pinned sets); equal for the same scene however it was given. It held the particles,
    materials and colliders alone, so a ghost floor where the table's was plastic, or a force
    field added, resumed another scene's table without a word. Positions and velocities in
    float32 and no masses (computed in the model's precision), so that the precision is told
    apart by ``dtype`` alone, not as another model too. ``version``: the fingerprint version
    whose ``scene_record`` it holds (None: this one's)."""
    import hashlib  # noqa: PLC0415

    from .checkpoint import scene_record  # noqa: PLC0415

    h = hashlib.sha256()
    for a in (np.asarray(model.particle_x0, np.float32), np.asarray(model.particle_v0, np.float32),
              model.particle_material_np, model.particle_body_np):
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    h.update(repr((model.spacing, tuple(model.gravity), model.materials, *model.static_colliders(),
                   scene_record(model) if version is None else scene_record(model, version))).encode())
    return h.hexdigest()[:16]


#: The format of a sweep's record (``SweepTable.identity``): what it holds and how its model
#: digest is made. Bumped with them, so that a table of an earlier format is refused as such
#: and not as another scene: format 1 (no ``format`` key) digested the particles, materials and
#: colliders alone, and a table of the same scene read "model = ... there, ... here".
RECORD_FORMAT = 2
#: The first fingerprint version a table of ``RECORD_FORMAT`` records (format 2 began at 2): a
#: table of a later one but this package's is compared with this scene's record of its version.
FIRST_FINGERPRINT_OF_FORMAT = 2


def _identity(scene, sc, scale, plist, sample, count, seed, frames, fps, dt, dtype, device, extra, model,
              version: int | None = None) -> dict:
    """What makes a sweep's rows: two sweeps of one identity have the same table (``wall_s``
    aside), so a resumed sweep's must be its table's. JSON values, as ``sweep.json`` and a
    Parquet table's metadata keep them. ``format`` and ``fingerprint_version`` say how the
    rest was recorded (the model digest holds ``checkpoint.scene_record`` of that version),
    ``version`` the package that ran the rows (another may compute other results). The
    argument ``version``: the fingerprint version to record (None: this one's)."""
    from . import __version__  # noqa: PLC0415 (the package is imported whole by now)
    from .checkpoint import FINGERPRINT_VERSION  # noqa: PLC0415

    b = sc.builder
    from_file = isinstance(scene, (str, os.PathLike)) and os.path.isfile(scene)
    digest = None
    if from_file:
        import hashlib  # noqa: PLC0415

        # The file's every setting (a tool, a mesh's path) and not only what the model holds.
        with open(scene, "rb") as f:
            digest = hashlib.sha256(f.read()).hexdigest()[:16]
    by_name = isinstance(scene, (str, os.PathLike)) or scene is None
    out = {"format": RECORD_FORMAT, "fingerprint_version": FINGERPRINT_VERSION if version is None else version,
           "version": __version__, "scene": sc.name, "scene_file": digest, "scale": float(scale) if by_name else None,
           "model": f"{model.particle_count} particles, {_model_digest(model, version)}",
           "params": [_spec(p) for p in plist], "sample": sample, "samples": int(count), "seed": int(seed),
           "frames": int(frames), "fps": float(fps), "dt": None if dt is None else float(dt), "dtype": dtype,
           "device": device, "solver": {"fit": b.fit, "contact_ramp": b.contact_ramp, "hourglass": b.hourglass,
                                        "fit_weight": b.fit_weight},
           "extra": None if extra is None else f"{getattr(extra, '__module__', '?')}.{getattr(extra, '__qualname__', repr(extra))}"}
    # Through JSON and back, so that it compares equal to what a file read gives (tuples as lists).
    return json.loads(json.dumps(out, default=str))


#: The fields that act only on a material that can flow (a finite ``yield_stress`` and a
#: ``flow_rate`` above 0, ``Material.plastic``): the flow rule's.
_FLOW_FIELDS = ("yield_stress", "flow_rate", "hardening")


def _check_flow_parameters_act(sc, assignments, points, flag) -> None:
    """Refuse a parameter of the flow rule (``_FLOW_FIELDS``) none of whose materials can flow
    in any sample: it changes nothing (an elastic material's rows of two yield stresses were
    the same to the bit), and the sweep ran every sample to a table of one result."""
    materials, bodies = sc.builder._materials, sc.builder._bodies
    swept: dict[int, dict[str, str]] = {}  # material -> {field: the parameter that sets it}
    for name, field, idx in assignments:
        for k in idx:
            swept.setdefault(k, {})[field] = name

    def flow_of(k, values, field):
        return values[swept[k][field]] if field in swept.get(k, {}) else getattr(materials[k], field)

    def can_flow(k, values):
        return math.isfinite(flow_of(k, values, "yield_stress")) and flow_of(k, values, "flow_rate") > 0.0

    for name, field, idx in assignments:
        if field not in _FLOW_FIELDS or any(can_flow(k, v) for v in points for k in idx):
            continue
        k = idx[0]
        shown = _material_shown(bodies, k)
        why = []
        if not any(math.isfinite(flow_of(k, v, "yield_stress")) for v in points):
            why.append("yield_stress = inf")
        if not any(flow_of(k, v, "flow_rate") > 0.0 for v in points):
            why.append("flow_rate = 0")
        raise ValueError(f"{flag('param')} {name} is not allowed: it changes nothing in this scene: {field} acts only on a "
                         f"material that can flow (a finite yield_stress and a flow_rate above 0), and in no sample can "
                         f"{shown} flow ({' or '.join(why) or 'no sample gives it both'}); sweep yield_stress and "
                         f"flow_rate too, or give the scene's material them")


def _check_some_sample_material(model, assignments, points, flag) -> None:
    """Refuse a sweep every sample of which makes a material the model refuses (``_apply``:
    ``Material``'s checks and the precision's): each sample failed alone with the same
    refusal, and the sweep exited 3 with a table of failures. A sample the material takes is
    enough (the others are rows of the table, as a sample that blew up is). The refusal names
    the material refused and the swept parameters of that material whose fields its refusal
    names, with the first sample's values of them."""
    first = None
    for k, values in enumerate(points):
        try:
            _apply(model, assignments, values)
        except ValueError as e:
            first = first or (k, values, e)
            continue
        return
    if first is None:
        return
    k, values, e = first
    # The refusal names the material and the fields it is about ('material 1 (body 'blob'):
    # Material.lam = ...'): only the parameters that set those fields of that material are named
    # (all of them were, a swept yield stress told to change beside a lam that no material takes;
    # then every lam, that of a material taking each sample's); one naming no swept field names
    # that material's parameters, else them all.
    refused = set(re.findall(r"\bMaterial\.(\w+) =", str(e)))
    index = getattr(e, "index", None)
    concerned = [(name, field) for name, field, idx in assignments if index is None or index in idx]
    names = [name for name, field in concerned if field in refused] or [name for name, _ in concerned] or list(values)
    shown = ", ".join(f"{name} = {values[name]:g}" for name in names)
    said = flag("param") if len(names) == 1 or _cli(flag) else "params entries"
    raise ValueError(f"{said} {', '.join(names)} {'is' if len(names) == 1 else 'are'} not allowed: the material refuses every sample's values "
                     f"(sample {k}, {shown}: {_one_line(e)}); give values it allows")


def _check_some_sample_steps(model, assignments, points, frames, fps, rate, length, flag) -> None:
    """Refuse a sweep none of whose samples can take its own stable step at ``fps`` (a frame
    of more than ``MAX_STEPS_PER_FRAME`` steps, or a run of more than ``MAX_STEPS``): each
    failed alone, one after the other, with the same refusal, and the sweep exited 3. A
    sample that can is enough (the others are rows of the table, as a blown-up sample is).
    ``rate``, ``length``: the options (or the scene's values) the refusal names."""
    from .simulate import (STABLE_FIELD_ADVICE, STABLE_HOURGLASS_ADVICE, STABLE_REPULSION_ADVICE, StepRefusal,  # noqa: PLC0415
                           check_step_count, resolve_timestep)

    # The reasons without a run's advice ('give dt= or substeps=', 'a larger dt'): a sweep has no
    # substeps, and a --dt above a sample's stable step blows it up; these are its own options.
    coarser = f"a smaller {flag('scale')} (a larger spacing, whose stable step is longer)"
    first = None
    for k, values in enumerate(points):
        try:
            _apply(model, assignments, values)
        except ValueError:
            continue  # that sample's own refusal, its row's reason
        try:
            substeps, _ = resolve_timestep(model, fps)
        except StepRefusal as e:
            # Its detail, as below: its reason's 'the stable step ... is not allowed' inside the
            # sweep's own '--fps = ... is not allowed for this sweep' said the refusal twice.
            # Where the hourglass control's limit sets the step, its strength lengthens it, not a
            # softer material.
            weaker = ("a smaller --hourglass (or the scene's [solver] hourglass)" if _cli(flag) else
                      "a smaller hourglass control strength (the scene's SceneBuilder(hourglass=...) or [solver] hourglass)")
            cure = (weaker if e.advice == STABLE_HOURGLASS_ADVICE
                    else "a weaker compression field" if e.advice == STABLE_FIELD_ADVICE
                    else "a smaller pair_repulsion or pressure_stiffness" if e.advice == STABLE_REPULSION_ADVICE
                    else "softer or less viscous materials or swept values")
            first = first or (k, values, e.detail, rate, f"give a higher {flag('fps')}, {coarser}, or {cure}")
            continue
        try:
            check_step_count(frames, substeps)
        except StepRefusal as e:
            # Its detail alone: the reason named 'frames = N is not allowed' inside the sweep's own
            # '--frames = N is not allowed for this sweep', the refusal said twice.
            first = first or (k, values, e.detail, length, f"give fewer {flag('frames')} or a shorter {flag('duration')}, or {coarser}")
            continue
        return
    if first is None:
        return
    k, values, why, named, hint = first
    shown = ", ".join(f"{name} = {v:g}" for name, v in values.items())
    raise ValueError(f"{named} is not allowed for this sweep: no sample can run at its own stable step (sample {k}, "
                     f"{shown}: {why}); {hint}")


def _execute(plan: _Plan, workers, ray, on_result, kept: Sequence[dict] = ()) -> SweepTable:
    """Run the plan's samples but those of ``kept`` (rows of a resumed table); the table of all."""
    callback = None if on_result is None else (lambda i, row: on_result(row))
    have = {r["sample"] for r in kept}
    todo = [t for t in plan.tasks if t[1].index not in have]

    def failed(i, why):
        # The worker could not return a row (it died, or Ray lost it): the sample still gets one.
        task = todo[i][1]
        return {"sample": task.index, "status": "failed", **task.values, "seed": task.seed, "reason": why}

    if not todo:
        rows = []
    elif ray is not None and plan.identity["device"] != "cpu":
        with _ray_session(ray) as session:
            _check_ray_gpus(session, ray)
            rows = parallel_map(_run_sample, todo, ray=ray, on_result=callback, on_error=failed,
                                ray_resources=_ray_resources(plan.identity["device"]))
    else:
        rows = parallel_map(_run_sample, todo, workers=workers, ray=ray, on_result=callback, on_error=failed)
    return _table([*kept, *rows], [p.name for p in plan.params], plan.identity)


def _ray_resources(device: str) -> dict | None:
    """What each sample's Ray task asks for beyond its CPU: a GPU where the samples run on
    CUDA. Ray makes only the GPUs a task was given visible to it (``CUDA_VISIBLE_DEVICES``);
    older Ray (and a newer one with ``RAY_ACCEL_ENV_VAR_OVERRIDE_ON_ZERO=1``) hides every GPU
    from a task that asks for none, so each CUDA sample failed, finding no device, and a
    newer one shows such a task every GPU, so that all samples ran on the first."""
    return {"num_gpus": 1} if device != "cpu" else None


def _check_ray_gpus(session, address) -> None:
    """Refuse CUDA samples on a Ray cluster without a GPU: Ray holds a task that asks for one
    where none is, without an end."""
    have = float(session.cluster_resources().get("GPU", 0))
    if have < 1:
        raise ValueError(f"device = 'cuda' is not allowed with ray = {str(address)!r}: the Ray cluster has no GPU "
                         f"({have:g}), and each CUDA sample asks it for one; give device='cpu', or a cluster with GPUs")


def _resumed_rows(source, plan: _Plan, retry_failed, name: str, retry_name: str) -> list[dict]:
    """The rows of the table ``source`` (``resume``; the CLI's ``--resume``, the ``--output``
    folder) to keep: every one, or with ``retry_failed`` the ``ok`` ones. Refuses a table
    that is not of this sweep, naming what differs."""
    retry_failed = checks.boolean(retry_name, retry_failed)
    if source is None:
        if retry_failed:
            raise ValueError(f"{retry_name} is not allowed without {name}: it runs again the failed samples of the "
                             f"table resumed")
        return []
    table, shown = _resume_table(source, name)
    if not isinstance(table.identity, dict):
        raise ValueError(f"{name} = {shown} is not allowed: it holds no record of the sweep that wrote it (sweep.json "
                         f"beside the CSV table, or a Parquet table's metadata, as this version writes), so it cannot "
                         f"be told to be this sweep's; run the sweep anew")
    from .checkpoint import FINGERPRINT_VERSIONS, older_hold, read_fingerprint_version  # noqa: PLC0415

    # A table of an earlier fingerprint version (written before that version's change) is of
    # this sweep where this scene's record of that version is its record.
    ours = plan.identity
    identity = table.identity
    theirs = None
    if "fingerprint_version" in identity:  # a table of record format 1 has none
        theirs = read_fingerprint_version(identity["fingerprint_version"])
        if theirs is None:
            raise ValueError(f"{name} = {shown} is not allowed: its record has fingerprint_version = "
                             f"{_shown(identity['fingerprint_version'])} (must be {FINGERPRINT_VERSIONS}); "
                             f"{_again(name)}")
        # Every check below reads the version as read here (a 3.0 as 3, in a refusal too).
        identity = {**identity, "fingerprint_version": theirs}
    if identity.get("format") == ours["format"] and theirs is not None:
        ours = plan.earlier.get(theirs, ours)
    _check_record_format(identity, ours, name, shown)
    diff = [f"{k} = {_shown(identity.get(k))} there, {_shown(v)} here" for k, v in ours.items()
            if identity.get(k) != v and k != "version"]
    if diff:
        raise ValueError(f"{name} = {shown} is not allowed: its table is of another sweep: {'; '.join(diff)}; resume "
                         f"it with the settings it was run with{_weight_hint(table.identity, plan.identity, name)}, or "
                         f"run this sweep anew without resuming")
    why = older_hold(theirs, *plan.hold)
    if why is not None:
        raise ValueError(f"{name} = {shown} is not allowed: {why}; {_again(name)}")
    names = [p.name for p in plan.params]
    kept: dict[int, dict] = {}
    for r in table.rows:
        i = r.get("sample")
        if isinstance(i, bool) or not isinstance(i, int) or not 0 <= i < len(plan.tasks):
            raise ValueError(f"{name} = {shown} is not allowed: it has a row of sample {i!r}, and this sweep's samples "
                             f"are 0..{len(plan.tasks) - 1}")
        if i in kept:
            raise ValueError(f"{name} = {shown} is not allowed: it has two rows of sample {i}")
        task = plan.tasks[i][1]
        have = {k: r.get(k) for k in names}
        if have != task.values or r.get("seed") != task.seed or r.get("status") not in ("ok", "failed"):
            raise ValueError(f"{name} = {shown} is not allowed: its row of sample {i} ({_row_values(have, r.get('seed'))}, "
                             f"status {r.get('status')!r}) is not this sweep's ({_row_values(task.values, task.seed)}, "
                             f"status ok or failed)")
        kept[i] = r
    # A cell read back as None is a key the run's own row would not have had: without it the
    # resumed table's columns are those of one run straight through.
    return [{k: v for k, v in r.items() if v is not None} for i, r in sorted(kept.items())
            if not retry_failed or r["status"] == "ok"]


def _weight_hint(theirs: dict, ours: dict, name: str) -> str:
    """What names the table's fit weight where it is not this sweep's, else ''. The same
    command begun before the biweight became the default ran poly6, which its record holds
    (every sweep record has the weight: the option is older); its refusal named the model's
    digest and the solver's dict alone, read as another scene, not the option to give."""
    weight = (theirs.get("solver") if isinstance(theirs.get("solver"), dict) else {}).get("fit_weight")
    if not isinstance(weight, str) or weight == ours["solver"]["fit_weight"]:
        return ""
    how = (f"--fit-weight {weight}" if name.startswith("--")
           else f"the scene's fit_weight = {weight!r}, SceneBuilder(fit_weight=...) or [solver] fit_weight")
    then = "; a sweep begun before 2026-12-06 that named none ran poly6, the default then" if weight == "poly6" else ""
    return f" (its fit weight: {how}{then})"


def _again(name: str) -> str:
    """What a refused resume says to do instead (``name``: ``--resume``, or ``resume``)."""
    return "rerun without --resume" if name.startswith("--") else "rerun without resume"


def _check_record_format(theirs: dict, ours: dict, name: str, shown: str) -> None:
    """Refuse, in one line, a table another version of the package wrote: of another record
    format its identity cannot be compared (its model digest is made otherwise, and every
    table of the same scene read as another scene's), and of the same format but another
    version its rows may hold other results (a physics change), which resumed rows would mix
    with this version's where a run straight through holds one version's alone."""
    again = _again(name)
    fmt = (theirs.get("format", 1), theirs.get("fingerprint_version", 1 if "format" not in theirs else None))
    here = (ours["format"], ours["fingerprint_version"])
    by = f"warp_esph {theirs['version']}" if isinstance(theirs.get("version"), str) else "an earlier warp_esph"
    if fmt != here:
        raise ValueError(f"{name} = {shown} is not allowed: this table was written by {by} (record format {fmt[0]}, "
                         f"model fingerprint {fmt[1]}); this is warp_esph {ours['version']} (record format {here[0]}, "
                         f"model fingerprint {here[1]}), whose record of a sweep is another, so the table cannot be told "
                         f"to be this sweep's: {again} (or resume it with the version that wrote it)")
    if theirs.get("version") != ours["version"]:
        raise ValueError(f"{name} = {shown} is not allowed: this table was written by {by} (record format {fmt[0]}); "
                         f"this is warp_esph {ours['version']} (record format {here[0]}): another version may compute "
                         f"other results, and the table would mix the two: resume it with warp_esph "
                         f"{theirs.get('version')}, or {again}")


def _shown(v) -> str:
    if isinstance(v, list) and all(isinstance(x, str) for x in v):
        return "[" + ", ".join(v) + "]"
    return json.dumps(v)


def _row_values(values: Mapping, seed) -> str:
    return ", ".join([*(f"{k} = {v!r}" for k, v in values.items()), f"seed = {seed!r}"])


def _resume_table(source, name: str) -> tuple[SweepTable, str]:
    """The table ``source`` names and how a refusal shows it."""
    if isinstance(source, SweepTable):
        return source, f"<SweepTable of {len(source)} rows>"
    if not isinstance(source, (str, bytes, os.PathLike)):
        raise ValueError(f"{name} = {checks.shorten(source)!r} is not allowed: give a SweepTable, a sweep's output "
                         f"folder, its sweep.csv or a Parquet table")
    path = os.fspath(source)
    if isinstance(path, bytes):
        path = os.fsdecode(path)
    shown = repr(path)
    if os.path.isdir(path):
        folder = path
        path = next((os.path.join(folder, f) for f in ("sweep.csv", "sweep.parquet")
                     if os.path.isfile(os.path.join(folder, f))), None)
        if path is None:
            raise ValueError(f"{name} = {shown} is not allowed: the folder holds no sweep.csv or sweep.parquet, so there "
                             f"is nothing to resume; run the sweep without it")
    elif os.path.isfile(path):
        folder = os.path.dirname(path)
    else:
        raise ValueError(f"{name} = {shown} is not allowed: there is no such file or folder, so there is nothing to "
                         f"resume; run the sweep without it")
    if path.endswith(".parquet"):
        try:
            table = SweepTable.read_parquet(path)
        except ImportError:
            raise ValueError(f"{name} = {shown} is not allowed: reading {checks.shown_path(path)} needs pyarrow (pip install pyarrow); "
                             f"or resume from the sweep.csv beside it") from None
        if table.identity is not None:
            return table, shown
    record = os.path.join(folder, "sweep.json")
    meta = None
    if os.path.isfile(record):
        try:
            with open(record, encoding="utf-8") as f:
                meta = json.load(f)
        except (OSError, ValueError) as e:
            raise ValueError(f"{name} = {shown} is not allowed: its record {record!r} cannot be read: "
                             f"{_one_line(e)}") from None
    meta = meta if isinstance(meta, dict) else {}
    if not path.endswith(".parquet"):
        types = meta.get("column_types")
        # The columns' types as written: an extra's text "007" read back by its cells was the number 7.
        table = SweepTable._read_csv_kept(path, types if isinstance(types, dict) else None)
    table.identity = meta.get("sweep")
    if isinstance(table.identity, dict) and "version" not in table.identity and isinstance(meta.get("version"), str):
        # A record of format 1 kept the version beside it alone: the refusal names it.
        table.identity = {**table.identity, "version": meta["version"]}
    return table, shown


# ------------------------------------------------------------------ outputs
_UNITS = {"centroid_height": "m", "max_height": "m", "radial_spread": "m", "max_radius": "m", "kinetic_energy": "J"}


def plot(table: SweepTable, path, log_params: Sequence[str] = (), quantities: Sequence[str] = SUMMARY_COLUMNS) -> str:
    """One panel per (quantity, parameter): the quantity of every sample against the
    parameter; failed samples are red crosses on the axis. ``quantities``: columns of the
    table; ``log_params``: parameters drawn on a log axis (each a name or a list of names).
    Written at ``path`` in the format of its extension (PNG without one). Needs matplotlib."""
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    names = table.params
    # A name the table lacks was dropped without a word (all of them: matplotlib's 'Number of
    # rows must be a positive integer, not 0'), a string read letter by letter.
    quantities = [quantities] if isinstance(quantities, str) else list(quantities)
    log_params = [log_params] if isinstance(log_params, str) else list(log_params)
    for label, given, have in (("quantities", quantities, table.columns), ("log_params", log_params, names)):
        unknown = [q for q in given if q not in have]
        if unknown or (label == "quantities" and not given):
            raise ValueError(f"{label} = {checks.shorten(given)!r} is not allowed: "
                             + (f"the table has no column {unknown[0]!r}" if unknown else "give at least one")
                             + f"; choose from {', '.join(have)}")
    ok = table.column("status") == "ok"
    fig, axes = plt.subplots(len(quantities), len(names), figsize=(3.2 * len(names) + 0.6, 2.4 * len(quantities) + 0.6),
                             squeeze=False, sharex="col", constrained_layout=True)
    try:
        return _draw(fig, axes, table, names, quantities, ok, log_params, path)
    finally:
        plt.close(fig)  # also where drawing fails: a sweep in a loop kept every failed figure open


def _draw(fig, axes, table, names, quantities, ok, log_params, path) -> str:
    for j, name in enumerate(names):
        x = table.column(name)
        for i, q in enumerate(quantities):
            ax = axes[i, j]
            ax.scatter(x[ok], table.column(q)[ok], s=14, alpha=0.8)
            if (~ok).any():
                ax.scatter(x[~ok], np.zeros((~ok).sum()), transform=ax.get_xaxis_transform(), marker="x", color="red",
                           s=30, clip_on=False, label="failed")
            if name in log_params:
                ax.set_xscale("log")
            # The failed marks are drawn in axes coordinates, which autoscaling ignores.
            fin = x[np.isfinite(x)]
            if fin.size and fin.max() > fin.min():
                lo, hi = float(fin.min()), float(fin.max())
                if name in log_params and lo > 0:
                    pad = (hi / lo) ** 0.05
                    ax.set_xlim(lo / pad, hi * pad)
                else:
                    ax.set_xlim(lo - 0.05 * (hi - lo), hi + 0.05 * (hi - lo))
            if j == 0:
                ax.set_ylabel(f"{q.replace('_', ' ')} ({_UNITS.get(q, '')})")
            if i == len(quantities) - 1:
                ax.set_xlabel(name)
    fig.suptitle(f"{len(table)} samples, {int(ok.sum())} ok")
    path = os.fspath(path)
    # Without an extension matplotlib wrote path + '.png', and the path returned was not the file.
    ext = os.path.splitext(path)[1].lstrip(".").lower()
    fig.savefig(path, dpi=100, format=ext or "png")
    return path


def write_outputs(table: SweepTable, folder, meta: Mapping | None = None, log_params: Sequence[str] = (),
                  plot_figure: bool = True) -> list[str]:
    """Write ``sweep.csv``, ``sweep.parquet`` (with pyarrow), ``sweep.png`` (with
    matplotlib) and ``sweep.json`` (``meta``, the table's ``identity`` as ``sweep`` and its
    ``column_types``, which ``sweep.csv`` is read back by) into ``folder``; returns one line per file
    written or skipped. ``folder`` is made where it is not there; a file there is refused
    (``ValueError``: it was a bare ``FileExistsError`` from ``os.makedirs``)."""
    folder = os.fspath(folder)
    if os.path.exists(checks.bare_path(folder)) and not os.path.isdir(folder):
        raise ValueError(f"folder = {checks.shown_path(folder)} is not allowed: it is a file; the sweep's tables ({', '.join(OUTPUT_FILES)}) "
                         "are written into a folder, one that is there or one that is made")
    os.makedirs(folder, exist_ok=True)
    # The record first, then the tables: it holds the sweep's identity, which a resumed sweep is
    # checked against, and the columns' types, which the CSV is read back by (the CSV has no
    # place for either). Written after them, a kill in between (the first Parquet write imports
    # pyarrow, a second or so) left a sweep.csv with no record, which --resume refuses, so every
    # sample ran again; the identity is the same in every rewrite, and a record one rewrite
    # ahead of its table resumes as well. Before the plot, which must not hold it up.
    record = {**(meta or {}), **({"sweep": table.identity} if table.identity is not None else {}),
              "column_types": table.types()}
    path = os.path.join(folder, "sweep.json")
    if table.identity is not None and _recorded_identity(path) != table.identity:
        # Tables of another sweep (or of none recorded) must not stand beside this sweep's record
        # if the writes below are cut off: a resume would take their rows for this sweep's.
        for name in ("sweep.csv", "sweep.parquet"):
            with contextlib.suppress(FileNotFoundError):
                os.remove(os.path.join(folder, name))
    with checks.replaced_atomically(path) as tmp, open(tmp, "w") as f:
        json.dump(record, f, indent=2)
    lines = [f"wrote {table.to_csv(os.path.join(folder, 'sweep.csv'))}"]
    try:
        lines.append(f"wrote {table.to_parquet(os.path.join(folder, 'sweep.parquet'))}")
    except ImportError:
        lines.append("no Parquet table: pyarrow is not installed (pip install pyarrow); the CSV has the same data")
    lines.append(f"wrote {path}")
    if plot_figure:
        lines.append(_plot_line(table, folder, log_params))
    return lines


def _recorded_identity(path: str):
    """The sweep identity the record ``path`` (a ``sweep.json``) holds; None where there is none."""
    try:
        with open(path, encoding="utf-8") as f:
            meta = json.load(f)
    except (OSError, ValueError):
        return None
    return meta.get("sweep") if isinstance(meta, dict) else None


def _plot_line(table: SweepTable, folder: str, log_params: Sequence[str]) -> str:
    """Draw ``sweep.png`` in ``folder``; the line saying so, or why there is none (an earlier
    sweep's picture is removed then, also when a Ctrl-C stops the drawing)."""
    picture = os.path.join(folder, "sweep.png")
    line = None
    try:
        line = f"wrote {plot(table, picture, log_params)}"
    except ImportError:
        line = "no plot: matplotlib is not installed (pip install 'warp-esph[plot]')"
    except (ValueError, ArithmeticError) as e:
        # matplotlib cannot lay out axes of values near the float range ('arange: cannot
        # compute length' at 1e307..1.7e308): the sweep ran and its tables stand.
        line = f"no plot: matplotlib could not draw these values ({e}); the CSV has the data"
    except OSError as e:
        # The tables are written whole by now: a picture that cannot be saved (a full disk)
        # is no failed sweep.
        line = f"no plot: it could not be written ({e}); the CSV has the data"
    finally:
        if (line is None or line.startswith("no plot")) and os.path.isfile(picture):
            os.remove(picture)  # an earlier sweep's picture would no longer match the tables
    return line


#: Exit status of ``warp-esph sweep`` when at least one sample failed (the table has them).
EXIT_SOME_FAILED = 3
#: The files ``write_outputs`` writes into the output folder.
OUTPUT_FILES = ("sweep.csv", "sweep.parquet", "sweep.png", "sweep.json")
#: Seconds between the CLI's rewrites of the table while samples finish (a killed sweep
#: keeps what it had written; the last rewrite, at the end, is the whole table).
PARTIAL_EVERY_S = 2.0


def sweep_cli(args, out=None) -> int:
    """Run ``warp-esph sweep`` from parsed ``args``: 0 every sample ran, ``EXIT_SOME_FAILED``
    (3) some failed (see the table's ``reason``), 130 interrupted (the finished samples are
    written; ``--resume`` goes on from them). Raises ``ValueError`` on bad input (the CLI
    exits 2)."""
    from . import __version__  # noqa: PLC0415
    from .cli import EXIT_INTERRUPTED, EXIT_WRITE_FAILED, PROG, option_flag  # noqa: PLC0415

    out = sys.stdout if out is None else out
    from .cli import _solver_options  # noqa: PLC0415

    options = _solver_options(args)
    if not args.param:  # (sweep()'s own refusal names its argument, 'params = []', which nobody typed here)
        raise ValueError("--param is required: give at least one --param NAME=LO:HI:SCALE:N (e.g. yield_stress=100:1000:log:8)")
    if args.sample == "grid" and getattr(args, "seed_given", False):
        # Refused, not ignored, as fit refuses it where nothing is drawn: a grid's samples ran
        # exactly as without it, only the table's seed column differed (the CLI passes no extra
        # column function, the only user of the samples' seeds).
        raise ValueError(f"--seed = {checks.shorten(args.seed)!r} is not allowed with --sample grid: it seeds the draws of --sample "
                         "random and lhs, and a grid draws nothing")
    _refuse_workers_with_ray(args.workers, args.ray, "--workers", "--ray")
    # Every task holds the plan's scene: its builder's [solver] options, overridden, reach each sample's Solver(model).
    plan = _plan(args.scene, args.param or [], args.sample, args.samples, args.seed, args.frames, args.duration, args.fps,
                 args.dt, args.scale, args.dtype, "cpu", args.workers, args.max_samples, None, args.ray, options, option_flag)
    sc, plist, points = plan.scene, plan.params, plan.tasks
    folder = args.output if args.output is not None else f"sweep_{sc.name}"  # '' fell back to the default
    checks.output_place("--output", folder, folder=True)  # before the first sample, not after
    for name in OUTPUT_FILES:  # a folder in the way of one was found after every sample had run
        if os.path.isdir(os.path.join(folder, name)):
            raise ValueError(f"--output = {checks.shown_path(folder)} is not allowed: {checks.shown_path(os.path.join(folder, name))} is a folder; the "
                             f"sweep writes its {name} there")
    checks.output_files("--output", folder, OUTPUT_FILES)
    if args.retry_failed and not args.resume:
        raise ValueError("--retry-failed is not allowed without --resume: it runs again the failed samples of the table "
                         "resumed")
    # Read and checked before the first sample: a table of another sweep is refused, not overwritten.
    kept = _resumed_rows(folder if args.resume else None, plan, args.retry_failed, "--resume of --output", "--retry-failed")
    to_run = len(points) - len(kept)
    # Connected (or refused) before the plan's line, which says the sweep runs on Ray: an
    # address or 'auto' where no cluster runs is then the one line on stderr.
    with _ray_session(args.ray, "--ray") if args.ray is not None else contextlib.nullcontext():
        where = f"Ray at {args.ray}" if args.ray else checks.plural(min(args.workers or _cores(), max(to_run, 1)), "worker")
        resumed = f", {len(kept)} kept from its table, {to_run} to run" if args.resume else ""
        print(f"{PROG} sweep: {sc.name}: {len(points)} samples ({args.sample}) of {', '.join(p.name for p in plist)} "
              f"on {where} -> {folder}{resumed}", file=sys.stderr, flush=True)
        # The kept rows first: the tables written as samples finish, and on a stop, keep them too.
        done: list[dict] = list(kept)
        bar = None
        if not args.no_progress:
            from .simulate import _progress_bar  # noqa: PLC0415

            bar = _progress_bar(to_run, "samples")

        written = [0.0]

        def record(row):
            from .cli import _safe_point  # noqa: PLC0415

            done.append(row)
            if bar is not None:
                bar.update(1)
            # The samples finished so far, on disk as they come (at most every PARTIAL_EVERY_S): a
            # killed sweep (SIGKILL, out of memory) kept none of them.
            if written[0] is not None and time.perf_counter() - written[0] >= PARTIAL_EVERY_S:
                try:
                    write_outputs(_table(done, [p.name for p in plist], plan.identity), folder,
                                  {**meta, "partial": True, "samples_done": len(done)}, log_params, plot_figure=False)
                    written[0] = time.perf_counter()
                except (OSError, ValueError, ImportError) as e:  # a convenience: the sweep goes on without it
                    print(f"{PROG}: warning: the table so far could not be written ({e}); the sweep goes on and writes "
                          "it at its end", file=sys.stderr)
                    written[0] = None
            _safe_point(args)  # a Ctrl-C that landed in a finalizer stops the sweep here, this sample kept

        meta = {"command": "sweep", "version": __version__, "scene": args.scene if args.scene else sc.name,
                "scale": args.scale, "params": [dataclasses.asdict(p) for p in plist], "sample": args.sample,
                "samples": len(points), "seed": args.seed,
                # The frames each sample ran: a --duration is rounded to whole frames, at least one
                # (1e-320 s recorded "frames": null beside it, as if no frame had run).
                "frames": plan.tasks[0][1].frames if plan.tasks else args.frames, "duration": args.duration, "fps": args.fps,
                "dt": args.dt, "dtype": args.dtype, "workers": args.workers, "ray": args.ray,
                "fit": sc.builder.fit, "contact_ramp": sc.builder.contact_ramp, "hourglass": sc.builder.hourglass,
                "fit_weight": sc.builder.fit_weight}
        if args.scene and os.path.exists(str(args.scene)):
            meta["scene"] = os.path.abspath(args.scene)
        if args.resume:
            meta["resumed"] = {"kept": len(kept), "retry_failed": args.retry_failed}
        log_params = [p.name for p in plist if p.values is None and p.scale == "log"]
        from .cli import _arm, _signal_name, _stopped  # noqa: PLC0415

        _arm(args)  # from here Ctrl-C unwinds to the except below, which writes the samples finished
        t0 = time.perf_counter()
        try:
            table = _execute(plan, args.workers, args.ray, record, kept)
        except KeyboardInterrupt:
            if bar is not None:
                bar.close()
            table = _table(done, [p.name for p in plist], plan.identity)
            from .cli import _Deferred  # noqa: PLC0415

            try:
                # A second signal here (a second Ctrl-C; timeout signals the command, then its
                # group) ended the process at once: no table of the stopped sweep, a stray
                # .sweep.<pid>.part.csv beside the last partial one. It waits for the tables.
                with _Deferred(args):
                    # The signal by name, as the line says it and a stopped fit's fit.json records it.
                    written = write_outputs(table, folder, {**meta, "interrupted": True, "signal": _signal_name(args) or None},
                                            log_params)
            except (OSError, ValueError) as e:
                # A full disk under the table of the samples finished: the error reached the
                # command's handler as bad input (exit 2), the signal dropped and the folder unsaid.
                print(f"{PROG}: {_stopped(args)}: cannot write the table of the {len(done)} of {len(points)} samples "
                      f"finished in {checks.shown_path(folder, False)}: {_one_line(e)} (the tables in {checks.shown_path(folder, False)} do not keep them all)", file=sys.stderr)
                return EXIT_INTERRUPTED
            for line in written:
                print(line, file=out)
            print(f"{PROG}: {_stopped(args)}: the table keeps the {len(done)} of {len(points)} samples finished", file=sys.stderr)
            return EXIT_INTERRUPTED
        if bar is not None:
            bar.close()
        meta["seconds"] = time.perf_counter() - t0
        from .cli import _Deferred  # noqa: PLC0415

        from .cli import _held_signal_wins, _signals_seen  # noqa: PLC0415

        lines: list[str] = []
        seen = _signals_seen(args)
        try:
            # Every sample ran: a Ctrl-C while the tables are written waits for them (it cut one
            # short of the partial table, and the line said 'interrupted' alone); one under the
            # picture stops it, the tables whole.
            with _Deferred(args, then_stop=True):
                lines = write_outputs(table, folder, meta, log_params, plot_figure=False)
            lines.append(_plot_line(table, folder, log_params))
        except KeyboardInterrupt:
            # A signal held until the tables were whole stops the command before the plot is
            # drawn: an earlier sweep's picture stayed beside the new tables.
            with contextlib.suppress(OSError):
                os.remove(os.path.join(folder, "sweep.png"))
            for line in lines:
                print(line, file=out)
            print(f"{PROG}: {_stopped(args)}: the tables in {folder} keep all {len(table)} samples; sweep.png is not "
                  "written", file=sys.stderr)
            return EXIT_INTERRUPTED
        except OSError as e:
            # A full disk or a folder gone at the end: a failed write (not bad input, exit 2), and
            # what is left on disk said.
            from .cli import _err  # noqa: PLC0415

            said = (f"cannot write the sweep's tables in {checks.shown_path(folder, False)}: {e} ({len(table)} samples ran; the tables in "
                    f"{checks.shown_path(folder, False)} are not this sweep's whole result)")
            if _held_signal_wins(args, seen, said):
                return EXIT_INTERRUPTED
            _err(said)
            return EXIT_WRITE_FAILED
        except ValueError as e:
            # Not a failed write (exit 2 as before, said by the command's own handler); but a
            # signal held under it was dropped with it: the command was asked to stop.
            if _held_signal_wins(args, seen, str(e)):
                return EXIT_INTERRUPTED
            raise
        for line in lines:
            print(line, file=out)
        failed = table.failed
        print(f"{len(table)} samples, {len(table) - len(failed)} ok, {len(failed)} failed, {meta['seconds']:.1f} s", file=out)
        for r in failed[:5]:
            print(f"{PROG}: sample {r['sample']} failed: {r.get('reason')}", file=sys.stderr)
        if len(failed) > 5:
            print(f"{PROG}: ... and {len(failed) - 5} more failed samples (see the table's reason column)", file=sys.stderr)
        return EXIT_SOME_FAILED if failed else 0
