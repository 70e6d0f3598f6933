"""Benchmarks of the hds trainer: `python -m bench.run [section ...]` (see bench/run.py).

Each section measures and reports; nothing here asserts a timing. Results are merged by section
into bench/results.json (re-running one section replaces only its entry) and rendered into
bench/RESULTS.md.
"""
