"""Exploration noise: TD3's clipped Gaussian and the Ornstein-Uhlenbeck process."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from td3_jax.core import noise

# --------------------------------------------------------------------------------------------
# Gaussian
# --------------------------------------------------------------------------------------------


def test_gaussian_stays_within_bounds():
    max_action = 2.0
    action = np.random.default_rng(0).uniform(-2, 2, (2000, 3)).astype(np.float32)
    out = np.asarray(noise.gaussian(jax.random.key(0), action, 3.0, max_action))
    assert out.shape == action.shape and out.dtype == np.float32
    assert np.all(np.abs(out) <= max_action)
    # The noise is large, so the clip is active often, at both bounds.
    assert np.sum(out == max_action) > 100 and np.sum(out == -max_action) > 100


def test_gaussian_std_and_exact_draw():
    expl_noise, max_action = 0.05, 2.0
    action = jnp.zeros((200_000,), jnp.float32)
    key = jax.random.key(1)
    out = np.asarray(noise.gaussian(key, action, expl_noise, max_action))
    # Clipping is negligible here (the bound is 20 standard deviations away).
    np.testing.assert_allclose(out.std(), expl_noise * max_action, rtol=0.02)
    assert abs(out.mean()) < 4 * expl_noise * max_action / np.sqrt(out.size)
    # Exactly action + expl_noise * max_action * N(0, 1) with the given key.
    expected = 0.1 * np.asarray(jax.random.normal(key, action.shape))
    np.testing.assert_allclose(out, expected, rtol=1e-6, atol=1e-7)


def test_gaussian_noise_is_added_to_the_action():
    action = jnp.full((50_000,), 0.3, jnp.float32)
    out = np.asarray(noise.gaussian(jax.random.key(2), action, 0.1, 1.0))
    np.testing.assert_allclose(out.mean(), 0.3, atol=0.003)
    np.testing.assert_allclose((out - 0.3).std(), 0.1, rtol=0.03)


def test_gaussian_per_env_expl_noise_and_per_dim_bounds():
    # expl_noise broadcast per environment (rows), max_action per action dimension (columns).
    expl = jnp.array([[0.01], [0.1]])
    max_action = jnp.array([0.5, 3.0])
    action = jnp.zeros((2, 2), jnp.float32)
    keys = jax.random.split(jax.random.key(3), 20_000)
    out = np.asarray(jax.vmap(lambda k: noise.gaussian(k, action, expl, max_action))(keys))
    std = out.std(axis=0)
    np.testing.assert_allclose(std, np.array([[0.005, 0.03], [0.05, 0.3]]), rtol=0.05)
    big = np.asarray(noise.gaussian(jax.random.key(4), jnp.zeros((5000, 2)), 10.0, max_action))
    assert np.all(np.abs(big) <= np.asarray(max_action))
    assert np.isclose(np.abs(big[:, 0]).max(), 0.5) and np.isclose(np.abs(big[:, 1]).max(), 3.0)


def test_gaussian_different_keys_differ():
    a = noise.gaussian(jax.random.key(0), jnp.zeros(8), 0.1)
    b = noise.gaussian(jax.random.key(1), jnp.zeros(8), 0.1)
    assert not np.allclose(a, b)


# --------------------------------------------------------------------------------------------
# Ornstein-Uhlenbeck
# --------------------------------------------------------------------------------------------


def test_ou_defaults_and_init():
    p = noise.OUParams()
    assert (p.mu, p.theta, p.max_sigma, p.min_sigma) == (0.0, 0.15, 0.3, 0.3)
    state = noise.ou_init(3, noise.OUParams(mu=0.25))
    np.testing.assert_array_equal(state.x, [0.25, 0.25, 0.25])
    assert int(state.t) == 0


def test_ou_one_step_by_hand():
    params = noise.OUParams(mu=0.3, theta=0.2, max_sigma=0.4, min_sigma=0.4)
    x = jnp.array([1.0, -0.5, 0.3, 2.0], jnp.float32)
    state = noise.OUState(x=x, t=jnp.array(7, jnp.int32))
    key = jax.random.key(5)
    new, out = noise.ou_step(key, state, params)
    eps = np.asarray(jax.random.normal(key, (4,)))
    expected = np.asarray(x) + 0.2 * (0.3 - np.asarray(x)) + 0.4 * eps
    np.testing.assert_allclose(out, expected, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(new.x, out)
    assert int(new.t) == 8


def test_ou_action_adds_process_and_clips():
    params = noise.OUParams(theta=0.0, max_sigma=5.0, min_sigma=5.0)
    state = noise.ou_init(64, params)
    action = jnp.full((64,), 0.5)
    key = jax.random.key(6)
    new, out = noise.ou_action(key, state, action, params, max_action=2.0)
    _, x = noise.ou_step(key, state, params)
    np.testing.assert_allclose(out, np.clip(0.5 + np.asarray(x), -2.0, 2.0), rtol=1e-6)
    np.testing.assert_array_equal(new.x, x)
    assert np.all(np.abs(np.asarray(out)) <= 2.0)
    assert np.any(np.asarray(out) == 2.0) and np.any(np.asarray(out) == -2.0)


@functools.partial(jax.jit, static_argnums=(1, 2, 3))
def _ou_run(key, num_envs, steps, action_size, params):
    """``steps`` OU steps for ``num_envs`` independent processes: xs ``[steps, envs, a]``."""
    states = jax.vmap(lambda _: noise.ou_init(action_size, params))(jnp.arange(num_envs))

    def body(states, key):
        keys = jax.random.split(key, num_envs)
        states, x = jax.vmap(lambda k, s: noise.ou_step(k, s, params))(keys, states)
        return states, x

    return jax.lax.scan(body, states, jax.random.split(key, steps))


def test_ou_stationary_variance():
    theta, sigma, mu = 0.15, 0.3, 0.2
    params = noise.OUParams(mu=mu, theta=theta, max_sigma=sigma, min_sigma=sigma)
    states, xs = _ou_run(jax.random.key(7), 64, 2000, 2, params)
    xs = np.asarray(xs)[200:]  # burn-in: (1 - theta)^200 ~ 1e-14
    stationary = sigma**2 / (1.0 - (1.0 - theta) ** 2)  # discrete AR(1), ~0.324
    np.testing.assert_allclose(xs.var(), stationary, rtol=0.05)
    np.testing.assert_allclose(xs.mean(), mu, atol=0.03)
    # Lag-1 autocorrelation of the AR(1) process is 1 - theta.
    centred = xs - mu
    lag1 = np.mean(centred[1:] * centred[:-1]) / np.mean(centred**2)
    np.testing.assert_allclose(lag1, 1.0 - theta, atol=0.02)
    assert np.all(np.asarray(states.t) == 2000)


def test_ou_envs_are_independent():
    params = noise.OUParams()  # mu 0, theta 0.15, sigma 0.3
    _, xs = _ou_run(jax.random.key(8), 64, 2000, 2, params)
    xs = np.asarray(xs)
    # The innovations sigma * N of x_{t+1} = (1 - theta) x_t + sigma * N, per env and dim.
    innovations = (xs[1:] - 0.85 * xs[:-1]).reshape(xs.shape[0] - 1, -1)  # [time, env * dim]
    np.testing.assert_allclose(innovations.std(axis=0), 0.3, rtol=0.1)
    corr = np.corrcoef(innovations.T)
    off_diag = corr[~np.eye(len(corr), dtype=bool)]
    # Independent draws: cross-correlations only at the sampling-error level (~0.02).
    assert np.max(np.abs(off_diag)) < 0.15
    assert abs(np.mean(off_diag)) < 0.01


def test_ou_vmap_matches_per_env_steps():
    params = noise.OUParams(theta=0.3, max_sigma=0.5, min_sigma=0.5)
    num_envs = 4
    states = jax.vmap(lambda _: noise.ou_init(3, params))(jnp.arange(num_envs))
    states = states.replace(x=jnp.arange(12.0).reshape(4, 3) / 10)
    keys = jax.random.split(jax.random.key(9), num_envs)
    new, xs = jax.vmap(lambda k, s: noise.ou_step(k, s, params))(keys, states)
    for e in range(num_envs):
        state_e = noise.OUState(x=states.x[e], t=states.t[e])
        _, x_e = noise.ou_step(keys[e], state_e, params)
        np.testing.assert_allclose(xs[e], x_e, rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(new.t, [1, 1, 1, 1])
    # Each environment got its own draw.
    increments = np.asarray(xs) - 0.7 * np.asarray(states.x)
    assert len({tuple(np.round(r, 6)) for r in increments}) == num_envs


@pytest.mark.parametrize(
    ("t", "expected"),
    [(0, 0.5), (250, 0.4), (500, 0.3), (1000, 0.1), (1001, 0.1), (5000, 0.1)],
)
def test_ou_sigma_decay(t, expected):
    params = noise.OUParams(max_sigma=0.5, min_sigma=0.1, decay_period=1000.0)
    np.testing.assert_allclose(noise.ou_sigma(params, jnp.array(t, jnp.int32)), expected, 1e-6)


def test_ou_step_uses_decayed_sigma():
    params = noise.OUParams(mu=0.0, theta=0.15, max_sigma=0.5, min_sigma=0.1, decay_period=1000.0)
    key = jax.random.key(10)
    eps = np.asarray(jax.random.normal(key, (3,)))
    for t, sigma in [(0, 0.5), (500, 0.3), (1000, 0.1), (3000, 0.1)]:
        state = noise.OUState(x=jnp.zeros(3), t=jnp.array(t, jnp.int32))
        new, x = noise.ou_step(key, state, params)
        np.testing.assert_allclose(x, sigma * eps, rtol=1e-5, atol=1e-7)
        assert int(new.t) == t + 1


def test_ou_reset_only_where_requested():
    params = noise.OUParams(mu=0.4)
    state = noise.OUState(x=jnp.array([1.0, 2.0, 3.0, 4.0]), t=jnp.array(17, jnp.int32))
    new = noise.ou_reset(state, jnp.array([True, False, True, False]), params)
    np.testing.assert_allclose(new.x, [0.4, 2.0, 0.4, 4.0])
    assert int(new.t) == 17  # the decay clock is global, not reset

    # Per environment under vmap: one reset flag per env resets that env's whole vector.
    xs = jnp.arange(12.0).reshape(4, 3)
    states = noise.OUState(x=xs, t=jnp.full((4,), 5, jnp.int32))
    done = jnp.array([False, True, False, True])
    new = jax.vmap(lambda s, d: noise.ou_reset(s, d, params))(states, done)
    expected = np.where(np.asarray(done)[:, None], 0.4, np.asarray(xs))
    np.testing.assert_allclose(new.x, expected)
    np.testing.assert_array_equal(new.t, [5, 5, 5, 5])
