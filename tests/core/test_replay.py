"""Property tests of the replay ring buffer (``td3_jax.core.replay``).

Every added row carries a unique integer id and every other leaf is a function of that id, so
the buffer's contents and samples can be checked exactly (which rows, and rows kept whole).
Capacities come from a small fixed set so that the jitted functions compile only a few times.
"""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import td3_jax as tj
from td3_jax.core import replay

CAPACITIES = (1, 5, 8)
SAMPLE_SIZE = 32

# Module-level jitted functions: one compilation per input shape, shared by all examples.
ADD = jax.jit(replay.add, donate_argnums=0)
SAMPLE = jax.jit(replay.sample, static_argnums=2)


def example():
    """One transition: int id, Transition of floats of several shapes, a uint8 image."""
    return {
        "id": jnp.zeros((), jnp.int32),
        "tr": tj.Transition(
            obs=jnp.zeros((3,), jnp.float32),
            action=jnp.zeros((2,), jnp.float32),
            reward=jnp.zeros((), jnp.float32),
            next_obs=jnp.zeros((3,), jnp.float32),
            done=jnp.zeros((), jnp.float32),
        ),
        "pix": jnp.zeros((2, 2), jnp.uint8),
    }


def rows(ids):
    """The rows for ``ids`` (``[n]`` ints > 0): every leaf a different function of the id."""
    ids = np.asarray(ids, np.int32)
    f = ids.astype(np.float32)
    return {
        "id": ids,
        "tr": tj.Transition(
            obs=f[:, None] + np.array([0.0, 0.25, 0.5], np.float32),
            action=-f[:, None] * np.array([1.0, 2.0], np.float32),
            reward=0.5 * f,
            next_obs=f[:, None] + np.array([1.0, 1.25, 1.5], np.float32),
            done=(ids % 2).astype(np.float32),
        ),
        "pix": np.broadcast_to((ids % 251).astype(np.uint8)[:, None, None], (len(ids), 2, 2)),
    }


def assert_rows_consistent(data, mask=None):
    """Each row of ``data`` (a pytree like ``rows``) is exactly ``rows(its id)``."""
    ids = np.asarray(data["id"])
    if mask is not None:
        ids = ids[mask]
    expected = rows(ids)
    for got, want in zip(jax.tree.leaves(data), jax.tree.leaves(expected), strict=True):
        got = np.asarray(got)
        got = got[mask] if mask is not None else got
        assert got.dtype == want.dtype
        np.testing.assert_array_equal(got, want)


def fill(capacity, sizes, start_id=1):
    """A buffer after adding batches of ``sizes`` rows with consecutive ids; and the ids."""
    buf = replay.init(capacity, example())
    all_ids = []
    next_id = start_id
    for n in sizes:
        ids = list(range(next_id, next_id + n))
        next_id += n
        buf = ADD(buf, rows(ids))
        all_ids += ids
    return buf, all_ids


@st.composite
def add_sequences(draw):
    capacity = draw(st.sampled_from(CAPACITIES))
    sizes = draw(st.lists(st.integers(1, capacity), max_size=8))
    return capacity, sizes


@settings(max_examples=50)
@given(add_sequences(), st.integers(0, 2**31 - 1))
def test_contents_are_last_capacity_transitions(case, seed):
    capacity, sizes = case
    buf, all_ids = fill(capacity, sizes)
    total = len(all_ids)
    assert buf.capacity == capacity
    assert int(buf.size) == min(total, capacity)
    assert int(buf.position) == total % capacity
    assert buf.size.dtype == jnp.int32 and buf.position.dtype == jnp.int32

    stored = np.asarray(buf.data["id"])
    if total >= capacity:
        # Read in ring order from ``position`` (the oldest slot): exactly the last ``capacity``.
        np.testing.assert_array_equal(np.roll(stored, -int(buf.position)), all_ids[-capacity:])
        assert_rows_consistent(buf.data)
    else:
        np.testing.assert_array_equal(stored[:total], all_ids)
        np.testing.assert_array_equal(stored[total:], 0)  # untouched slots stay zero
        filled = np.arange(capacity) < total
        assert_rows_consistent(buf.data, filled)
        for leaf in jax.tree.leaves(buf.data):
            assert not np.any(np.asarray(leaf)[~filled])

    if total > 0:
        batch = SAMPLE(buf, jax.random.key(seed), SAMPLE_SIZE)
        sampled = np.asarray(batch["id"])
        assert sampled.shape == (SAMPLE_SIZE,)
        assert set(sampled.tolist()) <= set(all_ids[-capacity:])
        assert_rows_consistent(batch)
        assert batch["tr"].obs.shape == (SAMPLE_SIZE, 3)
        assert batch["pix"].shape == (SAMPLE_SIZE, 2, 2) and batch["pix"].dtype == jnp.uint8


