"""Shared pytest configuration for the td3_jax test suite."""

from __future__ import annotations

import os
import tempfile

import jax
import pytest
from hypothesis import HealthCheck, settings

# The CLI's default --compile-cache is ~/.cache/td3-jax/jax (with its traced programs): tests
# that leave it at its default write into a home of their own, not the user's cache.
os.environ["HOME"] = tempfile.mkdtemp(prefix="td3-jax-tests-home-")

# Everything in the library is float32 / int32; keep the tests on the same footing.
jax.config.update("jax_enable_x64", False)

# Compiling dominates on a CPU, and many tests build the same small programs. JAX's persistent
# compilation cache, in the CLI's default place under this session's fresh home, compiles each
# distinct program once per test session (in this process and in the CLI processes that tests
# start without a --compile-cache of their own); a hit is the executable XLA compiled, so no
# result changes. It starts empty in every session, so nothing carries over between runs.
# Tests about the cache itself give their runs a --compile-cache of their own.
jax.config.update("jax_compilation_cache_dir", os.path.expanduser("~/.cache/td3-jax/jax"))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)

# jit compilation makes the first example of a property test slow: no per-example deadline.
settings.register_profile(
    "td3_jax",
    deadline=None,
    max_examples=40,
    suppress_health_check=[HealthCheck.too_slow],
    derandomize=False,
)
settings.load_profile("td3_jax")


#: The markers of the tests left out of the fast command (``-m "not heavy"``); pyproject.toml
#: says what each one selects.
HEAVY = ("slow", "robots", "mjx", "processes", "subprocess")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Marks ``heavy`` every test that carries one of the ``HEAVY`` markers."""
    for item in items:
        if any(item.get_closest_marker(name) for name in HEAVY):
            item.add_marker(pytest.mark.heavy)
