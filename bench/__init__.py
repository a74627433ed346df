"""Benchmarks (`make bench`): each bench_*.py prints its own table; none runs in the test suite."""
