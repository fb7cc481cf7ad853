"""A pytest plugin that logs when each test ran and on which xdist worker, with the worker's
CPU time for it: the measurement behind docs/performance.md, "The test suite" (where the wall
time of the README's command goes, and whether a worker waits at the end for a long test the
other started late). Not loaded by the suite; run as

    WORKER_LOG=$(mktemp -d) python -m pytest -n 2 --dist worksteal -p worker_log

(with ``tests`` on ``PYTHONPATH``), then ``python tests/worker_log.py $WORKER_LOG``. Each worker
writes ``<worker>.jsonl``: a first line with the time its session started (before collection),
then one line a test (its id, start and end by the wall clock, the CPU seconds of the worker's
process: a subprocess's do not count)."""

import collections
import glob
import json
import os
import sys
import time

import pytest

_out = None


def _write(record):
    global _out
    if _out is None:
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        _out = open(os.path.join(os.environ.get("WORKER_LOG", "."), f"{worker}.jsonl"), "a")
    _out.write(json.dumps(record) + "\n")
    _out.flush()


def pytest_sessionstart(session):
    _write({"session_start": time.time()})


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    t0, cpu0 = time.time(), time.process_time()
    yield
    _write({"test": item.nodeid, "start": t0, "end": time.time(), "cpu": time.process_time() - cpu0})


def summary(folder, top=20):
    """Per worker: when its first test started and its last ended (seconds from the earliest
    session start: the first is the collection's cost, the difference of the last the tail),
    its tests' wall and CPU seconds; then the ``top`` tests and test functions by CPU."""
    tests, starts = [], []
    for path in sorted(glob.glob(os.path.join(folder, "*.jsonl"))):
        worker = os.path.basename(path)[:-len(".jsonl")]
        for line in open(path):
            r = json.loads(line)
            if "session_start" in r:
                starts.append(r["session_start"])
            else:
                tests.append({**r, "worker": worker})
    t0 = min(starts)
    lines = []
    for worker in sorted({r["worker"] for r in tests}):
        rs = [r for r in tests if r["worker"] == worker]
        lines.append(f"{worker}: {len(rs)} tests, first at {min(r['start'] for r in rs) - t0:.1f} s, last ended at "
                     f"{max(r['end'] for r in rs) - t0:.1f} s, {sum(r['end'] - r['start'] for r in rs):.1f} s in tests, "
                     f"{sum(r['cpu'] for r in rs):.1f} s of CPU")
    by_function = collections.defaultdict(lambda: [0, 0.0])
    for r in tests:
        f = by_function[r["test"].split("[")[0]]
        f[0] += 1
        f[1] += r["cpu"]
    lines.append("longest by CPU (s of CPU, s of wall, worker, started at):")
    for r in sorted(tests, key=lambda r: -r["cpu"])[:top]:
        lines.append(f"  {r['cpu']:6.1f} {r['end'] - r['start']:6.1f} {r['worker']} {r['start'] - t0:7.1f} {r['test']}")
    lines.append("test functions by CPU (s, tests):")
    for name, (n, cpu) in sorted(by_function.items(), key=lambda kv: -kv[1][1])[:top]:
        lines.append(f"  {cpu:6.1f} x{n} {name}")
    return "\n".join(lines)


if __name__ == "__main__":
    print(summary(sys.argv[1]))
