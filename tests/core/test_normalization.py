"""Tests of the running observation statistics (``td3_jax.core.normalization``).

The reference is numpy's mean and population variance of all the data merged so far; the data
have a large offset and per-dimension scales, so a naive sum-of-squares update would visibly
lose precision in float32.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from td3_jax.core import normalization

N, SIZE = 48, 3
DATA = (
    np.random.default_rng(0).normal(size=(N, SIZE)) * np.array([0.5, 3.0, 20.0])
    + np.array([100.0, -5.0, 0.0])
).astype(np.float32)


#: The update compiled whole per batch size (op by op, each example took seconds).
_update = jax.jit(normalization.update)


def merged(batches) -> normalization.RunningStats:
    stats = normalization.init(SIZE)
    for batch in batches:
        stats = _update(stats, jnp.asarray(batch))
    return stats


@given(cuts=st.sets(st.integers(1, N - 1), max_size=8))
def test_merged_batches_match_numpy(cuts):
    batches = np.split(DATA, sorted(cuts))
    stats = merged(batches)
    assert float(stats.count) == N
    np.testing.assert_allclose(stats.mean, DATA.astype(np.float64).mean(0), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(stats.var, DATA.astype(np.float64).var(0), rtol=1e-4)


@settings(max_examples=10)
@given(prefix=st.integers(1, N))
def test_prefix_statistics(prefix):
    """Row-by-row merging (batches of one, each with zero variance) of the first rows."""
    stats = merged(DATA[i : i + 1] for i in range(prefix))
    ref = DATA[:prefix].astype(np.float64)
    assert float(stats.count) == prefix
    np.testing.assert_allclose(stats.mean, ref.mean(0), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(stats.var, ref.var(0), rtol=1e-3, atol=1e-5)


def test_init():
    stats = normalization.init(SIZE)
    np.testing.assert_array_equal(stats.mean, np.zeros(SIZE))
    np.testing.assert_array_equal(stats.var, np.ones(SIZE))
    assert float(stats.count) == 0.0
    assert stats.mean.dtype == jnp.float32 and stats.var.dtype == jnp.float32


def test_normalize_is_identity_before_any_update():
    stats = normalization.init(SIZE)
    # Values far beyond the clip would be clipped if normalisation were applied.
    obs = jnp.asarray([[1e3, -250.0, 0.5], [7.0, 0.0, -1e6]], jnp.float32)
    np.testing.assert_array_equal(normalization.normalize(stats, obs), obs)
    np.testing.assert_array_equal(normalization.normalize(stats, obs, clip=1.0), obs)


@pytest.mark.parametrize("clip", [10.0, 2.0])
def test_normalized_values_are_clipped(clip):
    stats = merged([DATA])
    mean, std = DATA.mean(0), DATA.std(0)
    # Rows at mean + k std for k from -50 to 50: beyond +-clip they must be exactly +-clip.
    ks = np.linspace(-50.0, 50.0, 101, dtype=np.float32)
    obs = mean[None, :] + ks[:, None] * std[None, :]
    out = np.asarray(normalization.normalize(stats, jnp.asarray(obs), clip=clip))
    assert out.max() == pytest.approx(clip) and out.min() == pytest.approx(-clip)
    assert np.all(np.abs(out) <= clip)
    outside = np.abs(ks) > clip + 0.01
    np.testing.assert_array_equal(
        out[outside], np.sign(ks[outside])[:, None] * clip * np.ones(SIZE)
    )
    inside = np.abs(ks) < clip - 0.01
    np.testing.assert_allclose(
        out[inside], np.repeat(ks[inside][:, None], SIZE, axis=1), rtol=1e-3, atol=1e-3
    )


def test_default_clip_is_ten():
    stats = merged([DATA])
    obs = jnp.asarray(DATA.mean(0) + 1e3 * DATA.std(0))[None, :]
    np.testing.assert_allclose(normalization.normalize(stats, obs), np.full((1, SIZE), 10.0))


def test_normalizing_data_with_its_own_stats_standardizes_it():
    stats = merged(np.split(DATA, [5, 17, 30]))
    out = np.asarray(normalization.normalize(stats, jnp.asarray(DATA)))
    np.testing.assert_allclose(out.mean(0), np.zeros(SIZE), atol=1e-4)
    np.testing.assert_allclose(out.std(0), np.ones(SIZE), rtol=1e-3)
    # And it is the plain standardisation, elementwise.
    ref = (DATA - DATA.mean(0)) / DATA.std(0)
    np.testing.assert_allclose(out, ref, rtol=1e-3, atol=1e-3)


def test_constant_dimension_does_not_blow_up():
    data = DATA.copy()
    data[:, 1] = 3.0  # zero variance: the epsilon keeps the result finite
    stats = merged([data[:20], data[20:]])
    out = np.asarray(normalization.normalize(stats, jnp.asarray(data)))
    assert np.all(np.isfinite(out))
    np.testing.assert_allclose(out[:, 1], 0.0, atol=1e-2)
