"""Tests of the environment interface and its auto-reset (``td3_jax.envs``).

Most of the auto-reset semantics are checked on a tiny hand-made "counter" environment whose
every value can be worked out by hand; the adapters are then checked against their sources:
gymnax's Pendulum against gymnax's own ``step_env`` and the Pendulum reward formula, Brax's
inverted pendulum (MJX backend, slow on CPU: one shared rollout) against its termination rule.
"""

from __future__ import annotations

import dataclasses
import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from td3_jax import envs
from td3_jax.envs import Environment, UnknownEnvironmentError

# ---------------------------------------------------------------------------------------------
# A deterministic 1-D counter environment.
#
# obs = [position, step_count]; reset draws position ~ U[-1, 1) from its key; a step adds the
# (rescaled) action to the position and rewards the new position; the episode terminates when
# |position| > THRESHOLD.
# ---------------------------------------------------------------------------------------------

THRESHOLD = 5.0


def counter_env(episode_length: int, low=(-2.0,), high=(2.0,)) -> Environment:
    def reset_fn(key):
        position = jax.random.uniform(key, (), minval=-1.0, maxval=1.0)
        inner = {"position": position, "count": jnp.zeros((), jnp.int32)}
        return inner, jnp.stack([position, 0.0])

    def step_fn(inner, action, key):
        del key
        position = inner["position"] + action[0]
        count = inner["count"] + 1
        obs = jnp.stack([position, count.astype(jnp.float32)])
        return {"position": position, "count": count}, obs, position, jnp.abs(position) > THRESHOLD

    return Environment(
        name="test/counter",
        observation_size=2,
        action_size=len(low),
        episode_length=episode_length,
        action_low=np.asarray(low, np.float32),
        action_high=np.asarray(high, np.float32),
        reset_fn=reset_fn,
        step_fn=step_fn,
    )


def jitted(env: Environment):
    return jax.jit(functools.partial(envs.step, env)), jax.jit(
        functools.partial(envs.reset, env), static_argnums=1
    )


def host(tree):
    return jax.tree.map(np.asarray, jax.device_get(tree))


def const_action(num_envs: int, value: float) -> jax.Array:
    return jnp.full((num_envs, 1), value, jnp.float32)


# Action rescaling ------------------------------------------------------------------------------


def test_to_env_action_rescales_and_clips():
    env = counter_env(4, low=(-2.0,), high=(2.0,))
    agent = jnp.asarray([[0.5], [-1.0], [1.0], [0.0], [-0.5], [3.0], [-7.0], [1.0001]])
    expected = np.asarray([[1.0], [-2.0], [2.0], [0.0], [-1.0], [2.0], [-2.0], [2.0]])
    np.testing.assert_allclose(env.to_env_action(agent), expected, atol=1e-6)


def test_to_env_action_is_per_dimension():
    env = counter_env(4, low=(0.0, -1.0), high=(10.0, 3.0))
    agent = jnp.asarray([[0.0, 0.0], [1.0, -1.0], [-1.0, 1.0], [0.5, -0.5], [5.0, -5.0]])
    expected = np.asarray([[5.0, 1.0], [10.0, -1.0], [0.0, 3.0], [7.5, 0.0], [10.0, -1.0]])
    np.testing.assert_allclose(env.to_env_action(agent), expected, atol=1e-6)


def test_step_applies_the_rescaled_action():
    env = counter_env(10)
    step, reset = jitted(env)
    state = reset(jax.random.PRNGKey(0), 4)
    p0 = np.asarray(state.obs[:, 0])
    action = jnp.asarray([[0.5], [-1.0], [3.0], [-0.25]])
    _, result = host(step(state, action))
    moved = p0 + np.asarray([1.0, -2.0, 2.0, -0.5])
    np.testing.assert_allclose(result.next_obs[:, 0], moved, atol=1e-6)
    np.testing.assert_allclose(result.reward, moved, atol=1e-6)


# Reset -----------------------------------------------------------------------------------------


