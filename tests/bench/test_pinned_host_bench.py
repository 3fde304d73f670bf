"""benchmarks.pinned_host on a CPU: its loop computes what it says, and a measurement frees
what it allocates and reports every time."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from benchmarks import pinned_host


@pytest.mark.parametrize("callback", [False, True])
def test_the_loop_is_iterations_of_half_tanh_of_the_square(callback):
    x = np.array([[0.3, -0.2], [0.1, 0.4]], np.float32)
    expected = x
    for _ in range(3):
        expected = np.tanh(expected @ expected) * 0.5
    got = pinned_host.loop(3, callback)(jnp.asarray(x))
    np.testing.assert_allclose(np.asarray(got), expected, rtol=1e-6)


def test_an_allocation_holds_the_sizes_at_once_and_frees_them(monkeypatch):
    placed = []
    real_put = jax.device_put

    def put(value, sharding):
        placed.append((value.nbytes, sharding.memory_kind))
        return real_put(value, sharding)

    monkeypatch.setattr(pinned_host.jax, "device_put", put)
    seconds = pinned_host.allocate_and_free([4000, 800], jax.devices()[0])
    assert seconds >= 0
    assert placed == [(4000, "pinned_host"), (800, "pinned_host")]


def test_a_measurement_reports_the_loop_alone_and_beside_each_allocation():
    out = pinned_host.measure([4000], matrix=4, iterations=2, callback=False)
    assert out["gb"] == pytest.approx(4e-6)
    for key in ("loop_alone_s", "loop_beside_first_s", "first_allocation_s",
                "loop_alone_again_s", "loop_beside_second_s", "second_allocation_s"):
        assert out[key] >= 0
