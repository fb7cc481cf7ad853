"""The suite's shared runs (tests/shared_run.py): a long validation case that several tests
read runs once per session, not once per xdist worker."""

import fcntl
import threading

import pytest

from shared_run import shared_run


def test_a_second_caller_reads_the_first_callers_run(tmp_path):
    calls = []

    def run():
        calls.append(1)
        return {"ratio": 1.07, "history": [0.5, 0.25]}

    first = shared_run(tmp_path, "case", run)
    second = shared_run(tmp_path, "case", run)
    assert calls == [1] and second == first == {"ratio": 1.07, "history": [0.5, 0.25]}
    assert shared_run(tmp_path, "other case", run) == first and calls == [1, 1]  # a key of its own runs


def test_the_run_holds_its_lock_while_it_computes_so_a_second_caller_waits_for_it(tmp_path):
    """The two workers ask at once: while the first computes, the key's lock is taken (a
    second caller blocks on it; probed without blocking here, so the test cannot hang), and
    once it is done the second reads its result instead of running its own."""
    started, go, probe = threading.Event(), threading.Event(), {}

    def slow():
        started.set()
        assert go.wait(30.0)
        return 1.0

    first = threading.Thread(target=lambda: probe.setdefault("first", shared_run(tmp_path, "case", slow)))
    first.start()
    try:
        assert started.wait(30.0)
        with open(tmp_path / "shared_run-case.lock", "w") as lock, pytest.raises(BlockingIOError):
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    finally:
        go.set()
        first.join(30.0)
    assert probe == {"first": 1.0}
    assert shared_run(tmp_path, "case", lambda: 2.0) == 1.0


def test_a_pickle_cut_short_by_a_killed_worker_is_run_again_not_read(tmp_path):
    """A worker killed (or out of disk) while it wrote the result leaves a partial pickle; the
    other worker, or the one xdist starts in its place, must run the case again, not fail every
    test of the fixture on an unreadable file."""
    import pickle

    whole = pickle.dumps({"ratio": 1.07, "history": list(range(100))})
    (tmp_path / "shared_run-case.pickle").write_bytes(whole[: len(whole) // 2])
    assert shared_run(tmp_path, "case", lambda: {"ratio": 1.5}) == {"ratio": 1.5}
    assert shared_run(tmp_path, "case", lambda: 2.0) == {"ratio": 1.5}  # its run replaced the partial one


def test_the_result_is_written_whole_or_not_at_all(tmp_path, monkeypatch):
    """The pickle appears under its name only once written in full: a write cut off (here: the
    disk full after half of it) leaves nothing a later caller would take for the result."""
    import pathlib

    real = pathlib.Path.write_bytes

    def half_then_full(self, data):
        real(self, data[: len(data) // 2])
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(pathlib.Path, "write_bytes", half_then_full)
    with pytest.raises(OSError, match="No space"):
        shared_run(tmp_path, "case", lambda: {"ratio": 1.07, "history": list(range(100))})
    monkeypatch.undo()
    assert not (tmp_path / "shared_run-case.pickle").exists()
    assert shared_run(tmp_path, "case", lambda: 2.0) == 2.0


def test_the_shared_folder_is_the_sessions_own_or_none(tmp_path):
    """A local worker's basetemp is ``<session>/popen-<id>``: the session's folder is shared.
    Any other (a remote gateway's worker, which makes its own numbered folder under the
    user's pytest folder) has no such parent of its own: sharing its parent would read a
    pickle an earlier session left there."""
    from shared_run import session_root

    session = tmp_path / "pytest-7"
    assert session_root(session / "popen-gw1", "gw1") == session
    assert session_root(session, "gw1") is None
    assert session_root(session / "popen-gw0", "gw1") is None
