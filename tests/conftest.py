"""Shared pytest configuration for the td3_jax test suite."""

from __future__ import annotations

import os
import tempfile

import jax
from hypothesis import HealthCheck, settings

# The CLI's default --compile-cache is ~/.cache/td3-jax/jax (with its traced programs): tests
# that leave it at its default write into a home of their own, not the user's cache.
os.environ["HOME"] = tempfile.mkdtemp(prefix="td3-jax-tests-home-")

# Everything in the library is float32 / int32; keep the tests on the same footing.
jax.config.update("jax_enable_x64", False)

# jit compilation makes the first example of a property test slow: no per-example deadline.
settings.register_profile(
    "td3_jax",
    deadline=None,
    max_examples=40,
    suppress_health_check=[HealthCheck.too_slow],
    derandomize=False,
)
settings.load_profile("td3_jax")
