"""The ``parallel_map`` items of the sweep tests that kill or exit their worker: plain Python,
in a module of their own because each spawned worker imports the module of the function it
runs, and this one (unlike test_sweep.py, which brings USD, pytest and Warp) costs it
nothing to import."""

import os
import sys


def _dies_first(i, notes):
    """A parallel_map item: item 0 kills its worker once item 3 has started beside it; item 3
    waits for item 0's note that it dies, then 1 s more, so that it is in flight when the
    pool breaks (a sleep of 3 s had made that likely, and cost 3 s again in its run alone).
    Run again, each finds its notes: item 0 dies, item 3 returns, at once."""
    import time

    started, died = os.path.join(notes, "3 started"), os.path.join(notes, "0 died")
    if i == 0:
        for _ in range(6000):  # at most 60 s: then it dies anyway, with the same rows
            if os.path.exists(started):
                break
            time.sleep(0.01)
        open(died, "w").close()
        os._exit(7)
    if i == 3 and not os.path.exists(started):
        open(started, "w").close()
        while not os.path.exists(died):
            time.sleep(0.01)
        time.sleep(1.0)
    return i


def _dies_second(i, marker):
    """A parallel_map item: item 1 kills its worker; item 0 is still running then (it waits
    for item 1's note, then 1 s more), and returns 0 whenever it runs once item 1 has died."""
    import time

    if i == 1:
        open(marker, "w").close()
        os._exit(7)
    while not os.path.exists(marker):
        time.sleep(0.01)
    time.sleep(1.0)
    return i


def _exits_at(i):
    """A parallel_map item: item 1 calls sys.exit(5)."""
    if i == 1:
        sys.exit(5)
    return i


def _waits_in(i, notes):
    """A parallel_map item: notes its worker's pid in ``notes/<i>.pid``, then waits for the
    file ``notes/release`` (at most 120 s), so that it is in flight when the test kills the
    process that runs the pool."""
    import time

    with open(os.path.join(notes, f"{i}.pid.part"), "w") as f:
        f.write(str(os.getpid()))
    os.replace(os.path.join(notes, f"{i}.pid.part"), os.path.join(notes, f"{i}.pid"))
    for _ in range(2400):
        if os.path.exists(os.path.join(notes, "release")):
            break
        time.sleep(0.05)
    return i
