"""Benchmarks of warp_esph (run as modules: ``python -m benchmarks.step``)."""
