"""Reproducible measurements that print ratios against a baseline measured in the same run.

`python -m benchmarks` runs every `benchmarks/bench_*.py` module's `main()` in turn (`make bench`);
`python -m benchmarks planner` runs only the modules whose name contains "planner".
"""
