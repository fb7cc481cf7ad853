"""Sweeps and ``parallel_map`` on Ray: the same rows as in this process or a process pool.

One local Ray instance serves every test here: starting one took 5-7 s of a test's 6-11 s on
a 2-core machine, and its workers, once started, import warp_esph for the next test too.
These tests live apart from ``test_sweep.py`` so that the instance is never running while a
test there expects no Ray session in this process (``sweep`` uses a running one as it is)."""

import os

import pytest

from sweep_cases import FRAMES, YIELD, _box, _extra_raising_what_pickle_cannot_rebuild, _extra_that_exits, _rows
from warp_esph.sweep import sweep


@pytest.fixture(scope="module")
def cluster():
    """A local instance of 2 CPUs and no GPU (declared: the machine's own may have one), its
    workers able to import ``sweep_cases`` for the ``extra`` functions samples are sent with."""
    ray = pytest.importorskip("ray")
    here = os.path.dirname(__file__)
    with pytest.MonkeyPatch.context() as mp:
        # Ray's workers inherit the environment the instance starts in.
        mp.setenv("PYTHONPATH", os.pathsep.join(p for p in (here, os.environ.get("PYTHONPATH")) if p))
        ray.init(num_cpus=2, num_gpus=0, include_dashboard=False, log_to_driver=False)
    try:
        yield ray
    finally:
        ray.shutdown()


def test_ray_gives_the_same_table(cluster):
    serial = sweep(_box(), [YIELD], frames=FRAMES, workers=1)
    remote = sweep(_box(), [YIELD], frames=FRAMES, ray="auto")
    assert remote.columns == serial.columns
    assert _rows(remote) == _rows(serial)


def test_ray_a_sample_that_crashes_its_worker_is_a_failed_row_at_once(cluster, tmp_path):
    """Ray retried a task whose worker died (3 more times by default): a sample that crashes
    its worker every time (a fault in native code, out of memory) ran four times, each dying
    the same way, before its row said it failed. It now runs once, and its row says what a
    process pool's says of an item that kills its worker alone: it was Ray's words ('Ray:
    WorkerCrashedError: ...', the worker's pid, colour codes), another reason on every run."""
    from warp_esph.sweep import parallel_map

    # os.system's shell notes the attempt, then kills its parent: the worker. Two items, so
    # that the pool has two worker processes (one item runs in this one); the one beside the
    # crash, if in flight, runs again alone, and the crash dies alone: the rows do not depend
    # on which was in flight.
    pool = parallel_map(os.system, [(f"echo x >> {tmp_path / 'pool'}; kill -9 $PPID",), ("true",)], workers=2,
                        on_error=lambda i, why: why)
    assert pool[1] == 0 and "worker process died running this item alone" in pool[0], pool
    note = tmp_path / "attempts"
    rows = parallel_map(os.system, [(f"echo x >> {note}; kill -9 $PPID",), ("true",)], ray="auto",
                        on_error=lambda i, why: why)
    assert note.read_text() == "x\n"
    assert rows == pool


def test_a_sample_s_error_is_the_same_reason_on_ray_as_here(cluster):
    """A sample whose ``extra`` raised was a row whose reason was Ray's text on Ray (colour
    codes, the worker's pid and ip, a traceback: 'Ray: RayTaskError(TypeError): ...'), and
    ``TypeError: ...`` in this process or a worker process: the same sweep, another table on
    every run. ``int`` is an ``extra`` every Ray worker can import, and it raises a TypeError."""
    here = sweep(_box(), ["yield_stress=10,100"], frames=1, workers=1, extra=int)
    assert [r["status"] for r in here.rows] == ["failed", "failed"]
    assert here.rows[0]["reason"].startswith("TypeError: int() takes"), here.rows[0]["reason"]
    remote = sweep(_box(), ["yield_stress=10,100"], frames=1, ray="auto", extra=int)
    assert _rows(remote) == _rows(here)


def test_a_cuda_sweep_on_a_ray_cluster_without_a_gpu_is_refused_before_any_sample(cluster):
    """Ray holds a task that asks for a GPU where the cluster has none, without an end."""
    with pytest.raises(ValueError, match=r"^device = 'cuda' is not allowed with ray = 'auto': the Ray cluster has no "
                                         r"GPU \(0\), and each CUDA sample asks it for one"):
        sweep(_box(), ["mu=1e4"], frames=1, device="cuda", ray="auto")


def test_a_sample_s_exception_the_driver_cannot_rebuild_is_its_reason_on_ray_too(cluster):
    """On Ray the same exception was a row of Ray's words ('Ray: UnserializableException: ...',
    the worker's pid and ip, colour codes): another reason on every run. It says the exception."""
    here = sweep(_box(), ["yield_stress=10,100"], frames=1, workers=1, extra=_extra_raising_what_pickle_cannot_rebuild)
    exits = sweep(_box(), ["yield_stress=10,100"], frames=1, workers=1, extra=_extra_that_exits)
    remote = sweep(_box(), ["yield_stress=10,100"], frames=1, ray="auto", extra=_extra_raising_what_pickle_cannot_rebuild)
    # A sample that calls sys.exit was a row of Ray's 'WorkerCrashedError: The worker died unexpectedly'.
    remote_exits = sweep(_box(), ["yield_stress=10,100"], frames=1, ray="auto", extra=_extra_that_exits)
    assert _rows(remote) == _rows(here)
    assert _rows(remote_exits) == _rows(exits)
