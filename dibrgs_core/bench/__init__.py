"""Benchmark suites: runs (local or Ray) and their pages (CSV, curves, Markdown tables)."""
