"""benchmarks.compile_options: its variants as written on the command line, and each timed
compile a compile from nothing of the same program."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from benchmarks.compile_options import option_value, parse_variant, timed_compile

BACKEND_COMPILE = "/jax/core/compile/backend_compile_duration"


@pytest.mark.parametrize(("text", "value"), [
    ("true", True), ("False", False), (" TRUE ", True), ("0", 0), ("4", 4), (" 4", 4),
    ("0.5", 0.5),
    ("xla_gpu_enable_triton_gemm", "xla_gpu_enable_triton_gemm"), ("a,b", "a,b"),
])  # fmt: skip
def test_option_values_are_booleans_numbers_or_the_text(text, value):
    assert option_value(text) == value
    assert type(option_value(text)) is type(value)


def test_a_variant_is_its_name_and_its_options():
    assert parse_variant("default") == ("default", {})
    assert parse_variant("off:xla_gpu_autotune_level=0,xla_x=true") == (
        "off",
        {"xla_gpu_autotune_level": 0, "xla_x": True},
    )


@pytest.mark.parametrize("text", [":a=1", "x:a", "x:=1", "x:a=1,b"])
def test_a_malformed_variant_is_refused_by_name(text):
    with pytest.raises(SystemExit, match="is not NAME"):
        parse_variant(text)


def test_each_timed_compile_compiles_anew_and_gives_the_same_program():
    x = jnp.linspace(-1.0, 1.0, 5)
    lowered = jax.jit(lambda v: jnp.sin(v) * 2.0).lower(x)
    compiles = []
    listener = lambda name, *_, **__: compiles.append(name) if name == BACKEND_COMPILE else None
    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        first, first_s = timed_compile(lowered, {})
        again, again_s = timed_compile(lowered, {})
        other, _ = timed_compile(lowered, {"xla_cpu_enable_fast_math": False})
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
    assert compiles.count(BACKEND_COMPILE) == 3  # none of them read back from a cache
    assert first_s > 0 and again_s > 0
    for executable in (first, again, other):
        np.testing.assert_allclose(executable(x), np.sin(np.asarray(x)) * 2.0, rtol=1e-6)
