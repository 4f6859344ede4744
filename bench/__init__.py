"""Benchmarks: each prints its figures beside the target they answer to (never asserted in tests)."""
