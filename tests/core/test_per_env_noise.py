"""Per-environment exploration stds: their distribution, the redraw at episode ends, the noise
they put on actions, and their place in the checkpointed state."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from td3_jax.config import build
from td3_jax.config.schema import TrainConfig
from td3_jax.core import training
from td3_jax.runner.checkpoint import Checkpointer

LOW, HIGH = 0.05, 0.4
CFG = TrainConfig(
    env="gymnax/Pendulum-v1",
    hidden_sizes=(8, 8),
    num_envs=2048,
    steps_per_iter=1,
    updates_per_iter=1,
    batch_size=4,
    buffer_size=3 * 2048,
    warmup_steps=0,
    eval_every=2048,
    total_steps=3 * 2048,
    eval_envs=2,
    episode_length=3,
    expl_noise_min=LOW,
    expl_noise_max=HIGH,
)


@pytest.fixture(scope="module")
def spec():
    return build.make_spec(CFG)


@pytest.fixture(scope="module")
def hp():
    return build.hyperparams(CFG)


@pytest.fixture(scope="module")
def fresh(spec):
    return jax.jit(training.init, static_argnums=0)(spec, jax.random.PRNGKey(0))


def check_uniform(stds):
    """Uniform on [LOW, HIGH): range, mean, std and the quartiles within sampling error."""
    n, width = stds.size, HIGH - LOW
    assert stds.min() >= LOW and stds.max() < HIGH
    assert abs(stds.mean() - (LOW + HIGH) / 2) < 4 * width / np.sqrt(12 * n)
    assert abs(stds.std() - width / np.sqrt(12)) < 0.05 * width / np.sqrt(12)
    for q in (0.25, 0.5, 0.75):
        assert abs(np.mean(stds < LOW + q * width) - q) < 4 * np.sqrt(q * (1 - q) / n)


def test_initial_stds_are_uniform_per_environment(spec, hp, fresh):
    stds = np.asarray(training.exploration_std(spec, hp, fresh.expl_draw))
    assert stds.shape == (CFG.num_envs,)
    check_uniform(stds)
    other = jax.jit(training.init, static_argnums=0)(spec, jax.random.PRNGKey(1))
    assert not np.allclose(other.expl_draw, fresh.expl_draw)  # drawn from the run's key


def test_without_the_range_every_environment_gets_expl_noise(hp, fresh):
    spec = build.make_spec(dataclasses.replace(CFG, expl_noise_min=None, expl_noise_max=None))
    assert not spec.per_env_noise
    plain_hp = build.hyperparams(dataclasses.replace(CFG, expl_noise=0.3))
    stds = training.exploration_std(spec, plain_hp, fresh.expl_draw)
    np.testing.assert_array_equal(stds, np.full(CFG.num_envs, 0.3, np.float32))
    ended = jnp.ones(CFG.num_envs, bool)
    kept = training.redraw_exploration(spec, fresh.expl_draw, ended, jax.random.PRNGKey(0))
    np.testing.assert_array_equal(kept, fresh.expl_draw)


def test_redraw_only_where_an_episode_ended(spec, hp, fresh):
    ended = np.random.default_rng(0).uniform(size=CFG.num_envs) < 0.5
    draw = training.redraw_exploration(spec, fresh.expl_draw, jnp.asarray(ended),
                                       jax.random.PRNGKey(5))  # fmt: skip
    draw = np.asarray(draw)
    np.testing.assert_array_equal(draw[~ended], np.asarray(fresh.expl_draw)[~ended])
    assert np.all(draw[ended] != np.asarray(fresh.expl_draw)[ended])
    check_uniform(np.asarray(training.exploration_std(spec, hp, jnp.asarray(draw[ended]))))


def test_collect_redraws_at_episode_ends_and_explores_with_each_std(spec, hp, fresh):
    """Episodes of 3 steps: draws stay for two steps and all change on the third; actions
    carry each environment's own std (recomputed by hand from the same key)."""
    step = jax.jit(training.collect_step, static_argnums=0)
    state = fresh
    for i in range(3):
        key = jax.random.split(state.key)[1]
        new, _ = step(spec, hp, state)
        changed = np.asarray(new.expl_draw) != np.asarray(state.expl_draw)
        assert changed.all() if i == 2 else not changed.any(), i
        # The stored action: clip(policy + std_e * N(0, 1)) with explore's key schedule.
        obs = training.normalize(spec, state.obs_stats, state.env_state.obs)
        policy = spec.agent.actor.apply(state.agent.actor_params, obs)
        noise_keys = jax.random.split(jax.random.split(key)[1], CFG.num_envs)
        eps = jax.vmap(lambda k: jax.random.normal(k, (1,)))(noise_keys)
        std = LOW + (HIGH - LOW) * state.expl_draw
        expected = np.clip(policy + std[:, None] * eps, -1.0, 1.0)
        stored = np.asarray(new.buffer.data[0].action[0, i * CFG.num_envs : (i + 1) * CFG.num_envs])
        np.testing.assert_allclose(stored, expected, atol=1e-6)
        state = new


def test_the_draws_are_checkpointed(tmp_path, spec, fresh):
    state = fresh.replace(expl_draw=fresh.expl_draw[::-1])
    checkpointer = Checkpointer(tmp_path / "ckpt")
    checkpointer.save(1, state, {})
    restored, _, _ = checkpointer.restore(jax.eval_shape(lambda: state))
    np.testing.assert_array_equal(restored.expl_draw, state.expl_draw)
