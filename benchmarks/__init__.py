"""Benchmarks: each writes JSON under benchmarks/results/; report.py turns them into BENCHMARKS.md."""