def test_reset_draws_a_fresh_state_per_environment():
    env = counter_env(4)
    _, reset = jitted(env)
    state = host(reset(jax.random.PRNGKey(0), 8))
    positions = state.obs[:, 0]
    assert len(np.unique(positions)) == 8
    assert np.all((positions >= -1.0) & (positions < 1.0))
    np.testing.assert_array_equal(state.obs[:, 1], 0.0)
    np.testing.assert_array_equal(state.steps, 0)
    np.testing.assert_array_equal(state.episode_return, 0.0)
    assert len({tuple(k) for k in state.key}) == 8  # every environment has its own key
    # ... and not the key its initial state was drawn from (that would repeat the start).
    redrawn = np.asarray(jax.vmap(env.reset_fn)(jnp.asarray(state.key))[1])
    assert not np.any(np.all(redrawn == state.obs, axis=-1))
    assert state.obs.dtype == np.float32 and state.steps.dtype == np.int32
    # Deterministic in the key, different for another key.
    np.testing.assert_array_equal(host(reset(jax.random.PRNGKey(0), 8)).obs, state.obs)
    assert not np.any(host(reset(jax.random.PRNGKey(1), 8)).obs[:, 0] == positions)


# Truncation --------------------------------------------------------------------------------


def test_truncation_exactly_at_episode_length():
    n, length = 3, 4
    env = counter_env(length)
    step, reset = jitted(env)
    state = reset(jax.random.PRNGKey(3), n)
    p0 = np.asarray(state.obs[:, 0])
    # Agent actions 0.25, -0.25, 0.5, 0 are env actions 0.5, -0.5, 1, 0; positions (= rewards)
    # p0 + 0.5, p0, p0 + 1, p0 + 1; the return is 4 p0 + 2.5.
    agent_actions = [0.25, -0.25, 0.5, 0.0]
    positions = [p0 + 0.5, p0, p0 + 1.0, p0 + 1.0]
    for t in range(length):
        state, result = step(state, const_action(n, agent_actions[t]))
        state, result = host(state), host(result)
        np.testing.assert_allclose(result.reward, positions[t], atol=1e-6)
        np.testing.assert_array_equal(result.terminated, False)
        if t < length - 1:
            np.testing.assert_array_equal(result.truncated, False)
            np.testing.assert_array_equal(state.steps, t + 1)
            np.testing.assert_allclose(state.episode_return, sum(positions[: t + 1]), atol=1e-5)
            # No episode ended: the state continues from the step's observation.
            np.testing.assert_array_equal(state.obs, result.next_obs)
    # The time limit: truncated, not terminated.
    np.testing.assert_array_equal(result.truncated, True)
    np.testing.assert_array_equal(result.finished_length, length)
    np.testing.assert_allclose(result.finished_return, 4 * p0 + 2.5, atol=1e-5)
    # next_obs is the true last observation [p0 + 1, 4] ...
    np.testing.assert_allclose(result.next_obs[:, 0], p0 + 1.0, atol=1e-6)
    np.testing.assert_array_equal(result.next_obs[:, 1], 4.0)
    # ... while the state already holds a fresh first observation of the next episode.
    np.testing.assert_array_equal(state.obs[:, 1], 0.0)
    assert np.all((state.obs[:, 0] >= -1.0) & (state.obs[:, 0] < 1.0))
    assert not np.any(state.obs[:, 0] == p0), "reset must not reuse the first initial state"
    np.testing.assert_array_equal(state.inner["count"], 0)
    np.testing.assert_array_equal(state.inner["position"], state.obs[:, 0])
    np.testing.assert_array_equal(state.steps, 0)
    np.testing.assert_array_equal(state.episode_return, 0.0)


def test_consecutive_resets_use_fresh_keys():
    n, length = 6, 2
    env = counter_env(length)
    step, reset = jitted(env)
    state = reset(jax.random.PRNGKey(5), n)
    starts = [np.asarray(state.obs[:, 0])]
    for _ in range(4):  # four episodes of two zero-action steps
        for t in range(length):
            before = state
            state, result = step(state, const_action(n, 0.0))
            result = host(result)
            assert bool(np.all(result.truncated)) == (t == length - 1)
        # No key is used twice: neither the ended episode's key nor the new one redraws the start.
        for key in (before.key, state.key):
            redrawn = np.asarray(jax.vmap(env.reset_fn)(key)[1])
            assert not np.any(np.all(redrawn == np.asarray(state.obs), axis=-1))
        np.testing.assert_allclose(result.finished_return, 2 * starts[-1], atol=1e-6)
        starts.append(np.asarray(state.obs[:, 0]))
    starts = np.stack(starts)  # [episodes, envs]
    for env_index in range(n):
        # Every episode of an environment starts somewhere new (never a cached start) ...
        assert len(np.unique(starts[:, env_index])) == len(starts)
    for episode in range(len(starts)):
        # ... and environments resetting together reset to different states.
        assert len(np.unique(starts[episode])) == n


