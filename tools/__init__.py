"""Benchmarks and soak tools (run as scripts: ``python tools/bench_x.py``).

A package too, so that tests import them by name (``from tools import bench_lifelong``) rather
than loading files by path.
"""
