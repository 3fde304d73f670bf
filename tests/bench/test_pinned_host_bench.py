"""benchmarks.pinned_host on a CPU: its loop computes what it says with its trip count an
argument, an allocation holds its buffers at once and frees them, and a measurement reports
every time (and the allocating thread's error)."""

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
    f = pinned_host.loop(callback)
    np.testing.assert_allclose(np.asarray(f(jnp.asarray(x), jnp.int32(3))), expected, rtol=1e-6)
    compiled = f.lower(jnp.asarray(x), jnp.int32(3)).compile().as_text()
    assert "known_trip_count" not in compiled  # (so the host reads the condition)


def test_an_allocation_holds_the_sizes_at_once_then_frees_them(monkeypatch):
    events = []
    real_put = jax.device_put

    def put(value, sharding):
        events.append(("put", value.nbytes, sharding.memory_kind))
        placed = real_put(value, sharding)
        real_delete = placed.delete
        monkeypatch.setattr(placed, "delete", lambda: (events.append(("delete",)),
                                                        real_delete()))  # fmt: skip
        return placed

    monkeypatch.setattr(pinned_host.jax, "device_put", put)
    seconds = pinned_host.allocate_and_free([4000, 800], jax.devices()[0])
    assert seconds >= 0
    assert events == [("put", 4000, "pinned_host"), ("put", 800, "pinned_host"),
                      ("delete",), ("delete",)]  # fmt: skip


def test_a_measurement_reports_the_loop_alone_and_beside_each_allocation():
    out = pinned_host.measure([4000], matrix=4, iterations=2, callback=False)
    assert out["gb"] == pytest.approx(4e-6)
    for which in ("first", "second"):
        assert 0 <= out[f"{which}_call_began_s"] <= out[f"{which}_call_returned_s"]
        assert out[f"{which}_call_returned_s"] <= out[f"{which}_loop_s"]
        assert out[f"{which}_allocation_s"] >= 0
    assert out["loop_alone_s"] >= 0 and out["loop_alone_again_s"] >= 0


def test_an_error_of_the_allocating_thread_is_raised():
    def fails() -> float:
        raise MemoryError("no pinned memory")

    with pytest.raises(MemoryError, match="no pinned memory"):
        pinned_host.timed_beside(lambda: jnp.ones(2), fails)