# Termination ----------------------------------------------------------------------------------


@pytest.mark.parametrize("length", [3, 10])
def test_termination(length):
    # Env action +2 per step from p0 in [-1, 1): p0 + 2, p0 + 4 (<= 5), p0 + 6 > 5: terminated
    # at step 3, which is also the time limit for length 3: a termination, not a truncation.
    n = 4
    env = counter_env(length)
    step, reset = jitted(env)
    state = reset(jax.random.PRNGKey(7), n)
    p0 = np.asarray(state.obs[:, 0])
    for t in range(3):
        state, result = host(step(state, const_action(n, 1.0)))
        np.testing.assert_array_equal(result.terminated, t == 2)
        np.testing.assert_array_equal(result.truncated, False)
    np.testing.assert_array_equal(result.finished_length, 3)
    np.testing.assert_allclose(result.finished_return, 3 * p0 + 12.0, atol=1e-5)
    np.testing.assert_allclose(result.next_obs[:, 0], p0 + 6.0, atol=1e-6)
    np.testing.assert_array_equal(result.next_obs[:, 1], 3.0)
    assert np.all(np.abs(state.obs[:, 0]) < 1.0)
    np.testing.assert_array_equal(state.obs[:, 1], 0.0)
    np.testing.assert_array_equal(state.steps, 0)
    np.testing.assert_array_equal(state.episode_return, 0.0)
    assert result.terminated.dtype == np.bool_ and result.truncated.dtype == np.bool_


def test_only_the_finished_environments_reset():
    # Env 0 pushes +2 per step (terminates at step 3); env 1 stands still (truncated at 5).
    env = counter_env(5)
    step, reset = jitted(env)
    state = reset(jax.random.PRNGKey(11), 2)
    p0 = np.asarray(state.obs[:, 0])
    action = jnp.asarray([[1.0], [0.0]])
    ended_at = {}
    for t in range(1, 7):
        state, result = host(step(state, action))
        for i in np.flatnonzero(result.terminated | result.truncated):
            ended_at.setdefault(int(i), (t, bool(result.terminated[i]), result))
        if t == 3:
            assert result.terminated.tolist() == [True, False]
            # Env 1 carries on: same observation, its step count and return keep growing.
            np.testing.assert_array_equal(state.obs[1], result.next_obs[1])
            np.testing.assert_allclose(state.obs[1], [p0[1], 3.0], atol=1e-6)
            assert state.steps.tolist() == [0, 3]
            np.testing.assert_allclose(state.episode_return[1], 3 * p0[1], atol=1e-5)
    t0, terminated0, _ = ended_at[0]
    t1, terminated1, result1 = ended_at[1]
    assert (t0, terminated0) == (3, True)
    assert (t1, terminated1) == (5, False)
    assert result1.truncated.tolist() == [False, True]
    assert result1.finished_length[1] == 5
    np.testing.assert_allclose(result1.finished_return[1], 5 * p0[1], atol=1e-5)
    # At step 5 env 0 is two steps into its second episode and was not reset again.
    assert not result1.terminated[0] and not result1.truncated[0]
    assert result1.finished_length[0] == 2


def _random_rollout(env, n, steps, seed, **step_kwargs):
    """States and results of ``steps`` steps with per-environment random actions."""
    step = jax.jit(functools.partial(envs.step, env, **step_kwargs))
    state = envs.reset(env, jax.random.PRNGKey(seed), n)
    keys = jax.random.split(jax.random.PRNGKey(seed + 1), steps)
    history = []
    for key in keys:
        state, result = step(state, jax.random.uniform(key, (n, 1), minval=-1.0, maxval=1.0))
        history.append(host((state, result)))
    return history


def test_resetting_a_few_environments_equals_resetting_the_batch():
    # Random walks terminating at |position| > 5, time limit 6: on some steps no episode ends,
    # on some one, on others more than 5 (several reset rounds for every setting below).
    # Every reset_slots setting must give the same trajectories as always resetting the batch.
    env, n = counter_env(6, low=(-3.0,), high=(3.0,)), 16
    reference = _random_rollout(env, n, 30, seed=2, reset_slots=n)
    counts = [int(np.sum(r.terminated | r.truncated)) for _, r in reference]
    assert 0 in counts and 1 in counts and max(counts) > 5, counts
    for slots, groups in ((1, 1), (2, 1), (5, 1), (1, 4), (2, 2)):
        rollout = _random_rollout(env, n, 30, seed=2, reset_slots=slots, groups=groups)
        for (state, result), (ref_state, ref_result) in zip(rollout, reference, strict=True):
            np.testing.assert_array_equal(state.obs, ref_state.obs)
            np.testing.assert_array_equal(state.inner["position"], ref_state.inner["position"])
            np.testing.assert_array_equal(state.steps, ref_state.steps)
            np.testing.assert_array_equal(result.next_obs, ref_result.next_obs)


