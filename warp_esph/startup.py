"""Starting Warp quietly: ``init_warp()`` for scripts, notebooks, the CLI and sweep workers.

``wp.config.log_level`` silences what Warp's Python side prints at start-up (the banner, the
kernel-cache line, module loads). One note does not pass through it: on a machine without a
CUDA driver, Warp's native initialisation writes "could not find or load the NVIDIA CUDA
driver" straight to the process's standard error, below Python. For a CPU run that note is
noise (a notebook would carry it in its committed outputs); for a run that asked for a GPU it
is the reason the run cannot go on. ``init_warp`` holds the native output back while Warp
starts and decides which of the two it is.
"""

from __future__ import annotations

import os
import sys
import tempfile


def _native_notes(init) -> list[str]:
    """Run ``init()`` with file descriptor 2 sent to a temporary file; return its lines."""
    try:
        if sys.stderr is not None:  # None where the process started with descriptor 2 closed (2>&-)
            sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no real stderr (some embedded interpreters)
        init()
        return []
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        tmp.seek(0)
        text = tmp.read().decode(errors="replace")
    return [line for line in text.splitlines() if line.strip()]


class UnreadStream:
    """A text stream (standard error) whose writes are dropped once its reader has left
    (``BrokenPipeError``: ``2> >(head -c 1)``, a closed log pipe): a progress bar or a note
    nobody can read any more must not end the work it reports on (a run ended with exit 1
    after two frames, a traceback written to nobody). Any other error still raises."""

    def __init__(self, stream):
        self.stream = stream
        self.gone = False

    def write(self, text):
        if not self.gone:
            try:
                return self.stream.write(text)
            except BrokenPipeError:
                self.gone = True
        return len(text)

    def flush(self):
        if not self.gone:
            try:
                self.stream.flush()
            except BrokenPipeError:
                self.gone = True

    def __getattr__(self, name):  # fileno, isatty, encoding: the stream's own
        return getattr(self.stream, name)


def unread_stream(stream):
    """``stream`` as an ``UnreadStream`` (itself where it already is one, or None)."""
    return stream if stream is None or isinstance(stream, UnreadStream) else UnreadStream(stream)


def _cache_refusal(e: OSError, cache, configured=None) -> str | None:
    """The refusal of a kernel cache folder ``wp.init`` could not make (``e``; None where
    ``e`` is of something else): Warp's own ``[Errno 20] Not a directory: '.../1.19.0'``
    named neither ``WARP_CACHE_PATH`` nor what it must be. ``configured``: the
    ``wp.config.kernel_cache_dir`` set before ``wp.init``, which Warp takes over the variable."""
    from . import checks  # noqa: PLC0415

    if not (e.filename and cache and os.fspath(cache).startswith(os.fspath(e.filename))):
        return None
    why = e.strerror or str(e)
    if configured is not None:
        # Not the variable: it was fine, and the advice to change it changed nothing.
        return (f"wp.config.kernel_cache_dir = {checks.shown_path(configured)} is not allowed: Warp keeps its compiled "
                f"kernels in a folder there (before WARP_CACHE_PATH), and cannot make {checks.shown_path(cache)} ({why}); "
                "give a folder that is there or can be made, or leave it None")
    given = os.environ.get("WARP_CACHE_PATH")
    if given:
        return (f"WARP_CACHE_PATH = {checks.shown_path(given)} is not allowed: Warp keeps its compiled kernels in a folder "
                f"there, and cannot make {checks.shown_path(cache)} ({why}); give a folder that is there or can be made, "
                "or unset WARP_CACHE_PATH")
    return (f"Warp's kernel cache {checks.shown_path(cache)} cannot be made ({why}); set WARP_CACHE_PATH to a folder "
            "that is there or can be made")


def init_warp(device: str | None = None, log_level: int | None = None, echo: bool = True) -> list[str]:
    """Initialise Warp without its start-up lines; return the native notes it printed.

    ``log_level`` (default ``wp.LOG_WARNING``) is set on ``wp.config`` before ``wp.init()``.
    Native notes about a missing CUDA driver are held back when the run does not ask for a
    GPU (``device`` None or ``"cpu"``); every other note (and those, for ``device="cuda"`` or
    ``"cuda:N"``) is echoed to ``sys.stderr`` when ``echo`` is true. A Warp ``Device``
    (``model.device``) is taken as its name; another ``device``, a
    ``log_level`` that is no integer or an ``echo`` other than True or False is a ``ValueError``. Calling it again, or after Warp has
    started, only sets the log level and returns ``[]``.
    """
    import numbers  # noqa: PLC0415
    import re  # noqa: PLC0415

    import warp as wp  # noqa: PLC0415 (importing this module must not load Warp)

    from . import checks  # noqa: PLC0415

    # Checked before the log level is set: 'debug' met int()'s own error, 2.5 was taken as 2,
    # and a device name Warp has none of ('gpu') or a text echo ('no') passed without a word.
    if log_level is not None and (isinstance(log_level, bool) or not isinstance(log_level, numbers.Integral)):
        raise ValueError(f"log_level = {checks.shorten(log_level)!r} is not allowed: must be an integer, e.g. wp.LOG_WARNING "
                         f"({wp.LOG_WARNING}) or wp.LOG_DEBUG ({wp.LOG_DEBUG})")
    if isinstance(device, wp.Device):  # (model.device: refused, it read "device = 'cpu' is not allowed")
        device = str(device)
    if device is not None and not (isinstance(device, str) and re.fullmatch(r"cpu|cuda(:\d+)?", device)):
        raise ValueError(f"device = {checks.shorten(device)!r} is not allowed: must be None, 'cpu', 'cuda' or 'cuda:N'")
    checks.boolean("echo", echo)
    wp.config.log_level = wp.LOG_WARNING if log_level is None else int(log_level)
    from warp._src import context  # noqa: PLC0415

    if getattr(context, "runtime", None) is not None:
        return []
    configured = wp.config.kernel_cache_dir
    try:
        notes = _native_notes(wp.init)
    except OSError as e:
        refusal = _cache_refusal(e, wp.config.kernel_cache_dir, configured)
        # Warp set it to the folder it could not make: left so, it took it over a mended
        # WARP_CACHE_PATH, and init_warp() again in this process failed the same way.
        wp.config.kernel_cache_dir = configured
        if refusal is None:
            raise
        raise ValueError(refusal) from None
    wants_gpu = device is not None and str(device).startswith("cuda")
    if echo:
        for note in notes:
            if wants_gpu or "CUDA" not in note:
                print(note, file=sys.stderr)
    return notes


def cuda_absence() -> str:
    """Why the started Warp has no CUDA device, read from its runtime (the same words whenever
    Warp was started: its own note at the start is printed once a process, so a second command
    of one process named another reason)."""
    from warp._src import context  # noqa: PLC0415

    runtime = getattr(context, "runtime", None)
    if runtime is None or not getattr(runtime, "is_cuda_enabled", True):
        return "this Warp was built without CUDA"
    driver, least = getattr(runtime, "driver_version", None), getattr(runtime, "min_driver_version", None)
    if driver is None:
        return "it could not find or load the NVIDIA CUDA driver"
    if least is not None and driver < least:
        return f"the CUDA driver {driver[0]}.{driver[1]} is older than the {least[0]}.{least[1]} it needs"
    return "the CUDA driver reports no device"
