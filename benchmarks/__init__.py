"""Micro-benchmarks and per-method timing scripts that need the whole stack (top layer, beside
``run_bench.py``): ``python -m benchmarks.<name> --help``."""
