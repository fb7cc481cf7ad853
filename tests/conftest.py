"""Test configuration: one Warp kernel cache for every test process, quiet output."""

import os
import pathlib

# Must be set before warp is imported anywhere: every test run and every subprocess
# (CLI tests) then load kernels compiled once instead of compiling them again.
os.environ.setdefault("WARP_CACHE_PATH", str(pathlib.Path(__file__).resolve().parent.parent / ".warp_cache"))

from warp_esph.startup import init_warp  # noqa: E402

init_warp()  # wp.config.log_level = WARNING, and no native CUDA-driver note on a CPU machine

# Under CI=true the property tests draw the same examples every run (a failure there is
# reproducible from the log); locally they explore new ones and keep failures in the database.
from hypothesis import settings  # noqa: E402

settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI", "").lower() == "true":
    settings.load_profile("ci")
