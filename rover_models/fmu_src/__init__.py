"""Sources of the test/example rover FMUs and their builders (see build_fmus.py)."""