@settings(max_examples=30)
@given(add_sequences())
def test_sample_eager_equals_jitted(case):
    capacity, sizes = case
    if not sizes:
        sizes = [1]
    buf, all_ids = fill(capacity, sizes)
    key = jax.random.key(len(all_ids))
    eager = replay.sample(buf, key, SAMPLE_SIZE)
    jitted = SAMPLE(buf, key, SAMPLE_SIZE)
    for a, b in zip(jax.tree.leaves(eager), jax.tree.leaves(jitted), strict=True):
        np.testing.assert_array_equal(a, b)


def chi_square(counts):
    expected = counts.sum() / len(counts)
    return float(np.sum((counts - expected) ** 2 / expected))


def test_sampling_is_uniform_over_full_buffer():
    buf, all_ids = fill(8, [4, 4, 4, 4, 4])  # 20 rows: wrapped, ids 13..20 remain
    n = 16_000
    sampled = np.asarray(replay.sample(buf, jax.random.key(0), n)["id"])
    assert set(sampled.tolist()) <= set(all_ids[-8:])
    counts = np.array([np.sum(sampled == i) for i in all_ids[-8:]])
    # 7 degrees of freedom: P(chi2 > 30) ~ 1e-4 for a uniform sampler.
    assert chi_square(counts) < 30.0, counts
    # Independent draws, in random order: consecutive draws increase with P = 7/16.
    np.testing.assert_allclose(np.mean(np.diff(sampled) > 0), 7 / 16, atol=0.02)


def test_sampling_is_uniform_over_filled_part_only():
    buf, all_ids = fill(8, [5])
    n = 10_000
    sampled = np.asarray(replay.sample(buf, jax.random.key(1), n)["id"])
    assert set(sampled.tolist()) == set(all_ids)  # every filled slot drawn, no empty slot
    counts = np.array([np.sum(sampled == i) for i in all_ids])
    assert chi_square(counts) < 25.0, counts  # 4 degrees of freedom


def test_different_keys_give_different_samples():
    buf, _ = fill(8, [8])
    a = np.asarray(SAMPLE(buf, jax.random.key(0), SAMPLE_SIZE)["id"])
    b = np.asarray(SAMPLE(buf, jax.random.key(1), SAMPLE_SIZE)["id"])
    assert not np.array_equal(a, b)


def test_add_more_than_capacity_raises():
    buf = replay.init(4, example())
    with pytest.raises(ValueError):
        replay.add(buf, rows(range(1, 6)))
    with pytest.raises(ValueError):
        jax.jit(replay.add)(buf, rows(range(1, 6)))
    # Exactly capacity is fine.
    full = replay.add(buf, rows(range(1, 5)))
    assert int(full.size) == 4 and int(full.position) == 0


def test_add_mismatched_leading_sizes_raises():
    buf = replay.init(4, example())
    bad = rows([1, 2])
    bad["id"] = np.array([1, 2, 3], np.int32)
    with pytest.raises(ValueError):
        replay.add(buf, bad)


def test_sample_from_empty_raises():
    buf = replay.init(4, example())
    with pytest.raises(ValueError):
        replay.sample(buf, jax.random.key(0), 2)


def test_sample_from_empty_inside_jit_returns_zero_slot():
    """Documented: inside a compiled program (where it cannot raise) slot 0 is returned."""
    buf = replay.init(4, example())
    batch = SAMPLE(buf, jax.random.key(0), SAMPLE_SIZE)
    for leaf in jax.tree.leaves(batch):
        assert leaf.shape[0] == SAMPLE_SIZE
        assert not np.any(np.asarray(leaf))


@pytest.mark.parametrize("capacity", [0, -3])
def test_init_bad_capacity_raises(capacity):
    with pytest.raises(ValueError):
        replay.init(capacity, example())


