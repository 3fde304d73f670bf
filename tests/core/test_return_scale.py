"""Reward scaling by running return statistics (``--return-bound``, td3_jax.core.return_scale):
the statistics against a NumPy re-computation, their place in the training chunk (replayed from
the rewards and episode ends the ring stored), the scaled rewards in the update, and the
config's checks."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from td3_jax.config.build import make_trainer
from td3_jax.config.schema import ConfigError, TrainConfig, validate
from td3_jax.core import actor_critic as ac
from td3_jax.core import return_scale, training

NUM_ENVS = 4


def reference(rewards: np.ndarray, ended: np.ndarray, discount: float, bound: float):
    """NumPy: every step's discounted returns ``[steps, envs]`` (an episode's last reward ends
    its sum), the sums left running, and the scale from all returns seen."""
    running = np.zeros(rewards.shape[1])
    seen = []
    for reward, end in zip(rewards, ended, strict=True):
        running = discount * running + reward
        seen.append(running.copy())
        running = np.where(end, 0.0, running)
    seen = np.stack(seen)
    scale = max(np.sqrt(np.var(seen) + return_scale.EPSILON), np.max(np.abs(seen)) / bound)
    return seen, running, scale


def test_statistics_and_scale_match_a_numpy_recomputation():
    rng = np.random.default_rng(3)
    rewards = rng.normal(-1.0, 2.0, size=(12, 3)).astype(np.float32)
    ended = rng.random((12, 3)) < 0.25
    state = return_scale.init(3)
    assert float(return_scale.scale(state, jnp.float32(5.0))) == 1.0  # nothing seen yet
    for reward, end in zip(rewards, ended, strict=True):
        state = return_scale.update(state, jnp.asarray(reward), jnp.asarray(end), 0.9)
    seen, running, scale = reference(rewards, ended, 0.9, 5.0)
    np.testing.assert_allclose(state.returns, running, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(state.stats.mean[0], seen.mean(), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(state.stats.var[0], seen.var(), rtol=1e-5)
    np.testing.assert_allclose(state.max_abs, np.abs(seen).max(), rtol=1e-6)
    np.testing.assert_allclose(return_scale.scale(state, jnp.float32(5.0)), scale, rtol=1e-5)
    # A small bound lets the largest return set the scale; a large one leaves the spread.
    assert float(return_scale.scale(state, jnp.float32(0.1))) == pytest.approx(
        np.abs(seen).max() / 0.1, rel=1e-5
    )
    assert float(return_scale.scale(state, jnp.float32(1e6))) == pytest.approx(seen.std(), rel=1e-4)


def test_one_episode_of_constant_rewards_by_hand():
    # rewards 1, 1, 1 with discount 0.5 and the episode ending on the third: returns 1, 1.5,
    # 1.75 (then 0); mean 17/12, variance of {1, 1.5, 1.75}; the bound 1 gives scale 1.75.
    state = return_scale.init(1)
    for end in (False, False, True):
        state = return_scale.update(state, jnp.ones(1), jnp.asarray([end]), 0.5)
    assert float(state.returns[0]) == 0.0
    assert float(state.stats.mean[0]) == pytest.approx(17 / 12)
    assert float(state.stats.var[0]) == pytest.approx(np.var([1.0, 1.5, 1.75]))
    assert float(return_scale.scale(state, jnp.float32(1.0))) == pytest.approx(1.75)


SCALED = TrainConfig(
    env="gymnax/Pendulum-v1",
    hidden_sizes=(16, 16),
    num_envs=NUM_ENVS,
    eval_envs=2,
    episode_length=16,
    eval_every=96,
    total_steps=192,
    updates_per_iter=1,
    batch_size=16,
    buffer_size=192,  # the ring never wraps: every transition of the run is still in it
    warmup_steps=64,
    discount=0.9,
    return_bound=5.0,
)


@pytest.fixture(scope="module")
def scaled_run():
    trainer = make_trainer(validate(SCALED))
    state = jax.jit(trainer.init)(jax.random.PRNGKey(0))
    chunk = jax.jit(trainer.chunk)
    state, _ = chunk(state)
    state, second = chunk(state)
    return trainer, jax.device_get(state), jax.device_get(second)


def test_the_chunk_keeps_the_statistics_of_the_rewards_it_stored(scaled_run):
    _, state, metrics = scaled_run
    data, ended = jax.tree.map(lambda x: np.asarray(x[0]), state.buffer.data)
    steps = SCALED.run_steps // NUM_ENVS
    rewards = data.reward.reshape(steps, NUM_ENVS)  # row r: step r // 4 of environment r % 4
    ends = ended.reshape(steps, NUM_ENVS)
    assert ends.any() and (rewards < 0).all()  # 16-step episodes of Pendulum's costs
    seen, running, scale = reference(rewards, ends, SCALED.discount, SCALED.return_bound)
    np.testing.assert_allclose(state.returns.returns, running, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(state.returns.max_abs, np.abs(seen).max(), rtol=1e-5)
    np.testing.assert_allclose(metrics["reward_scale"], scale, rtol=1e-4)
    assert state.returns.stats.count == SCALED.run_steps


def test_the_update_learns_from_rewards_divided_by_the_scale(scaled_run):
    trainer, state, _ = scaled_run
    spec, hp = trainer.spec, trainer.hyperparams
    key = jax.random.PRNGKey(5)
    # (compiled: op by op, an update of these networks takes about a minute on a CPU)
    step = jax.jit(lambda scale: training.gradient_step(spec, hp, state.buffer, state.obs_stats,
                                                        scale, state.agent, key))  # fmt: skip
    got, _ = step(jnp.float32(7.5))

    @jax.jit
    def by_hand():  # the same sample, its rewards divided by the scale, the agent's update
        sample_key, update_key = jax.random.split(key)
        sampled = training.sample_batch(spec, hp, state.buffer, sample_key)
        batch = training.agent_batch(spec, state.obs_stats, sampled)
        batch = batch._replace(reward=batch.reward / 7.5)
        return ac.update(spec.agent, hp.agent, state.agent, batch, update_key)

    want, _ = by_hand()
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6), got, want)
    unscaled, _ = step(jnp.float32(1.0))
    differs = jax.tree.map(lambda a, b: not np.allclose(a, b), unscaled.critic_params,
                           got.critic_params)  # fmt: skip
    assert any(jax.tree.leaves(differs))  # the scale reaches the critics' targets


def test_a_run_without_it_keeps_its_state_layout():
    trainer = make_trainer(validate(dataclasses.replace(SCALED, return_bound=None)))
    state = jax.eval_shape(trainer.init, jax.random.PRNGKey(0))
    assert state.returns is None
    assert not trainer.spec.scale_rewards


@pytest.mark.parametrize("bound", [0.0, -1.0, float("nan"), float("inf")])
def test_a_bound_that_is_not_a_positive_number_is_refused(bound):
    with pytest.raises(ConfigError, match="--return-bound"):
        validate(TrainConfig(return_bound=bound))


def test_an_iteration_learns_through_the_scale_and_only_through_it(scaled_run, monkeypatch):
    """After warm-up, one iteration with reward scaling (A) differs from the same iteration
    whose scale is forced to 1 (B), and B equals the iteration of a run without scaling (C):
    the scale reaches the updates, and by :func:`training.reward_scale` alone."""
    trainer, state, _ = scaled_run
    spec, hp = trainer.spec, trainer.hyperparams

    def step(spec, state):  # a new function each time: traced afresh, patches included
        return jax.jit(lambda s: training.iteration(spec, hp, s))(state)[0]

    scaled = step(spec, state)
    assert float(training.reward_scale(spec, hp, state)) > 1.0  # Pendulum's returns: far from 1
    monkeypatch.setattr(training, "reward_scale", lambda *_: jnp.ones((), jnp.float32))
    unit = step(spec, state)
    plain = step(dataclasses.replace(spec, scale_rewards=False), state.replace(returns=None))
    leaves = lambda s: jax.tree.leaves(s.agent.critic_params)
    assert any(not np.allclose(a, b) for a, b in zip(leaves(scaled), leaves(unit), strict=True))
    for a, b in zip(leaves(unit), leaves(plain), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)
