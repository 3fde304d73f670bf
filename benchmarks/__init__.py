"""Benchmarks of td3-jax against its baselines (see docs/benchmarks.md)."""