def test_init_shapes_and_dtypes():
    buf = replay.init(6, example())
    shapes = jax.tree.map(lambda x: (x.shape, x.dtype), buf.data)
    assert shapes["id"] == ((6,), jnp.int32)
    assert shapes["tr"].obs == ((6, 3), jnp.float32)
    assert shapes["tr"].reward == ((6,), jnp.float32)
    assert shapes["pix"] == ((6, 2, 2), jnp.uint8)
    assert int(buf.size) == 0 and int(buf.position) == 0


def test_jit_with_donation_updates_in_place():
    buf = replay.init(5, example())
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # "donated buffers were not usable" would fail here
        new = ADD(buf, rows([1, 2, 3]))
        jax.block_until_ready(new)
    assert all(leaf.is_deleted() for leaf in jax.tree.leaves(buf.data))
    np.testing.assert_array_equal(new.data["id"], [1, 2, 3, 0, 0])
    new = ADD(new, rows([4, 5, 6, 7]))
    np.testing.assert_array_equal(new.data["id"], [6, 7, 3, 4, 5])
    assert int(new.position) == 2 and int(new.size) == 5


def test_scan_of_adds_equals_python_loop():
    capacity, n, steps = 5, 3, 7
    ids = np.arange(1, n * steps + 1).reshape(steps, n)
    stacked = jax.tree.map(lambda *xs: np.stack(xs), *[rows(i) for i in ids])

    @jax.jit
    def scanned(buf, stacked):
        return jax.lax.scan(lambda b, x: (replay.add(b, x), b.size), buf, stacked)

    buf, sizes = scanned(replay.init(capacity, example()), stacked)
    looped, all_ids = fill(capacity, [n] * steps)
    for a, b in zip(jax.tree.leaves(buf), jax.tree.leaves(looped), strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(sizes, [0, 3, 5, 5, 5, 5, 5])
    np.testing.assert_array_equal(np.roll(buf.data["id"], -int(buf.position)), all_ids[-5:])


VADD = jax.jit(jax.vmap(replay.add), donate_argnums=0)
VSAMPLE = jax.jit(jax.vmap(replay.sample, in_axes=(0, 0, None)), static_argnums=2)


@settings(max_examples=30)
@given(st.lists(st.integers(1, 5), min_size=1, max_size=6))
def test_vmap_one_buffer_per_seed(sizes):
    seeds, capacity = 3, 5
    single = replay.init(capacity, example())
    bufs = jax.tree.map(lambda x: jnp.stack([x] * seeds), single)
    per_seed = [[] for _ in range(seeds)]
    next_id = 1
    for n in sizes:
        # Different data per seed: seed s gets ids s * 1000 + ...
        batch_ids = [[s * 1000 + next_id + i for i in range(n)] for s in range(seeds)]
        next_id += n
        bufs = VADD(bufs, jax.tree.map(lambda *xs: np.stack(xs), *[rows(b) for b in batch_ids]))
        for s in range(seeds):
            per_seed[s] += batch_ids[s]
    total = sum(sizes)
    np.testing.assert_array_equal(bufs.size, [min(total, capacity)] * seeds)
    np.testing.assert_array_equal(bufs.position, [total % capacity] * seeds)
    keys = jax.random.split(jax.random.key(total), seeds)
    samples = VSAMPLE(bufs, keys, SAMPLE_SIZE)
    for s in range(seeds):
        buf_s = jax.tree.map(lambda x, s=s: x[s], bufs)
        expected, _ = fill(capacity, sizes, start_id=s * 1000 + 1)
        for a, b in zip(jax.tree.leaves(buf_s), jax.tree.leaves(expected), strict=True):
            np.testing.assert_array_equal(a, b)
        sampled_s = jax.tree.map(lambda x, s=s: x[s], samples)
        assert set(np.asarray(sampled_s["id"]).tolist()) <= set(per_seed[s][-capacity:])
        assert_rows_consistent(sampled_s)
        # Same draw as the unbatched sample with that seed's key.
        np.testing.assert_array_equal(
            sampled_s["id"], replay.sample(buf_s, keys[s], SAMPLE_SIZE)["id"]
        )


def test_add_of_rows_shaped_unlike_the_buffer_names_the_field():
    """Shape errors at the API boundary, not raw JAX scatter errors."""
    buf = replay.init(8, tj.Transition(np.zeros(3), np.zeros(2), 0.0, np.zeros(3), 0.0))
    good = tj.Transition(np.zeros((4, 3)), np.zeros((4, 2)), np.zeros(4), np.zeros((4, 3)),
                         np.zeros(4))  # fmt: skip
    assert int(replay.add(buf, good).size) == 4
    wrong_obs = good._replace(next_obs=np.zeros((4, 5)))
    with pytest.raises(ValueError, match=r"\.next_obs has shape \[4, 5\]; expected \[n, 3\]"):
        replay.add(buf, wrong_obs)
    unbatched = good._replace(reward=np.float32(0.0))
    with pytest.raises(ValueError, match=r"\.reward has shape \[\]; expected \[n\]"):
        replay.add(buf, unbatched)
    with pytest.raises(ValueError, match="structure"):
        replay.add(buf, {"obs": np.zeros((4, 3))})


@settings(max_examples=20, deadline=None)
@given(shards=st.sampled_from([1, 2]), adds=st.integers(0, 4), members=st.sampled_from([0, 3]))
def test_a_ring_grown_after_its_adds_equals_the_larger_ring_after_them(shards, adds, members):
    """A ring of ``short`` rows per slice that never wrapped, grown to ``long`` rows, is the
    ring of ``long`` rows that received the same adds: same rows, position and size, also
    under a leading member axis; and the ring of ``long`` rows shrunk to ``short`` is the short
    ring, where its filled rows fit (a shrink below them raises)."""
    short, long, per_add = 8, 20, 2 * shards
    example = {"x": jnp.zeros((3,)), "flag": jnp.zeros((), bool)}
    stack = (lambda b: jax.tree.map(lambda x: jnp.stack([x] * members), b)) if members else None
    small, large = (replay.init_slices(rows * shards, shards, example) for rows in (short, long))
    for i in range(adds):
        rows = {"x": jnp.full((per_add, 3), float(i + 1)), "flag": jnp.arange(per_add) % 2 == 0}
        small, large = replay.add_slices(small, rows), replay.add_slices(large, rows)
    if stack:
        small, large = stack(small), stack(large)
    grown = replay.resize_slices(small, long)
    assert replay.slice_rows(grown) == long
    for a, b in zip(jax.tree.leaves(grown), jax.tree.leaves(large), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    shrunk = replay.resize_slices(large, short)  # a resume that shortens the run
    assert replay.slice_rows(shrunk) == short
    for a, b in zip(jax.tree.leaves(shrunk), jax.tree.leaves(small), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    if adds == 4 and not members:  # 10 filled rows of a slice do not fit in 8
        extra = {"x": jnp.ones((per_add, 3)), "flag": jnp.ones(per_add, bool)}
        over = replay.add_slices(large, extra)
        with pytest.raises(ValueError, match="shrink"):
            replay.resize_slices(over, short)


@pytest.mark.parametrize(("field", "value"), [("obs", jnp.inf), ("next_obs", jnp.nan),
                                              ("critic_obs", -jnp.inf), (None, 0.0)])  # fmt: skip
def test_a_ring_s_observations_are_finite_unless_one_value_is_not(field, value):
    """``training.observations_finite`` over a ring of 6 rows, one value of one field made
    non-finite (the actions and rewards, which it does not read, always are)."""
    from td3_jax.core.training import observations_finite
    from td3_jax.core.types import Transition

    rows = Transition(obs=jnp.ones((6, 3)), action=jnp.full((6, 2), jnp.nan),
                      reward=jnp.full((6,), jnp.inf), next_obs=jnp.ones((6, 3)),
                      done=jnp.zeros(6), critic_obs=jnp.ones((6, 5)),
                      next_critic_obs=jnp.ones((6, 5)))  # fmt: skip
    if field is not None:
        rows = rows._replace(**{field: getattr(rows, field).at[4, 1].set(value)})
    ring = replay.add(replay.init(8, (jax.tree.map(lambda x: x[0], rows),
                                      jnp.zeros((), bool))), (rows, jnp.zeros(6, bool)))
    assert bool(observations_finite(ring)) is (field is None)
    without_critic = rows._replace(critic_obs=None, next_critic_obs=None)
    ring = replay.add(replay.init(8, (jax.tree.map(lambda x: x[0], without_critic),
                                      jnp.zeros((), bool))), (without_critic, jnp.zeros(6, bool)))
    assert bool(observations_finite(ring)) is (field in (None, "critic_obs"))
