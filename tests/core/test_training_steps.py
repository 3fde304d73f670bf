"""The steps of the training program on their own: collect, learn, evaluate, and the one driver.

Tiny gymnax/Pendulum-v1 specs; every expectation is computed independently (numpy pendulum
physics, hand counts, explicit compositions of the agent's update).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from td3_jax import envs
from td3_jax.cli.app import main as cli_main
from td3_jax.config import build
from td3_jax.config.schema import TrainConfig
from td3_jax.core import actor_critic, training
from td3_jax.runner.logger import read_metrics

TINY = TrainConfig(
    env="gymnax/Pendulum-v1",
    hidden_sizes=(8, 8),
    num_envs=2,
    steps_per_iter=3,
    updates_per_iter=2,
    batch_size=4,
    buffer_size=64,
    warmup_steps=1_000,
    eval_every=12,
    total_steps=24,
    eval_envs=3,
    episode_length=10,
)
G, M, L, DT, MAX_SPEED, MAX_TORQUE = 10.0, 1.0, 1.0, 0.05, 8.0, 2.0  # gymnax Pendulum-v1


@pytest.fixture(scope="module")
def spec():
    return build.make_spec(TINY)


@pytest.fixture(scope="module")
def hp():
    return build.hyperparams(TINY)


@pytest.fixture(scope="module")
def fresh(spec):
    return jax.jit(training.init, static_argnums=0)(spec, jax.random.PRNGKey(0))


def test_collect_writes_one_row_per_environment_step(spec, hp, fresh):
    state, metrics = jax.jit(training.collect, static_argnums=0)(spec, hp, fresh)
    assert int(state.env_steps) == 6 and int(state.buffer.size[0]) == 6
    rows, ended = jax.tree.map(lambda x: np.asarray(x[0, :6]), state.buffer.data)
    obs = rows.obs.reshape(3, 2, 3)  # [steps, envs, obs]
    np.testing.assert_array_equal(obs[0], fresh.env_state.obs)
    np.testing.assert_array_equal(rows.next_obs.reshape(3, 2, 3)[:2], obs[1:])  # no episode end
    np.testing.assert_array_equal(rows.next_obs.reshape(3, 2, 3)[2], state.env_state.obs)
    assert not ended.any() and np.all(rows.done == 0)
    # Pendulum reward of each stored (obs, action), by hand; torque u = 2 a.
    theta = np.arctan2(rows.obs[:, 1], rows.obs[:, 0])
    u = MAX_TORQUE * rows.action[:, 0]
    np.testing.assert_allclose(rows.reward, -(theta**2 + 0.1 * rows.obs[:, 2] ** 2 + 0.001 * u**2),
                               rtol=1e-5, atol=1e-5)  # fmt: skip
    assert float(metrics["episodes"]) == 0.0
    assert float(metrics["reward_mean"]) == pytest.approx(rows.reward.mean(), rel=1e-5)
    assert float(state.obs_stats.count) == 6.0
    assert int(state.agent.step) == 0


def test_learn_is_the_agents_update_on_sampled_normalised_batches(spec, hp, fresh):
    state = fresh
    collect = jax.jit(training.collect, static_argnums=0)
    for _ in range(3):
        state, _ = collect(spec, hp, state)
    key = jax.random.PRNGKey(7)
    learn = jax.jit(training.learn, static_argnums=0)
    scale = training.reward_scale(spec, hp, state)  # 1: this run does not scale rewards
    agent, metrics = learn(spec, hp, state.agent, state.buffer, state.obs_stats, scale, key)
    assert int(agent.step) == 2 and float(metrics["updates"]) == 2.0
    # The same two updates, composed by hand from the agent's own functions (each compiled on
    # its own: run op by op, they took most of this test's time).
    sample = jax.jit(training.sample_batch, static_argnums=0)
    normalize = jax.jit(training.normalize, static_argnums=0)
    update = jax.jit(actor_critic.update, static_argnums=0)
    expected, losses = state.agent, []
    for k in jax.random.split(key, 2):
        sample_key, update_key = jax.random.split(k)
        batch = sample(spec, hp, state.buffer, sample_key)
        norm = lambda o: normalize(spec, state.obs_stats, o)
        batch = batch._replace(obs=norm(batch.obs), next_obs=norm(batch.next_obs))
        expected, m = update(spec.agent, hp.agent, expected, batch, update_key)
        losses.append(float(m["critic_loss"]))
    for a, b in zip(jax.tree.leaves(agent), jax.tree.leaves(expected), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    assert float(metrics["critic_loss"]) == pytest.approx(sum(losses), rel=1e-5)
    assert float(metrics["actor_updated"]) == 1.0  # the second update (policy_freq 2)


def test_iteration_before_warmup_skips_learning_with_zero_metrics(spec, hp, fresh):
    state, metrics = jax.jit(training.iteration, static_argnums=0)(spec, hp, fresh)
    assert int(state.iteration) == 1 and int(state.agent.step) == 0
    for name in (*actor_critic.METRIC_NAMES, "updates"):
        assert float(metrics[name]) == 0.0, name


def _pendulum_returns(obs0: np.ndarray, steps: int) -> np.ndarray:
    """Zero-torque pendulum episodes from observations ``[n, 3]`` (cos, sin, thetadot)."""
    theta = np.arctan2(obs0[:, 1], obs0[:, 0]).astype(np.float64)
    thetadot = obs0[:, 2].astype(np.float64)
    total = np.zeros(len(obs0))
    for _ in range(steps):
        angle = (theta + np.pi) % (2 * np.pi) - np.pi
        total -= angle**2 + 0.1 * thetadot**2
        thetadot = np.clip(thetadot + 3 * G / (2 * L) * np.sin(theta) * DT, -MAX_SPEED, MAX_SPEED)
        theta = theta + thetadot * DT
    return total


def test_evaluate_runs_one_deterministic_episode_per_environment(spec, fresh):
    # A policy that outputs exactly 0 (all actor weights zero): zero torque.
    zero_actor = jax.tree.map(jnp.zeros_like, fresh.agent.actor_params)
    state = fresh.replace(agent=fresh.agent.replace(actor_params=zero_actor))
    key = jax.random.PRNGKey(3)
    returns = np.asarray(jax.jit(training.evaluate, static_argnums=0)(spec, state, key))
    start = envs.reset(spec.env, key, spec.eval_envs)
    expected = _pendulum_returns(np.asarray(start.obs), TINY.episode_length)
    np.testing.assert_allclose(returns, expected, rtol=1e-3, atol=1e-3)


def lifetime_env(episode_length: int) -> envs.Environment:
    """Each episode lives a random 1..12 steps (drawn at reset, observed), paying 1 per step."""

    def reset_fn(key):
        life = jax.random.randint(key, (), 1, 13).astype(jnp.float32)
        return {"life": life, "age": jnp.float32(0)}, jnp.stack([life, jnp.float32(0)])

    def step_fn(inner, action, key):
        del action, key
        age = inner["age"] + 1
        obs = jnp.stack([inner["life"], age])
        return {**inner, "age": age}, obs, jnp.float32(1), age >= inner["life"]

    one = np.ones(1, np.float32)
    return envs.Environment("test/lifetime", 2, 1, episode_length, -one, one, reset_fn, step_fn)


@pytest.mark.parametrize("limit", [8, 30])
def test_evaluation_returns_each_first_episode_whether_or_not_it_stops_early(limit):
    """The evaluation stops stepping once all episodes ended; the returns equal the lifetimes
    (cut at the time limit) and the recorded evaluation's, which steps to the limit."""
    env = lifetime_env(limit)
    spec = build.make_spec(dataclasses.replace(TINY, eval_envs=16), env)
    state = jax.jit(training.init, static_argnums=0)(spec, jax.random.PRNGKey(0))
    key = jax.random.PRNGKey(5)
    returns = np.asarray(jax.jit(training.evaluate, static_argnums=0)(spec, state, key))
    lives = np.asarray(envs.reset(spec.env, key, 16).obs)[:, 0]
    np.testing.assert_array_equal(returns, np.minimum(lives, limit))
    recorded = jax.jit(training.evaluate_recorded, static_argnums=(0, 3))
    env_with_qpos = dataclasses.replace(env, qpos_fn=lambda inner: inner["age"][None])
    spec_q = dataclasses.replace(spec, env=env_with_qpos)
    np.testing.assert_array_equal(recorded(spec_q, state, key, 2)[0], returns)


