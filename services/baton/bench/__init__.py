"""Benchmarks that reproduce the paper's Section 5.4: timeline, worst case, micro."""
