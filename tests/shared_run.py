"""One run of a long validation case per test session, shared by the xdist workers.

A module fixture runs once per worker: under ``-n 2 --dist worksteal`` a module's tests are
shared out between both workers, and a run that several of them read (a validation case of
10-40 s) then ran twice. ``shared_run`` leaves the first caller's result, pickled, in a
folder both workers see; a second caller waits on a lock for it instead of running it again.
"""

import pickle

try:
    import fcntl
except ImportError:  # no POSIX locks (Windows): each caller runs its own
    fcntl = None


def shared_run(root, key: str, fn):
    """``fn()``'s result, computed by the first caller with this ``key`` under ``root`` and
    read back by the others; a caller that comes while it is computed waits for it."""
    if fcntl is None:
        return fn()
    path = root / f"shared_run-{key}.pickle"
    with open(root / f"shared_run-{key}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            if path.is_file():
                return pickle.loads(path.read_bytes())
            result = fn()
            path.write_bytes(pickle.dumps(result))
            return result
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