def test_reset_rounds_under_vmap_equal_each_member_alone():
    # Members end different numbers of episodes on the same step; with the count reduced over
    # the member axis each member still gets exactly its own resets.
    env, n = counter_env(7, low=(-4.0,), high=(4.0,)), 8
    seeds = jnp.asarray([3, 4, 5])

    def rollout(seed, axis_name=None):
        state = envs.reset(env, jax.random.PRNGKey(seed), n)

        def body(state, key):
            action = jax.random.uniform(key, (n, 1), minval=-1.0, maxval=1.0)
            state, result = envs.step(env, state, action, axis_name, reset_slots=2)
            return state, (state.obs, result.terminated | result.truncated)

        keys = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(0), seed), 20)
        return jax.lax.scan(body, state, keys)[1]

    together = host(jax.jit(jax.vmap(lambda s: rollout(s, "m"), axis_name="m"))(seeds))
    ended_counts = together[1].sum(axis=2)  # [members, steps]
    assert np.any(ended_counts.min(axis=0) != ended_counts.max(axis=0))
    for i, seed in enumerate(seeds):
        alone = host(jax.jit(rollout)(seed))
        np.testing.assert_array_equal(together[0][i], alone[0])


def test_without_auto_reset_ended_environments_carry_on():
    # Env +2 per step terminates at step 3 (position p0 + 6); without resets the next step
    # continues from there (p0 + 8) while the episode bookkeeping restarts.
    env, n = counter_env(10), 3
    step = jax.jit(functools.partial(envs.step, env, auto_reset=False))
    state = envs.reset(env, jax.random.PRNGKey(9), n)
    p0 = np.asarray(state.obs[:, 0])
    for _ in range(3):
        state, result = host(step(state, const_action(n, 1.0)))
    assert result.terminated.all()
    np.testing.assert_allclose(state.obs[:, 0], p0 + 6.0, atol=1e-6)
    np.testing.assert_array_equal(state.steps, 0)
    state, result = host(step(state, const_action(n, 1.0)))
    np.testing.assert_allclose(result.next_obs[:, 0], p0 + 8.0, atol=1e-6)
    np.testing.assert_array_equal(result.finished_length, 1)  # still past 5: ends again


def test_step_keys_are_fresh_per_environment_and_step():
    def reset_fn(key):
        del key
        return jnp.zeros(()), jnp.zeros((1,))

    def step_fn(inner, action, key):
        noise = jax.random.uniform(key, ())
        return inner, noise[None], noise, jnp.asarray(False)

    env = Environment("test/noise", 1, 1, 100, -np.ones(1), np.ones(1), reset_fn, step_fn)
    step, reset = jitted(env)
    state = reset(jax.random.PRNGKey(0), 5)
    draws = []
    for _ in range(3):
        state, result = step(state, jnp.zeros((5, 1)))
        draws.append(np.asarray(result.reward))
    assert len(np.unique(np.concatenate(draws))) == 15


# gymnax Pendulum -------------------------------------------------------------------------------

PENDULUM_ENVS, PENDULUM_STEPS = 4, 210


@pytest.fixture(scope="module")
def pendulum():
    """A 210-step rollout of 4 Pendulums, with gymnax's own step of the same states alongside."""
    import gymnax

    env = envs.make("gymnax/Pendulum-v1")
    reference, params = gymnax.make("Pendulum-v1")

    def rollout(key):
        reset_key, action_key, dummy_key = jax.random.split(key, 3)
        state = envs.reset(env, reset_key, PENDULUM_ENVS)
        # Mostly inside [-1, 1] (so rescaling matters), some beyond (so clipping matters).
        actions = jax.random.uniform(
            action_key, (PENDULUM_STEPS, PENDULUM_ENVS, 1), minval=-1.3, maxval=1.3
        )
        dummy_keys = jax.random.split(dummy_key, PENDULUM_ENVS)

        def body(state, action):
            # gymnax's own step of the same inner state, with the action rescaled by hand.
            torque = 2.0 * jnp.clip(action, -1.0, 1.0)
            ref_obs, _, ref_reward, _, _ = jax.vmap(reference.step_env, in_axes=(0, 0, 0, None))(
                dummy_keys, state.inner, torque, params
            )
            new_state, result = envs.step(env, state, action)
            out = dict(
                obs=state.obs,
                torque=torque[:, 0],
                result=result,
                ref_obs=ref_obs,
                ref_reward=ref_reward,
                new_obs=new_state.obs,
                new_steps=new_state.steps,
                new_return=new_state.episode_return,
                new_time=new_state.inner.time,
            )
            return new_state, out

        return jax.lax.scan(body, state, actions)[1]

    return env, host(jax.jit(rollout)(jax.random.PRNGKey(42)))


