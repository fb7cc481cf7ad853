"""A pytest plugin that logs, for each test, the Warp modules it loads and those it compiles,
with the compile's CPU time: the measurement behind docs/performance.md, "Where a cold run's
compiling goes" and "Modules only a test compiles". Not loaded by the suite; run as

    COMPILE_AUDIT=compile.jsonl WARP_CACHE_PATH=$(mktemp -d) python -m pytest -p compile_audit tests/test_fit.py

(with ``tests`` on ``PYTHONPATH``; an empty cache, else nothing compiles). Each line of
``compile.jsonl`` is one test: its id, the modules it loaded (``name:hash``) and, for those it
compiled, the CPU seconds of each compile (Warp compiles a CPU module in-process, so the
process's CPU time is the compiler's). A module one test alone loads is compile time spent
for that test only."""

import json
import os
import time

import pytest

_current = {"loaded": set(), "compiled": {}}


def _install():
    from warp._src import context

    module_cls = context.Module
    if getattr(module_cls, "_compile_audit", False):
        return
    load, compile_ = module_cls.load, module_cls._compile

    def logged_load(self, device, *args, **kwargs):
        _current["build"] = None
        exec_ = load(self, device, *args, **kwargs)
        if exec_ is not None and exec_.module_hash is not None:
            # (The hash a load reports, the one its block_dim resolves to.)
            key = f"{self.name}:{exec_.module_hash.hex()[:8]}"
            _current["loaded"].add(key)
            if _current["build"] is not None:
                _current["compiled"][key] = _current["compiled"].get(key, 0.0) + _current["build"]
        return exec_

    def logged_compile(self, *args, **kwargs):
        t0 = time.process_time()
        compiled = compile_(self, *args, **kwargs)
        if compiled:
            _current["build"] = time.process_time() - t0
        return compiled

    module_cls.load, module_cls._compile = logged_load, logged_compile
    module_cls._compile_audit = True


def pytest_configure(config):
    _install()


def _flush(nodeid):
    out = os.environ.get("COMPILE_AUDIT", "compile_audit.jsonl")
    with open(out, "a") as f:
        f.write(json.dumps({"test": nodeid, "loaded": sorted(_current["loaded"]),
                            "compiled": {k: round(v, 3) for k, v in sorted(_current["compiled"].items())}}) + "\n")
    _current["loaded"], _current["compiled"] = set(), {}


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    # Fixtures' compiles (set-up and tear-down) count for the test that first needs them.
    _current["loaded"], _current["compiled"] = set(), {}
    yield
    _flush(item.nodeid)
