"""The compiled training program: ``chunk(train_state) -> (train_state, metrics)``.

One chunk is a ``jax.lax.scan`` over iterations of {act in every environment, step them all,
write the transitions to the ring buffer, take ``updates_per_iter`` gradient updates}. Nothing in
it touches the host. :func:`make_trainer` builds the pure pieces for a config; the host loop in
:mod:`td3_jax.run` only calls them, logs, evaluates and checkpoints. Because every piece is a
pure function of the :class:`TrainState` pytree, seeds are a ``jax.vmap`` over it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from td3_jax import envs, n_step, noise, normalization, replay
from td3_jax.config import TrainConfig
from td3_jax.td3 import ddpg, td3
from td3_jax.types import Agent, AgentState, Transition


@struct.dataclass
class TrainState:
    """The whole state of a run; checkpointing it is enough to resume exactly."""

    agent: AgentState
    # data (Transition, ended): leaves [replay_shards, capacity / replay_shards, ...]
    buffer: replay.ReplayBuffer
    env_state: envs.EnvState
    obs_stats: normalization.RunningStats
    ou_state: noise.OUState
    key: jax.Array
    env_steps: jax.Array  # int32 transitions collected so far (summed over environments)
    iteration: jax.Array  # int32 iterations done


class Trainer(NamedTuple):
    """Pure functions of one configuration.

    Attributes:
      env: the environment.
      agent: the TD3/DDPG agent.
      init: ``init(key) -> TrainState``.
      chunk: ``chunk(state) -> (state, metrics)``: ``config.iters_per_chunk`` iterations.
      evaluate: ``evaluate(state, key) -> returns[eval_envs]``: one deterministic episode per
        evaluation environment.
      sample: ``sample(buffer, key) -> Transition [batch_size, ...]``: one training batch as the
        updates draw it (n-step folded when ``n_step > 1``; observations not yet normalised).
    """

    config: TrainConfig
    env: envs.Environment
    agent: Agent
    init: Callable[[jax.Array], TrainState]
    chunk: Callable[[TrainState], tuple[TrainState, dict[str, jax.Array]]]
    evaluate: Callable[[TrainState, jax.Array], jax.Array]
    sample: Callable[[replay.ReplayBuffer, jax.Array], Transition]


def make_agent(cfg: TrainConfig, env: envs.Environment, axis_name: str | None = None) -> Agent:
    if cfg.algo == "ddpg":
        return ddpg(cfg.agent_config(), env.observation_size, env.action_size)
    return td3(cfg.agent_config(), env.observation_size, env.action_size, axis_name=axis_name)


def make_trainer(
    cfg: TrainConfig,
    env: envs.Environment | None = None,
    axis_name: str | None = None,
    env_groups: int = 1,
) -> Trainer:
    """Builds the pure training pieces for ``cfg`` (the environment is made if not given).

    ``axis_name``: set when the pieces run under ``jax.vmap(..., axis_name=...)`` (seeds); the
    branch conditions (episode resets, learning started) are then reduced over that axis, so
    they stay branches instead of becoming selects that compute both sides.

    ``env_groups``: environments are reset within groups of this many contiguous environments
    (with the batch split over D devices, D keeps every reset on its device); with replay
    slices that the groups divide, the slices are the groups. Results do not depend on it.
    """
    env = env or envs.make(cfg.env, backend=cfg.env_backend, episode_length=cfg.episode_length)
    agent = make_agent(cfg, env, axis_name)
    ou_params = cfg.ou_params()
    num_envs, batch_size = cfg.num_envs, cfg.batch_size

    shards = cfg.replay_shards
    reset_groups = shards if shards % env_groups == 0 else env_groups  # envs.step checks it

    def group_by_shard(tree):
        """``[num_envs, ...] -> [shards, num_envs / shards, ...]``: env group g fills slice g."""
        return jax.tree.map(lambda x: x.reshape(shards, -1, *x.shape[1:]), tree)

    # Every add writes one row per environment of a slice, so in a slice row i + stride is the
    # next step of row i's environment: n-step runs are read straight from the ring.
    stride = num_envs // shards
    run_span = (cfg.n_step - 1) * stride

    def sample_slice(buffer, key):
        """``batch_size / shards`` uniform transitions of one slice, n-step folded (a run of
        one step folds to the transition itself)."""
        run, ended = replay.sample_runs(buffer, key, batch_size // shards, cfg.n_step, stride)
        return n_step.fold(run, ended, cfg.discount)

    def sample(buffer, key):
        """``batch_size / shards`` transitions from every slice, as one ``[batch_size]`` batch."""
        keys = key[None] if shards == 1 else jax.random.split(key, shards)
        rows = jax.vmap(sample_slice)(buffer, keys)
        return jax.tree.map(lambda x: x.reshape(batch_size, *x.shape[2:]), rows)

    def normalize(stats, obs):
        return normalization.normalize(stats, obs) if cfg.normalize_obs else obs

    def init(key: jax.Array) -> TrainState:
        agent_key, env_key, key = jax.random.split(key, 3)
        env_state = envs.reset(env, env_key, num_envs)
        example = Transition(
            obs=jnp.zeros((env.observation_size,), jnp.float32),
            action=jnp.zeros((env.action_size,), jnp.float32),
            reward=jnp.zeros((), jnp.float32),
            next_obs=jnp.zeros((env.observation_size,), jnp.float32),
            done=jnp.zeros((), jnp.float32),
        )
        return TrainState(
            agent=agent.init(agent_key),
            buffer=jax.vmap(
                lambda _: replay.init(cfg.replay_capacity // shards, (example, jnp.zeros((), bool)))
            )(jnp.arange(shards)),
            env_state=env_state,
            obs_stats=normalization.init(env.observation_size),
            ou_state=jax.vmap(lambda _: noise.ou_init(env.action_size, ou_params))(
                jnp.arange(num_envs)
            ),
            key=key,
            env_steps=jnp.zeros((), jnp.int32),
            iteration=jnp.zeros((), jnp.int32),
        )

    def explore(state: TrainState, key: jax.Array) -> tuple[jax.Array, noise.OUState]:
        """Actions [num_envs, action_size] in [-1, 1]: random during warm-up, noisy policy after."""
        random_key, noise_key = jax.random.split(key)
        obs = normalize(state.obs_stats, state.env_state.obs)
        policy = agent.act(state.agent.actor_params, obs)
        noise_keys = jax.random.split(noise_key, num_envs)
        ou_state = state.ou_state
        if cfg.exploration == "ou":
            ou_state, noisy = jax.vmap(lambda k, s, a: noise.ou_action(k, s, a, ou_params))(
                noise_keys, ou_state, policy
            )
        else:
            noisy = jax.vmap(lambda k, a: noise.gaussian(k, a, cfg.expl_noise))(noise_keys, policy)
        uniform = jax.random.uniform(random_key, policy.shape, minval=-1.0, maxval=1.0)
        action = jnp.where(state.env_steps < cfg.warmup_steps, uniform, noisy)
        return action, ou_state

    def env_step(state: TrainState, _) -> tuple[TrainState, dict[str, jax.Array]]:
        key, act_key = jax.random.split(state.key)
        action, ou_state = explore(state, act_key)
        obs = state.env_state.obs
        env_state, result = envs.step(env, state.env_state, action, axis_name, groups=reset_groups)
        transition = Transition(
            obs=obs,
            action=action,
            reward=result.reward,
            next_obs=result.next_obs,
            done=result.terminated.astype(jnp.float32),
        )
        ended = result.terminated | result.truncated
        stored = group_by_shard((transition, ended))
        state = state.replace(
            buffer=jax.vmap(replay.add)(state.buffer, stored),
            env_state=env_state,
            obs_stats=normalization.update(state.obs_stats, obs),
            ou_state=noise.ou_reset(ou_state, ended[:, None], ou_params),
            key=key,
            env_steps=state.env_steps + num_envs,
        )
        metrics = {
            "episodes": jnp.sum(ended).astype(jnp.float32),
            "return_sum": jnp.sum(jnp.where(ended, result.finished_return, 0.0)),
            "length_sum": jnp.sum(jnp.where(ended, result.finished_length, 0)).astype(jnp.float32),
            "reward_mean": jnp.mean(result.reward),
        }
        return state, metrics

    def updates(agent_state: AgentState, buffer, stats, key) -> tuple[AgentState, dict]:
        """``updates_per_iter`` gradient steps on fresh batches (the buffer is only read)."""

        def gradient_step(agent_state, key):
            sample_key, update_key = jax.random.split(key)
            batch = sample(buffer, sample_key)
            batch = batch._replace(
                obs=normalize(stats, batch.obs), next_obs=normalize(stats, batch.next_obs)
            )
            return agent.update(agent_state, batch, update_key)

        keys = jax.random.split(key, cfg.updates_per_iter)
        agent_state, metrics = jax.lax.scan(gradient_step, agent_state, keys)
        metrics = {k: jnp.sum(v) for k, v in metrics.items()}
        metrics["updates"] = jnp.asarray(cfg.updates_per_iter, jnp.float32)
        return agent_state, metrics

    def no_updates(agent_state: AgentState, buffer, stats, key):
        del buffer, stats, key
        return agent_state, zero_update_metrics

    def iteration(state: TrainState, _) -> tuple[TrainState, dict[str, jax.Array]]:
        state, env_metrics = jax.lax.scan(env_step, state, None, length=cfg.steps_per_iter)
        env_metrics = {
            k: (jnp.mean(v) if k == "reward_mean" else jnp.sum(v)) for k, v in env_metrics.items()
        }
        key, update_key = jax.random.split(state.key)
        stored = jnp.sum(state.buffer.size)
        learning = (
            (state.env_steps >= cfg.warmup_steps)
            & (stored >= batch_size)
            & (jnp.min(state.buffer.size) > run_span)  # every slice holds a whole n-step run
        )
        if axis_name is not None:  # identical for every member: keep it a real branch
            learning = jax.lax.psum(learning.astype(jnp.int32), axis_name) > 0
        if cfg.updates_per_iter > 0:
            agent_state, update_metrics = jax.lax.cond(
                learning,
                updates,
                no_updates,
                state.agent,
                state.buffer,
                state.obs_stats,
                update_key,
            )
        else:
            agent_state, update_metrics = state.agent, zero_update_metrics
        state = state.replace(agent=agent_state, key=key, iteration=state.iteration + 1)
        return state, {**env_metrics, **update_metrics}

    def chunk(state: TrainState) -> tuple[TrainState, dict[str, jax.Array]]:
        state, per_iter = jax.lax.scan(iteration, state, None, length=cfg.iters_per_chunk)
        totals = {k: jnp.sum(v) for k, v in per_iter.items()}
        n_updates = jnp.maximum(totals["updates"], 1.0)
        n_actor = jnp.maximum(totals["actor_updated"], 1.0)
        n_episodes = jnp.maximum(totals["episodes"], 1.0)
        metrics = {
            "critic_loss": totals["critic_loss"] / n_updates,
            "actor_loss": totals["actor_loss"] / n_actor,
            "q_mean": totals["q_mean"] / n_updates,
            "target_mean": totals["target_mean"] / n_updates,
            "chunk_updates": totals["updates"],
            "train_episodes": totals["episodes"],
            "train_return_mean": jnp.where(
                totals["episodes"] > 0, totals["return_sum"] / n_episodes, jnp.nan
            ),
            "train_length_mean": jnp.where(
                totals["episodes"] > 0, totals["length_sum"] / n_episodes, jnp.nan
            ),
            "reward_mean": jnp.mean(per_iter["reward_mean"]),
            "params_finite": _all_finite(state.agent).astype(jnp.float32),
            "env_steps": state.env_steps,
            "agent_steps": state.agent.step,
        }
        return state, metrics

    def evaluate(state: TrainState, key: jax.Array) -> jax.Array:
        env_state = envs.reset(env, key, cfg.eval_envs)

        def body(carry, _):
            env_state, returns, alive = carry
            obs = normalize(state.obs_stats, env_state.obs)
            action = agent.act(state.agent.actor_params, obs)
            # Only each environment's first episode counts: no resets needed.
            env_state, result = envs.step(env, env_state, action, auto_reset=False)
            returns = returns + jnp.where(alive, result.reward, 0.0)
            alive = alive & ~(result.terminated | result.truncated)
            return (env_state, returns, alive), None

        init_carry = (
            env_state,
            jnp.zeros((cfg.eval_envs,), jnp.float32),
            jnp.ones((cfg.eval_envs,), bool),
        )
        (_, returns, _), _ = jax.lax.scan(body, init_carry, None, length=env.episode_length)
        return returns

    # The update metrics' structure, for the branch that skips the updates (agent only: tracing
    # the whole init would trace an environment reset, seconds for MJX).
    key0 = jax.random.PRNGKey(0)
    o, a = env.observation_size, env.action_size
    example_batch = Transition(
        jnp.zeros((batch_size, o)), jnp.zeros((batch_size, a)), jnp.zeros((batch_size,)),
        jnp.zeros((batch_size, o)), jnp.zeros((batch_size,)),
    )  # fmt: skip
    lone = make_agent(cfg, env)  # the same shapes, without the member axis's collectives
    update_shapes = jax.eval_shape(
        lone.update, jax.eval_shape(lone.init, key0), example_batch, key0
    )
    zero_update_metrics = {k: jnp.zeros((), s.dtype) for k, s in update_shapes[1].items()}
    zero_update_metrics["updates"] = jnp.zeros((), jnp.float32)

    return Trainer(cfg, env, agent, init, chunk, evaluate, sample)


def _all_finite(tree: Any) -> jax.Array:
    leaves = [
        jnp.all(jnp.isfinite(x))
        for x in jax.tree.leaves(tree)
        if jnp.issubdtype(x.dtype, jnp.floating)
    ]
    return jnp.all(jnp.stack(leaves))


def make_train(
    cfg: TrainConfig, env: envs.Environment | None = None, axis_name: str | None = None
) -> Callable[[jax.Array], tuple[TrainState, dict[str, jax.Array]]]:
    """The whole run as one pure function ``train(key) -> (final_state, metrics)``.

    ``metrics`` has a leading axis of ``cfg.num_chunks`` (one entry per evaluation) and holds
    the chunk metrics plus ``eval_returns [num_chunks, eval_envs]``. ``jax.vmap(train)(keys)``
    trains one independent agent per key in one program (the purejaxrl shape)::

        train = jax.jit(jax.vmap(make_train(TrainConfig(...))))
        states, metrics = train(jax.random.split(jax.random.PRNGKey(0), 8))

    Unlike ``td3-jax train`` it writes nothing and cannot be resumed; use it inside your own
    programs. Vmapping with ``jax.vmap(train, axis_name=name)`` and ``axis_name=name`` here keeps
    the reset and warm-up branches as real branches (otherwise vmap turns them into selects that
    compute both sides; the numbers are the same either way).
    """
    trainer = make_trainer(cfg, env, axis_name)

    def train(key: jax.Array) -> tuple[TrainState, dict[str, jax.Array]]:
        init_key, eval_key = jax.random.split(key)

        def chunk_and_evaluate(state, index):
            state, metrics = trainer.chunk(state)
            returns = trainer.evaluate(state, jax.random.fold_in(eval_key, index))
            return state, {**metrics, "eval_returns": returns}

        return jax.lax.scan(chunk_and_evaluate, trainer.init(init_key), jnp.arange(cfg.num_chunks))

    return train
