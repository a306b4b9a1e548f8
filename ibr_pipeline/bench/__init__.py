"""Benchmarks and reports across stages (issue #10)."""
