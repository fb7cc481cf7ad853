"""The benchmarks' command lines: checked option values and one-line errors.

Every ``python -m benchmarks.<name>`` refuses bad input before it runs anything, with one
line on standard error that names the option, its value and what is allowed, and exit
status 2::

    python -m benchmarks.step: error: --steps = 0 is not allowed: must be an integer >= 1

``Parser`` is an ``argparse.ArgumentParser`` whose errors are that one line. The checks
below are its ``type=`` helpers (``positive_int``, ``positive_float``, ``int_list``,
``device``, ``output_file``, ``json_file``...): given to ``Parser.add_argument`` they learn
the option's name, so their error reads as above; called as ``check(text, "--name")`` they
raise it with that name (``Refused``: an ``argparse.ArgumentTypeError`` and a ``ValueError``).
``run(main, prog)`` calls a module's ``main`` and turns a ``ValueError`` or ``OSError`` it
raises (a file that cannot be written, a JSON that cannot be read) into the same one line
and exit status 2.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import pathlib
import re
import sys

# --------------------------------------------------------------------------- the parser


class Parser(argparse.ArgumentParser):
    """``argparse.ArgumentParser`` with one-line errors (``prog: error: message``, exit 2) and
    ``Check`` types that name their option."""

    def add_argument(self, *args, **kwargs):
        kind = kwargs.get("type")
        if isinstance(kind, Check) and kind.name is None:
            longs = [a for a in args if a.startswith("--")]
            name = longs[0] if longs else (args[0] if args and args[0].startswith("-") else
                                           kwargs.get("metavar") or (args[0] if args else kwargs.get("dest", "value")))
            kwargs["type"] = kind.named(str(name))
        return super().add_argument(*args, **kwargs)

    def error(self, message):
        # argparse writes "argument --steps: --steps = 0 is not allowed: ..." for a Check: the
        # option is named once.
        message = str(message)
        m = re.match(r"argument ([^:]+): (.*)\Z", message, re.S)
        if m and any(m.group(2).startswith(n + " = ") for n in m.group(1).split("/")):
            message = m.group(2)
        fail(self.prog, message)


def fail(prog: str, message) -> None:
    """Print ``prog: error: message`` as one line on standard error and exit with status 2."""
    text = " ".join(str(message).split()) or type(message).__name__
    sys.stderr.write(f"{prog}: error: {text}\n")
    sys.stderr.flush()
    raise SystemExit(2)


def run(main, prog: str, argv=None):
    """``main(argv)``; a ``ValueError`` or ``OSError`` it raises (``json.JSONDecodeError``
    and ``UnicodeDecodeError`` are ``ValueError``) ends the command with one line on standard
    error and exit status 2. Returns what ``main`` returns."""
    try:
        return main(argv)
    except (ValueError, OSError) as e:
        fail(prog, e)


# --------------------------------------------------------------------------- checks


class Check:
    """An argparse ``type``: ``fn(text, name)`` returns the value or raises ``Refused``;
    ``name`` is the option (``Parser`` fills it in)."""

    def __init__(self, fn, name: str | None = None):
        self.fn = fn
        self.name = name
        self.__name__ = getattr(fn, "__name__", "value")

    def named(self, name: str) -> Check:
        return Check(self.fn, name)

    def __call__(self, text, name: str | None = None):
        return self.fn(text, name or self.name or "value")

    def __repr__(self):
        return self.__name__


class Refused(argparse.ArgumentTypeError, ValueError):
    """A value refused: an ``argparse.ArgumentTypeError`` for a parser, a ``ValueError`` for
    ``run`` and for callers of the checks."""


def refuse(name: str, value, allowed: str) -> Refused:
    """``Refused("name = value is not allowed: allowed")``."""
    return Refused(f"{name} = {shown(value)} is not allowed: {allowed}")


def shown(value) -> str:
    """A value as an error shows it: a number as written, any other text quoted."""
    if isinstance(value, str):
        try:
            float(value)
        except ValueError:
            return repr(value)
        return value.strip()
    return repr(value)


def as_int(text, name: str, lo: int, what: str) -> int:
    """``int(text)`` if it is an integer >= ``lo``, else ``Refused`` with ``what`` allowed."""
    try:
        value = int(text)
    except (TypeError, ValueError):
        raise refuse(name, text, what) from None
    if value < lo:
        raise refuse(name, text, what)
    return value


def int_at_least(lo: int) -> Check:
    """An integer >= ``lo``."""

    def check(text, name):
        return as_int(text, name, lo, f"must be an integer >= {lo}")

    check.__name__ = f"int_at_least_{lo}"
    return Check(check)


positive_int = int_at_least(1)
nonnegative_int = int_at_least(0)


def number(lo: float | None = None, hi: float | None = None, lo_open: bool = False, hi_open: bool = False) -> Check:
    """A finite number, ``>= lo`` (``> lo`` with ``lo_open``) and ``<= hi`` (``< hi``) where given."""
    parts = []
    if lo is not None:
        parts.append(f"{'>' if lo_open else '>='} {lo:g}")
    if hi is not None:
        parts.append(f"{'<' if hi_open else '<='} {hi:g}")
    what = "must be a finite number" + (" " + " and ".join(parts) if parts else "")

    def check(text, name):
        try:
            value = float(text)
        except (TypeError, ValueError):
            raise refuse(name, text, what) from None
        if not math.isfinite(value):
            raise refuse(name, text, what)
        if lo is not None and (value <= lo if lo_open else value < lo):
            raise refuse(name, text, what)
        if hi is not None and (value >= hi if hi_open else value > hi):
            raise refuse(name, text, what)
        return value

    check.__name__ = "number"
    return Check(check)


positive_float = number(0.0, lo_open=True)
nonnegative_float = number(0.0)
finite_float = number()


def int_list(lo: int = 1) -> Check:
    """A comma-separated list of integers >= ``lo`` (at least one): a ``list[int]``."""
    what = f"must be a comma-separated list of integers >= {lo}"

    def check(text, name):
        parts = [p.strip() for p in str(text).split(",")]
        if not any(parts):
            raise refuse(name, text, what)
        out = []
        for p in parts:
            try:
                value = int(p)
            except ValueError:
                raise refuse(name, text, f"{what} ({p!r} is not one)") from None
            if value < lo:
                raise refuse(name, text, f"{what} ({p} is not one)")
            out.append(value)
        return out

    check.__name__ = "int_list"
    return Check(check)


positive_int_list = int_list(1)


def choice_list(choices) -> Check:
    """A comma-separated list of ``choices`` (at least one): a ``list[str]``."""
    choices = tuple(choices)
    what = f"must be a comma-separated list of {', '.join(choices)}"

    def check(text, name):
        parts = [p.strip() for p in str(text).split(",")]
        bad = [p for p in parts if p not in choices]
        if not parts or bad:
            raise refuse(name, text, what + (f" ({bad[0]!r} is not one)" if bad else ""))
        return parts

    check.__name__ = "choice_list"
    return Check(check)


@contextlib.contextmanager
def _quiet_native_stderr():
    """File descriptor 2 sent to /dev/null (Warp's native CUDA notes for a missing driver)."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):
        yield
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


def device_problem(text) -> str | None:
    """Why Warp has no device ``text`` here (``cpu``, ``cuda``, ``cuda:0``...), or None if it
    has. Starts Warp (``warp_esph.startup.init_warp``) if it has not started."""
    from warp_esph.startup import init_warp  # noqa: PLC0415 (importing this module must not load Warp)

    init_warp()
    import warp as wp  # noqa: PLC0415

    try:
        with _quiet_native_stderr():
            wp.get_device(text)
    except (RuntimeError, ValueError, TypeError) as e:
        have = ", ".join(str(d) for d in wp.get_devices())
        return " ".join(str(e).split()).rstrip(".") + f" (Warp's devices here: {have})"
    return None


def check_device(text, name: str = "--device") -> str:
    """``text`` if Warp has that device here, else ``Refused`` naming the devices it has."""
    problem = device_problem(text)
    if problem:
        raise refuse(name, str(text), problem)
    return text


device = Check(check_device)


def _first_existing(path: pathlib.Path) -> pathlib.Path:
    p = path
    while True:
        try:
            if p.exists() or p == p.parent:
                return p
        except OSError:
            pass
        p = p.parent


def check_output_file(text, name: str = "--json") -> str:
    """``text`` if a file can be written there: not a folder, in a folder that exists and is
    writable. Nothing is created."""
    if not str(text).strip():
        raise refuse(name, text, "must be a file path")
    path = pathlib.Path(text)
    if path.is_dir():
        raise refuse(name, text, "it is a folder, not a file")
    folder = path.parent
    if not folder.is_dir():
        anc = _first_existing(folder)
        if anc.exists() and not anc.is_dir():
            raise refuse(name, text, f"'{anc}' is a file, not a folder")
        raise refuse(name, text, f"its folder '{folder}' does not exist")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise refuse(name, text, f"its folder '{folder}' is not writable")
    if path.exists() and not os.access(path, os.W_OK):
        raise refuse(name, text, "the file is not writable")
    _probe(name, text, folder=False)
    return text


def _probe(name: str, text, folder: bool, place=None) -> None:
    """Whether a file can really be created there (``warp_esph.checks.output_place``; ``place``:
    the folder probed for ``text``, default ``text``): ``os.access`` says yes to root everywhere,
    /proc included, and the benchmark then ran to its end and failed writing its result."""
    from warp_esph import checks  # noqa: PLC0415

    try:
        checks.output_place(name, text if place is None else place, folder=folder)
    except ValueError as e:
        # The refusal names the value typed: '--out /proc/x/y' read "--out = '/proc'".
        raise refuse(name, text, str(e).split("is not allowed: ", 1)[-1]) from None


output_file = Check(check_output_file)


def check_output_folder(text, name: str = "--out") -> str:
    """``text`` if it is a writable folder or one that can be made (its nearest existing
    parent is a writable folder). Nothing is created."""
    if not str(text).strip():
        raise refuse(name, text, "must be a folder path")
    path = pathlib.Path(text)
    if path.exists():
        if not path.is_dir():
            raise refuse(name, text, "it is a file, not a folder")
        if not os.access(path, os.W_OK | os.X_OK):
            raise refuse(name, text, "the folder is not writable")
        _probe(name, text, folder=True)
        return text
    anc = _first_existing(path.parent)
    if not anc.is_dir():
        raise refuse(name, text, f"'{anc}' is a file, not a folder")
    if not os.access(anc, os.W_OK | os.X_OK):
        raise refuse(name, text, f"the folder cannot be made: '{anc}' is not writable")
    # The benchmarks make a missing folder with its parents (warp-esph's commands make only the
    # last one): the probe is of the folder that would take them.
    _probe(name, text, folder=True, place=str(anc))
    return text


output_folder = Check(check_output_folder)


def load_json(text, name: str = "--json", kinds=(dict, list)):
    """The data of the JSON file ``text``: it must exist, be a file, hold UTF-8 JSON and parse
    to one of ``kinds`` (an object or a list); else ``Refused``."""
    if not str(text).strip():
        raise refuse(name, text, "must be the path of a JSON file")
    path = pathlib.Path(text)
    try:
        if not path.exists():
            raise refuse(name, text, "no such file")
        if path.is_dir():
            raise refuse(name, text, "it is a folder, not a JSON file")
        if not path.is_file():
            raise refuse(name, text, "it is not a regular file")
        raw = path.read_bytes()
    except OSError as e:
        raise refuse(name, text, f"it cannot be read ({e.strerror or e})") from None
    if not raw.strip():
        raise refuse(name, text, "the file is empty, not JSON")
    try:
        data = json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError:
        raise refuse(name, text, "it is not a JSON file (not UTF-8 text)") from None
    except json.JSONDecodeError as e:
        raise refuse(name, text, f"it is not valid JSON ({e.msg} at line {e.lineno} column {e.colno})") from None
    if not isinstance(data, tuple(kinds)):
        want = " or ".join({dict: "an object", list: "a list"}.get(k, k.__name__) for k in kinds)
        raise refuse(name, text, f"it must hold a JSON {want}, not {type(data).__name__}")
    return data


def _json_file(text, name):
    load_json(text, name)
    return text


#: A JSON file that exists and holds an object or a list (the value stays the path).
json_file = Check(_json_file)
