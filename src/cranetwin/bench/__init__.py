"""Benchmarks. Each module registers one ``cranetwin bench NAME`` command that prints measured
figures, and ratios against a baseline measured in the same run, as JSON with ``--json``."""
