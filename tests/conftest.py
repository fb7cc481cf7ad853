"""Test configuration: one Warp kernel cache for every test process, quiet output."""

import os
import pathlib

# Must be set before warp is imported anywhere: every test run and every subprocess
# (CLI tests) then load kernels compiled once instead of compiling them again.
os.environ.setdefault("WARP_CACHE_PATH", str(pathlib.Path(__file__).resolve().parent.parent / ".warp_cache"))

import warp as wp  # noqa: E402

wp.config.log_level = wp.LOG_WARNING
wp.init()

# Under CI=true the property tests draw the same examples every run (a failure there is
# reproducible from the log); locally they explore new ones and keep failures in the database.
from hypothesis import settings  # noqa: E402

settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI", "").lower() == "true":
    settings.load_profile("ci")