def test_pendulum_spec(pendulum):
    env, _ = pendulum
    assert env.name == "gymnax/Pendulum-v1"
    assert (env.observation_size, env.action_size, env.episode_length) == (3, 1, 200)
    np.testing.assert_array_equal(env.action_low, [-2.0])
    np.testing.assert_array_equal(env.action_high, [2.0])


def test_pendulum_is_only_truncated_at_200(pendulum):
    _, out = pendulum
    result = out["result"]
    assert not result.terminated.any()
    truncated_steps = np.flatnonzero(result.truncated.any(axis=1))
    assert truncated_steps.tolist() == [199]
    assert result.truncated[199].all()
    np.testing.assert_array_equal(result.finished_length[199], 200)
    np.testing.assert_allclose(
        result.finished_return[199], result.reward[:200].sum(axis=0), rtol=1e-4
    )
    # After the time limit: counters, return and gymnax's own clock start again from 0.
    np.testing.assert_array_equal(out["new_steps"][199], 0)
    np.testing.assert_array_equal(out["new_return"][199], 0.0)
    np.testing.assert_array_equal(out["new_time"][199], 0)
    np.testing.assert_array_equal(out["new_steps"][209], 10)
    np.testing.assert_array_equal(out["new_time"][209], 10)


def test_pendulum_matches_gymnax(pendulum):
    _, out = pendulum
    result = out["result"]
    # The same rewards and observations as gymnax's step_env with the rescaled action ...
    np.testing.assert_allclose(result.reward, out["ref_reward"], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(result.next_obs, out["ref_obs"], rtol=1e-6, atol=1e-6)
    # ... and as the Pendulum reward written out: -(theta^2 + 0.1 theta_dot^2 + 0.001 u^2),
    # theta and theta_dot read off the observation [cos, sin, theta_dot] the action was taken in.
    cos, sin, theta_dot = out["obs"][..., 0], out["obs"][..., 1], out["obs"][..., 2]
    theta = np.arctan2(sin, cos)
    expected = -(theta**2 + 0.1 * theta_dot**2 + 0.001 * out["torque"] ** 2)
    np.testing.assert_allclose(result.reward, expected, rtol=1e-4, atol=1e-4)


def test_pendulum_truncation_keeps_the_last_observation(pendulum):
    _, out = pendulum
    result = out["result"]
    # At the limit next_obs is gymnax's observation of the last step, the state's is a reset one.
    np.testing.assert_allclose(result.next_obs[199], out["ref_obs"][199], rtol=1e-6, atol=1e-6)
    assert not np.any(np.all(out["new_obs"][199] == result.next_obs[199], axis=-1))
    assert not np.any(np.all(out["new_obs"][199] == out["obs"][0], axis=-1))
    # The next step starts from that reset observation.
    np.testing.assert_array_equal(out["obs"][200], out["new_obs"][199])
    # Elsewhere the state continues from next_obs.
    np.testing.assert_array_equal(out["new_obs"][:199], result.next_obs[:199])


# Brax inverted pendulum (MJX) ------------------------------------------------------------------

BRAX_ENVS, BRAX_STEPS = 16, 40


@pytest.fixture(scope="module")
def brax_rollout():
    """One shared 40-step rollout of 16 inverted pendulums under random bang-bang actions.

    MJX on CPU is slow: the reset and the step are each compiled once for the whole module.
    """
    env = envs.make("brax/inverted_pendulum")
    reset = jax.jit(functools.partial(envs.reset, env), static_argnums=1)
    step = jax.jit(functools.partial(envs.step, env))
    # Put the initial state on the device explicitly (as td3_jax.runner.run does). Eager reset
    # outputs are *uncommitted* arrays while the jitted step's outputs are committed, and that
    # difference alone would cost the step a second compile. Note that jax.device_put(x) with
    # no device leaves arrays uncommitted: the device has to be named.
    state = jax.device_put(reset(jax.random.PRNGKey(0), BRAX_ENVS), jax.devices()[0])
    initial = state
    signs = jax.random.rademacher(jax.random.PRNGKey(1), (BRAX_STEPS, BRAX_ENVS, 1), jnp.float32)
    steps = []
    for t in range(BRAX_STEPS):
        previous = state
        state, result = step(state, signs[t])
        steps.append(host(dict(obs=previous.obs, result=result, state=state)))
    return dict(
        env=env,
        initial=initial,
        final=state,
        steps=steps,
        cache_size=step._cache_size(),
    )


@pytest.mark.mjx
def test_brax_spec(brax_rollout):
    env = brax_rollout["env"]
    assert env.name == "brax/inverted_pendulum"
    assert (env.observation_size, env.action_size, env.episode_length) == (4, 1, 1000)
    np.testing.assert_array_equal(env.action_low, [-1.0])
    np.testing.assert_array_equal(env.action_high, [1.0])


@pytest.mark.mjx
def test_brax_step_compiles_once(brax_rollout):
    # The step was fed its own output 40 times; a state whose types drift (weak types, dtypes,
    # commitment) between reset and step would have been compiled again.
    assert brax_rollout["cache_size"] == 1

    def kind(x):
        t = jax.typeof(x)
        return t.shape, t.dtype, t.weak_type

    initial, final = brax_rollout["initial"], brax_rollout["final"]
    assert jax.tree.structure(initial) == jax.tree.structure(final)
    assert [kind(x) for x in jax.tree.leaves(initial)] == [kind(x) for x in jax.tree.leaves(final)]


@pytest.mark.mjx
def test_brax_falling_pole_terminates(brax_rollout):
    terminated = np.stack([s["result"].terminated for s in brax_rollout["steps"]])
    truncated = np.stack([s["result"].truncated for s in brax_rollout["steps"]])
    assert not truncated.any()  # episode_length 1000
    assert terminated.any(axis=0).all(), "every pole should fall under bang-bang actions"
    assert terminated.sum() >= BRAX_ENVS * 2  # and fall again after its reset


@pytest.mark.mjx
def test_brax_episode_bookkeeping(brax_rollout):
    # An independent count of each environment's steps since its last reset.
    count = np.zeros(BRAX_ENVS, np.int64)
    ret = np.zeros(BRAX_ENVS, np.float64)
    for record in brax_rollout["steps"]:
        result, state = record["result"], record["state"]
        count += 1
        ret += result.reward
        ended = result.terminated | result.truncated
        np.testing.assert_array_equal(result.finished_length[ended], count[ended])
        np.testing.assert_allclose(result.finished_return[ended], ret[ended], rtol=1e-5)
        # The pole is rewarded 1 per step alive, so the return equals the length.
        np.testing.assert_allclose(result.reward, 1.0)
        count[ended], ret[ended] = 0, 0.0
        np.testing.assert_array_equal(state.steps, count)
        np.testing.assert_allclose(state.episode_return, ret, rtol=1e-5)


@pytest.mark.mjx
def test_brax_terminal_observation_is_the_fallen_pole(brax_rollout):
    # Brax's inverted pendulum: obs = [cart, angle, cart velocity, angle velocity], terminated
    # when |angle| > 0.2; a reset starts within 0.01 of upright and at rest.
    seen = 0
    for record in brax_rollout["steps"]:
        result, state = record["result"], record["state"]
        done = result.terminated
        np.testing.assert_array_equal(done, np.abs(result.next_obs[:, 1]) > 0.2)
        np.testing.assert_array_equal(state.obs[~done], result.next_obs[~done])
        if done.any():
            seen += int(done.sum())
            assert np.all(np.abs(state.obs[done]) <= 0.0101)
            fresh = state.obs[done]
            assert len({tuple(o) for o in fresh}) == len(fresh)  # different fresh states
            assert not np.any(np.all(fresh == brax_rollout["steps"][0]["obs"][done], axis=-1))
    assert seen > 0


# Names ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "source"),
    [("nope/x", None), ("brax/nope", "brax"), ("gymnax/CartPole-v1", "gymnax"),
     ("gymnax", "gymnax")],
)  # fmt: skip
def test_unknown_environment(name, source):
    """Nothing close: a known source's own names, else how names look; never all of them."""
    with pytest.raises(UnknownEnvironmentError) as err:
        envs.make(name)
    message = str(err.value)
    assert repr(name) in message and "`td3-jax envs` lists all" in message
    if source is None:
        assert "SOURCE/NAME" in message and "brax/ant" not in message
    else:
        own = [n.split("/", 1)[1] for n in envs.known_names() if n.startswith(source + "/")]
        assert f"{source} has " in message and all(n in message for n in own)
        others = [n for n in envs.known_names() if not n.startswith(source + "/")]
        assert not any(n in message for n in others)
    assert isinstance(err.value, ValueError)


