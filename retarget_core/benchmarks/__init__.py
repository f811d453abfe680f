"""Benchmarks behind ``handretarget bench``: they measure and return figures; the CLI prints."""
