"""Test configuration: one Warp kernel cache for every test process, quiet output."""

import os
import pathlib

# Must be set before warp is imported anywhere: every test run and every subprocess
# (CLI tests) then load kernels compiled once instead of compiling them again.
os.environ.setdefault("WARP_CACHE_PATH", str(pathlib.Path(__file__).resolve().parent.parent / ".warp_cache"))

import warp as wp  # noqa: E402

wp.config.log_level = wp.LOG_WARNING
wp.init()