@pytest.mark.parametrize(
    ("name", "meant"),
    [("Pendulum-v1", "gymnax/Pendulum-v1"), ("brax/Ant", "brax/ant"),
     ("brax/humaniod", "brax/humanoid"), ("gymnax/pendulum-v1", "gymnax/Pendulum-v1")],
)  # fmt: skip
def test_a_mistyped_environment_gets_the_name_it_meant(name, meant):
    with pytest.raises(UnknownEnvironmentError) as err:
        envs.make(name)
    message = str(err.value)
    assert f"did you mean {meant}" in message, message
    assert "brax/inverted_pendulum" not in message  # no full listing when a guess exists


def test_a_task_under_another_source_gets_its_own_name_first():
    """A task given under the wrong source is named under its own first, also where the
    wrong source has a close spelling (brax/humanoid for brax/HumanoidRun)."""
    pytest.importorskip("mujoco_playground")
    cases = {"brax/HumanoidRun": "playground/HumanoidRun",
             "playground/humanoid": "brax/humanoid", "gymnax/ant": "brax/ant"}  # fmt: skip
    for name, meant in cases.items():
        with pytest.raises(UnknownEnvironmentError) as err:
            envs.make(name)
        assert f"did you mean {meant}" in str(err.value), str(err.value)


def test_known_names():
    names = envs.known_names()
    assert "brax/inverted_pendulum" in names and "gymnax/MountainCarContinuous-v0" in names
    assert all(n.count("/") == 1 for n in names)


