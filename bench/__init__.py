"""Benchmarks (run as scripts, ``python bench/<name>.py``, or as ``dejaview bench <name>``)."""
