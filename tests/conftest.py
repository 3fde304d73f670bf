"""Shared pytest configuration for the td3_jax test suite."""

from __future__ import annotations

import os
import tempfile

# XLA's CPU backend spends most of a small program's compile time in LLVM's optimisation
# passes, and the tests' programs are small and run briefly: compiled unoptimised, the fast set
# takes about half the CPU time. Set before JAX starts its backend; child processes inherit it
# (those given an XLA_FLAGS of their own compile optimised, as the CLI does). Run the suite with
# XLA_FLAGS=--xla_backend_optimization_level=3 to test optimised code.
_OPT_LEVEL = "--xla_backend_optimization_level"
if _OPT_LEVEL not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {_OPT_LEVEL}=0".strip()

import jax  # noqa: E402
import pytest  # noqa: E402
from hypothesis import HealthCheck, settings  # noqa: E402

from td3_jax.common.runtime import CACHE_MAX_BYTES  # noqa: E402

# The CLI's default --compile-cache is ~/.cache/td3-jax/jax (with its traced programs): tests
# that leave it at its default write into a home of their own, not the user's cache. Under
# pytest-xdist (`-n 2`) the workers share the home their controller made, so a program one
# worker compiled is a cache hit in the other (JAX's cache writes are file-locked, whole files).
_TESTS_HOME = "TD3_JAX_TESTS_HOME"
if not (os.environ.get("PYTEST_XDIST_WORKER") and os.environ.get(_TESTS_HOME)):
    os.environ[_TESTS_HOME] = tempfile.mkdtemp(prefix="td3-jax-tests-home-")
os.environ["HOME"] = os.environ[_TESTS_HOME]

# Everything in the library is float32 / int32; keep the tests on the same footing.
jax.config.update("jax_enable_x64", False)

# Compiling dominates on a CPU, and many tests build the same small programs. JAX's persistent
# compilation cache, in the CLI's default place under this test run's fresh home, compiles each
# distinct program once per test run (in this process and in the CLI processes that tests
# start without a --compile-cache of their own); a hit is the executable XLA compiled, so no
# result changes. It starts empty in every test run, so nothing carries over between runs.
# Tests about the cache itself give their runs a --compile-cache of their own.
jax.config.update("jax_compilation_cache_dir", os.path.expanduser("~/.cache/td3-jax/jax"))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
# With a size cap (the CLI's own), JAX reads and writes the cache under a file lock: xdist's
# workers share it, and one never reads an entry the other is half-way through writing.
jax.config.update("jax_compilation_cache_max_size", CACHE_MAX_BYTES)

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
HEAVY = ("slow", "robots", "mjx", "processes", "subprocess", "runs")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Marks ``heavy`` every test that carries one of the ``HEAVY`` markers."""
    for item in items:
        if any(item.get_closest_marker(name) for name in HEAVY):
            item.add_marker(pytest.mark.heavy)