# MuJoCo Playground -----------------------------------------------------------------------------

SLOW = pytest.mark.skipif(
    os.environ.get("TD3_JAX_SLOW") != "1",
    reason="compiling a Playground MJX step takes ~30 s on CPU; set TD3_JAX_SLOW=1",
)


@pytest.fixture(scope="module")
def cheetah():
    pytest.importorskip("mujoco_playground")
    return envs.make("playground/CheetahRun")


def test_playground_cheetah_spec(cheetah):
    assert cheetah.name == "playground/CheetahRun"
    assert "playground/CheetahRun" in envs.known_names()
    assert (cheetah.observation_size, cheetah.action_size, cheetah.episode_length) == (17, 6, 1000)
    np.testing.assert_array_equal(cheetah.action_low, -np.ones(6))
    np.testing.assert_array_equal(cheetah.action_high, np.ones(6))


@SLOW
def test_playground_cheetah_reset_and_step(cheetah):
    def reset_and_step(key):
        state = envs.reset(cheetah, key, 2)
        return state, *envs.step(cheetah, state, jnp.full((2, 6), 0.5))

    state, new_state, result = host(jax.jit(reset_and_step)(jax.random.PRNGKey(0)))
    assert state.obs.shape == (2, 17) and result.next_obs.shape == (2, 17)
    assert not np.array_equal(state.obs[0], state.obs[1])
    assert np.all(np.isfinite(result.next_obs)) and np.all(np.isfinite(result.reward))
    assert not result.terminated.any() and not result.truncated.any()
    np.testing.assert_array_equal(new_state.steps, 1)
    np.testing.assert_array_equal(new_state.obs, result.next_obs)


# MuJoCo Warp's shape of state: leaves kept once for the whole batch ----------------------------


