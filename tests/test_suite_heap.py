"""The suite's frozen heap (tests/conftest.py): what importing Warp and the package left is in
the permanent generation, so Python's automatic full collections skip it; a test of a peak
gets the heap thawed, as in a user's process."""

import gc

import warp as wp

import warp_esph as we


def _collected(obj):
    # gc.get_objects lists the collected generations only, not the permanent one.
    return any(o is obj for o in gc.get_objects())


def test_what_the_imports_left_is_frozen_and_what_a_test_makes_is_not():
    assert gc.get_freeze_count() > 10_000, gc.get_freeze_count()
    assert not _collected(vars(wp)) and not _collected(vars(we))
    made = {"cycle": None}
    made["cycle"] = made
    assert _collected(made)


def test_a_test_of_a_peak_runs_on_a_thawed_heap(thawed_heap):
    assert gc.get_freeze_count() == 0
    assert _collected(vars(wp)) and _collected(vars(we))