@pytest.mark.runs
def test_the_command_and_make_train_give_the_same_evaluations(tmp_path):
    """One driver, one key schedule: ``td3-jax train --seed s`` = ``make_train(cfg)(key(s))``."""
    cfg = dataclasses.replace(TINY, warmup_steps=12, total_steps=36, seed=4)
    out = tmp_path / "run"
    flags = {"env": cfg.env, "hidden-sizes": "8 8", "num-envs": "2", "steps-per-iter": "3",
             "updates-per-iter": "2", "batch-size": "4", "buffer-size": "64",
             "warmup-steps": "12", "eval-every": "12", "total-steps": "36", "eval-envs": "3",
             "episode-length": "10", "seed": "4"}  # fmt: skip
    args = [part for k, v in flags.items() for part in (f"--{k}", *v.split())]
    cli_main(["train", *args, "--out", str(out), "--quiet", "--compile-cache", "off"])
    records = read_metrics(out / "metrics.jsonl")
    _, metrics = jax.jit(build.make_train(cfg))(training.key_for_seed(4))
    library = np.asarray(metrics["eval_returns"]).mean(axis=1)
    assert [r["env_steps"] for r in records] == [12, 24, 36]
    np.testing.assert_allclose([r["eval_return_mean"] for r in records], library, rtol=1e-4)
    np.testing.assert_allclose([r["critic_loss"] for r in records],
                               np.asarray(metrics["critic_loss"]), rtol=1e-4)  # fmt: skip
