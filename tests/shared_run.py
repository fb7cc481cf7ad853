"""One run of a long validation case per test session, shared by the xdist workers.

A module fixture runs once per worker: under ``-n 2 --dist worksteal`` a module's tests are
shared out between both workers, and a run that several of them read (a validation case of
10-40 s) then ran twice. ``shared_run`` leaves the first caller's result, pickled, in a
folder both workers see; a second caller waits on a lock for it instead of running it again.
"""

import os
import pickle

try:
    import fcntl
except ImportError:  # no POSIX locks (Windows): each caller runs its own
    fcntl = None


def session_root(basetemp, worker_id: str):
    """The folder of this test session that every xdist worker sees, from a worker's own
    ``basetemp``: xdist gives a local (popen) worker ``<the session's basetemp>/popen-<id>``.
    None where the basetemp is not of that form (a remote gateway's worker makes its own
    numbered folder, whose parent holds every session's and would hand a result of an earlier
    session to this one): there each worker runs its own."""
    if basetemp.name != f"popen-{worker_id}":
        return None
    return basetemp.parent


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
                try:
                    return pickle.loads(path.read_bytes())
                except (EOFError, pickle.UnpicklingError, ValueError, IndexError):
                    pass  # a partial file is no result (the write below renames only whole ones in): run it again
            result = fn()
            # Written aside and renamed: a worker killed (or a disk filled) mid-write leaves no
            # partial pickle under the name the others read.
            part = path.with_name(f"{path.name}.{os.getpid()}.part")
            try:
                part.write_bytes(pickle.dumps(result))
                os.replace(part, path)
            finally:
                part.unlink(missing_ok=True)
            return result
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