def test_auto_reset_leaves_a_shared_leaf_alone_and_resets_the_rest():
    """MuJoCo Warp keeps its contact buffer and counters once for all the environments stepped
    together (no batch axis). The auto-reset must reset every per-environment leaf of the ended
    environments exactly as without the shared leaf, and keep the shared one as stepped."""
    plain = counter_env(episode_length=3)
    shared_size = 7  # neither the batch (4) nor a reset round's size

    def reset_fn(key):  # a reset makes its own (zero) buffer, as Warp's make_data does
        inner, obs = plain.reset_fn(key)
        return (inner, jnp.zeros((shared_size,))), obs

    env = dataclasses.replace(plain, reset_fn=reset_fn)
    batch = 4
    state = envs.reset(plain, jax.random.PRNGKey(0), batch)
    stepped, _ = envs.step(plain, state, const_action(batch, 0.5))
    shared = jnp.arange(shared_size, dtype=jnp.float32)  # a leaf without the batch axis
    keys = jax.random.split(jax.random.PRNGKey(1), batch)
    ended = jnp.array([True, False, True, False])
    inner, obs = envs.reset_ended(env, ended, keys, (stepped.inner, shared), stepped.obs)
    expected_inner, expected_obs = envs.reset_ended(plain, ended, keys, stepped.inner,
                                                    stepped.obs)  # fmt: skip
    np.testing.assert_array_equal(np.asarray(inner[1]), np.asarray(shared))
    for a, b in zip(jax.tree.leaves(inner[0]), jax.tree.leaves(expected_inner), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(np.asarray(obs), np.asarray(expected_obs))
    assert not np.array_equal(np.asarray(obs[0]), np.asarray(stepped.obs[0]))  # it did reset


def test_a_physics_overflow_is_reported_per_environment_and_step():
    """Environment.overflow_fn marks the environments whose physics ran out of a buffer; the
    step's result carries it (all false without one)."""
    plain = counter_env(episode_length=10)
    env = dataclasses.replace(plain, overflow_fn=lambda inner: inner["position"] > 0.0)
    state = envs.reset(env, jax.random.PRNGKey(3), 4)
    stepped, result = envs.step(env, state, const_action(4, 0.25))
    np.testing.assert_array_equal(np.asarray(result.overflow),
                                  np.asarray(stepped.inner["position"] > 0.0))  # fmt: skip
    _, quiet = envs.step(plain, state, const_action(4, 0.25))
    assert not np.asarray(quiet.overflow).any()


def test_the_physics_choice_and_its_errors(monkeypatch):
    """Warp where it can run (warp importable and an NVIDIA GPU), else JAX; an explicit
    --impl warp where it cannot is one message naming what is missing."""
    from td3_jax.envs import physics

    monkeypatch.delenv(physics.WARP_ON_CPU, raising=False)
    assert jax.default_backend() == "cpu"
    assert "NVIDIA GPU" in physics.warp_missing()
    assert physics.resolve(None) == "jax" and physics.resolve("jax") == "jax"
    with pytest.raises(ValueError, match="--impl warp: MuJoCo Warp needs an NVIDIA GPU"):
        physics.resolve("warp")
    with pytest.raises(ValueError, match="unknown --impl 'mjx'"):
        physics.resolve("mjx")
    real_find = physics.importlib.util.find_spec
    monkeypatch.setattr(physics.importlib.util, "find_spec",
                        lambda name: None if name == "warp" else real_find(name))  # fmt: skip
    assert "pip install 'td3-jax[warp]'" in physics.warp_missing()
    # Warp's contact buffer: Playground's tasks size it for 8192 environments (8 each for T1
    # and G1: 65536); td3-jax sizes it for the environments stepped together.
    assert physics.contact_capacity(65536, 4096, None) == 65536
    assert physics.contact_capacity(65536, 3 * 8192, None) == 8 * 3 * 8192
    assert physics.contact_capacity(65536, 1000, 20) == 20_000
    # The overflow flags that mean wrong physics: all but the iteration limits (bits 9, 10).
    assert physics.WRONG_PHYSICS & (1 << 0) and physics.WRONG_PHYSICS & (1 << 3)
    assert not physics.WRONG_PHYSICS & ((1 << 9) | (1 << 10))


def test_a_playground_task_without_playground_installed_names_the_extra_not_an_unknown_name(
    monkeypatch,
):
    """Without MuJoCo Playground no playground name can be checked: the message says what
    to install instead of calling a right name unknown."""
    from td3_jax.envs import playground

    monkeypatch.setattr(playground, "names", lambda: [])
    with pytest.raises(UnknownEnvironmentError) as err:
        envs.check_name("playground/CheetahRun")
    assert str(err.value) == (
        "environment 'playground/CheetahRun' needs MuJoCo Playground, which is not installed: "
        "pip install 'td3-jax[playground]', or 'td3-jax[locomotion]' for its robots (T1, G1, "
        "Go1 and the other locomotion tasks) (`td3-jax envs` lists all of them)"
    )
