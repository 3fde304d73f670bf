"""The training program as module-level pure functions over a static spec and traced floats.

* :class:`TrainSpec` (static: environment, agent structure, sizes, replay slices, n-step,
  iterations per chunk, the vmapped member axis) and :class:`Hyperparams` (traced floats:
  the agent's learning rates, tau, discount and smoothing noise, and the exploration scales):
  all the program knows of a run's settings. A config becomes them in one place,
  :mod:`td3_jax.config.build` (``build.make_spec(cfg)``, ``build.hyperparams(cfg)``).
* The steps of the loop: :func:`init`, :func:`explore`, :func:`collect` (act in every
  environment, step them, write the ring), :func:`learn` (``updates_per_iter`` gradient
  steps), :func:`iteration`, :func:`chunk` (a loop of iterations, summarised by
  :func:`summarize`) and :func:`evaluate`. With the spec's ``eval_in_chunk``, evaluation
  worlds are stepped inside the chunk instead (:mod:`td3_jax.core.eval_worlds`) and the
  evaluation after a chunk reads their last finished round.
* One driver and one key schedule: :func:`chunk_and_evaluate` is what both the CLI's host
  loop (:mod:`td3_jax.runner.run`) and :func:`make_train` run; the evaluation key after a chunk is
  :func:`evaluation_key` of the state, so ``td3-jax train --seed s`` and
  ``build.make_train(cfg)(key_for_seed(s))`` evaluate alike.

Seeds and sweeps are ``jax.vmap(chunk, in_axes=(None, 0, 0))`` over ``(hp, state)`` with the
spec's ``axis_name`` set (:mod:`td3_jax.core.population`); nothing is rebuilt per member.
"""

from __future__ import annotations

import dataclasses
import functools
import operator
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from td3_jax import envs
from td3_jax.common.axes import any_member
from td3_jax.common.errors import ConfigError
from td3_jax.core import actor_critic as ac
from td3_jax.core import eval_worlds, noise, normalization, replay, return_scale
from td3_jax.core.types import AgentState, Metrics, PRNGKey, Transition
from td3_jax.envs.base import reset_from_keys, reset_keys

#: Folded into a run's key to make its evaluation key (independent of the training draws).
EVAL_KEY_SALT = 1_000_003
#: Folded into a run's key for the first per-environment exploration draws, and into an
#: iteration's action key for the redraws at episode ends (independent of the other draws).
NOISE_KEY_SALT = 1_000_033


@struct.dataclass
class TrainState:
    """The whole state of a run; checkpointing it is enough to resume exactly."""

    agent: AgentState
    # data (Transition, ended): leaves [replay_shards, capacity / replay_shards, ...]
    buffer: replay.ReplayBuffer
    env_state: envs.EnvState
    obs_stats: normalization.RunningStats
    ou_state: noise.OUState
    # [num_envs] uniform draws in [0, 1) placing each environment's exploration std in
    # [expl_noise_min, expl_noise_max]; redrawn where an episode ends (None without them)
    expl_draw: jax.Array | None
    key: jax.Array
    eval_key: jax.Array  # evaluation after chunk c uses fold_in(eval_key, c)
    env_steps: jax.Array  # int32 transitions collected so far (summed over environments)
    iteration: jax.Array  # int32 iterations done
    # with eval_in_chunk: the evaluation worlds' round (env_state then holds
    # num_envs + eval_envs worlds, laid out by TrainSpec.layout); None without
    evaluator: eval_worlds.EvalRound | None = None
    # with scale_rewards: the running return statistics that scale the learner's rewards
    # (:mod:`td3_jax.core.return_scale`); None without
    returns: return_scale.ReturnScale | None = None


@dataclasses.dataclass(frozen=True)
class TrainSpec:
    """The static structure of a training run (everything that shapes the compiled program).

    Attributes:
      env: the environment.
      agent: the agent's structure (:class:`~td3_jax.core.actor_critic.AgentSpec`).
      num_envs, batch_size: global sizes.
      replay_capacity, replay_shards: ring rows in all, and the slices they are split into.
      n_step: steps folded into each sampled transition.
      steps_per_iter, updates_per_iter, iters_per_chunk: the loop's shape.
      warmup_steps: environment steps of uniform random actions before learning starts.
      eval_envs: evaluation episodes (one per environment).
      eval_in_chunk: the evaluation environments are stepped inside the chunk, beside the
        training ones (:mod:`td3_jax.core.eval_worlds`); needs a chunk of at least one episode.
      normalize_obs: observations normalised by running statistics.
      exploration: ``"gaussian"`` or ``"ou"``.
      per_env_noise: Gaussian exploration with a std per environment (:func:`exploration_std`).
      scale_rewards: the learner's rewards are divided by :func:`reward_scale` (running
        return statistics in ``TrainState.returns``).
      reset_groups: environments are reset within this many contiguous groups.
      axis_name: the vmapped member axis (seeds, sweeps), or ``None``.
    """

    env: envs.Environment
    agent: ac.AgentSpec
    num_envs: int
    batch_size: int
    replay_capacity: int
    replay_shards: int
    n_step: int
    steps_per_iter: int
    updates_per_iter: int
    iters_per_chunk: int
    warmup_steps: int
    eval_envs: int
    normalize_obs: bool
    exploration: str
    per_env_noise: bool = False
    scale_rewards: bool = False
    reset_groups: int = 1
    axis_name: str | None = None
    eval_in_chunk: bool = False

    def __post_init__(self) -> None:
        steps, length = self.iters_per_chunk * self.steps_per_iter, self.env.episode_length
        if self.eval_in_chunk and steps < length:
            raise ConfigError(f"eval_in_chunk needs chunks of at least one episode ({length} "
                             f"steps per environment), not {steps}")  # fmt: skip

    @property
    def stride(self) -> int:
        """Rows one vectorised step writes into each replay slice."""
        return self.num_envs // self.replay_shards

    @property
    def layout(self) -> eval_worlds.Layout:
        """Where the training and (with ``eval_in_chunk``) evaluation worlds are in the
        environment batch: one group per replay slice (a setting of the run, so a checkpoint
        resumes on any device count with its worlds where they were)."""
        evaluation = self.eval_envs if self.eval_in_chunk else 0
        return eval_worlds.Layout(self.num_envs, evaluation, self.replay_shards)


@struct.dataclass
class Hyperparams:
    """The run's float settings (scalars; ``[members]`` arrays in a population).

    ``expl_noise_min``, ``expl_noise_max``: the range of the per-environment exploration stds
    (used when the spec's ``per_env_noise``). ``return_bound``: the bound of
    :func:`td3_jax.core.return_scale.scale` (used when the spec's ``scale_rewards``).
    """

    agent: ac.AgentHyperparams
    expl_noise: jax.Array
    ou: noise.OUParams
    expl_noise_min: jax.Array = 0.0
    expl_noise_max: jax.Array = 0.0
    return_bound: jax.Array = 1.0


def key_for_seed(seed: int) -> PRNGKey:
    """The key a run of ``seed`` starts from (``td3-jax train --seed`` uses the same);
    ``ConfigError`` for a seed outside ``[0, 2**32 - 1]``, which JAX would wrap onto another
    seed's key (``-1`` and ``2**32 - 1`` give the same key; a traced seed, as in
    ``jax.vmap(key_for_seed)(seeds)``, is not checked)."""
    if isinstance(seed, float | np.floating):
        raise TypeError(f"seed must be a whole number, got {seed!r}")
    try:
        value = operator.index(seed)  # (ints, NumPy ints, concrete integer arrays of one value)
    except TypeError:  # (a traced seed; anything else is PRNGKey's to refuse)
        value = 0
    if not 0 <= value <= 2**32 - 1:
        raise ConfigError(f"seed {seed} must be in [0, {2**32 - 1}]: JAX's random keys hold 32 "
                         "bits of a seed")  # fmt: skip
    return jax.random.PRNGKey(seed)


def _example_row(spec: TrainSpec) -> tuple[Transition, jax.Array]:
    o, a = spec.env.row_size, spec.env.action_size  # rows: both observations, the actor's once
    z = lambda *shape: jnp.zeros(shape, jnp.float32)
    return Transition(z(o), z(a), z(), z(o), z()), jnp.zeros((), bool)


def _first_draws(spec: TrainSpec, key: PRNGKey) -> jax.Array | None:
    """``[num_envs]`` uniform draws of the per-environment exploration stds (``None`` without
    ``per_env_noise``, so a default run's state keeps its layout and older checkpoints)."""
    if not spec.per_env_noise:
        return None
    return jax.random.uniform(jax.random.fold_in(key, NOISE_KEY_SALT), (spec.num_envs,))


def _first_worlds(spec: TrainSpec, env_key: PRNGKey, eval_key: PRNGKey) -> envs.EnvState:
    """The freshly reset environment batch: ``num_envs`` training worlds drawn from
    ``env_key`` and, with ``eval_in_chunk``, the first evaluation round's worlds (reset in one
    batch; the training worlds are those of a run without them)."""
    keys = reset_keys(env_key, spec.num_envs)
    if spec.eval_in_chunk:
        evaluation = reset_keys(round_key(eval_key, 0), spec.eval_envs)
        join = functools.partial(eval_worlds.join, spec.layout)
        keys = tuple(join(t, e) for t, e in zip(keys, evaluation, strict=True))
    return reset_from_keys(spec.env, keys)


def init(spec: TrainSpec, key: PRNGKey) -> TrainState:
    """A fresh run: new networks, an empty ring, ``num_envs`` freshly reset environments
    (and, with ``eval_in_chunk``, the evaluation worlds' first round)."""
    agent_key, env_key, loop_key = jax.random.split(key, 3)
    eval_key = jax.random.fold_in(key, EVAL_KEY_SALT)
    ou_state = noise.ou_init(spec.env.action_size)
    agent = ac.init(spec.agent, agent_key)
    obs_stats = normalization.init(spec.env.row_size)  # per feature, so per input too
    evaluator = None
    if spec.eval_in_chunk:
        evaluator = eval_worlds.begin(agent.actor_params, obs_stats, spec.eval_envs)
    return TrainState(
        agent=agent,
        buffer=replay.init_slices(spec.replay_capacity, spec.replay_shards, _example_row(spec)),
        env_state=_first_worlds(spec, env_key, eval_key),
        obs_stats=obs_stats,
        ou_state=jax.tree.map(lambda x: jnp.broadcast_to(x, (spec.num_envs, *x.shape)), ou_state),
        expl_draw=_first_draws(spec, key),
        key=loop_key,
        eval_key=eval_key,
        env_steps=jnp.zeros((), jnp.int32),
        iteration=jnp.zeros((), jnp.int32),
        evaluator=evaluator,
        returns=return_scale.init(spec.num_envs) if spec.scale_rewards else None,
    )


def round_key(eval_key: PRNGKey, round_index: jax.Array | int) -> PRNGKey:
    """The key that resets the evaluation worlds of in-chunk round ``round_index`` (the key
    :func:`evaluate` would be given for the same episodes)."""
    return jax.random.fold_in(eval_key, round_index)


def ring_as_saved(abstract_state: Any, layout: list) -> tuple[Any, Callable[[Any], Any] | None]:
    """How to restore a checkpoint whose replay ring has other rows than ``abstract_state``'s: a
    run extended or shortened by ``--resume`` (the ring is capped at the run's length, so it
    never wrapped, and a shortened run still holds every step already taken).

    ``layout``: the checkpoint's ``[path, shape, dtype]`` rows, in leaf order. Returns the
    abstract state with the saved ring's rows and the function that resizes a state restored
    with it to ``abstract_state``'s shapes (:func:`td3_jax.core.replay.resize_slices`); unchanged
    and ``None`` where the rows agree (any other difference is the layout check's).
    """
    paths = [jax.tree_util.keystr(p) for p, _ in
             jax.tree_util.tree_leaves_with_path(abstract_state)]  # fmt: skip
    first = next((i for i, p in enumerate(paths) if p.startswith(".buffer.data")), None)
    if first is None or not isinstance(layout, list) or len(layout) != len(paths):
        return abstract_state, None
    buffer = abstract_state.buffer
    axis, rows = jnp.ndim(buffer.position), replay.slice_rows(buffer)
    saved_shape = list(layout[first][1])
    if len(saved_shape) <= axis or saved_shape[axis] == rows:
        return abstract_state, None
    saved_rows = saved_shape[axis]
    as_saved = lambda x: jax.ShapeDtypeStruct((*x.shape[:axis], saved_rows, *x.shape[axis + 1:]),
                                              x.dtype)  # fmt: skip
    saved = buffer.replace(data=jax.tree.map(as_saved, buffer.data))
    resize = lambda state: state.replace(buffer=replay.resize_slices(state.buffer, rows))
    return abstract_state.replace(buffer=saved), resize


def normalize(spec: TrainSpec, stats: normalization.RunningStats, obs: jax.Array) -> jax.Array:
    """``obs`` normalised by the running statistics when the spec asks for it."""
    return normalization.normalize(stats, obs) if spec.normalize_obs else obs


def policy_action(
    spec: TrainSpec, actor_params: Any, stats: normalization.RunningStats, obs: jax.Array
) -> jax.Array:
    """The deterministic policy's actions ``[n, action_size]`` for observation rows
    ``obs [n, row_size]`` (normalised by ``stats`` where the spec asks; NaN actions as 0)."""
    actor_obs = envs.actor_observation(spec.env, normalize(spec, stats, obs))
    return safe_action(spec.agent.actor.apply(actor_params, actor_obs))


def explore(
    spec: TrainSpec, hp: Hyperparams, state: TrainState, obs: jax.Array, key: PRNGKey
) -> tuple[jax.Array, noise.OUState]:
    """Actions ``[num_envs, action_size]`` in ``[-1, 1]`` for the training worlds' observation
    rows ``obs [num_envs, row_size]``: uniform during warm-up, the noisy policy after (Gaussian
    or OU per environment); returns the new OU states too."""
    random_key, noise_key = jax.random.split(key)
    obs = envs.actor_observation(spec.env, normalize(spec, state.obs_stats, obs))
    policy = spec.agent.actor.apply(state.agent.actor_params, obs)
    noise_keys = jax.random.split(noise_key, spec.num_envs)
    ou_state = state.ou_state
    if spec.exploration == "ou":
        ou_action = lambda k, s, a: noise.ou_action(k, s, a, hp.ou)
        ou_state, noisy = jax.vmap(ou_action)(noise_keys, ou_state, policy)
    else:
        std = exploration_std(spec, hp, state.expl_draw)
        noisy = jax.vmap(noise.gaussian)(noise_keys, policy, std)
    uniform = jax.random.uniform(random_key, policy.shape, minval=-1.0, maxval=1.0)
    action = jnp.where(state.env_steps < spec.warmup_steps, uniform, noisy)
    return safe_action(action), ou_state


def exploration_std(spec: TrainSpec, hp: Hyperparams, draw: jax.Array) -> jax.Array:
    """``[num_envs]`` Gaussian exploration stds: ``expl_noise`` everywhere, or with
    ``per_env_noise`` each environment's own ``min + (max - min) * draw`` (``draw [num_envs]``
    uniform in ``[0, 1)``, so the stds are uniform in ``[expl_noise_min, expl_noise_max)``)."""
    if not spec.per_env_noise:
        return jnp.broadcast_to(hp.expl_noise, (spec.num_envs,))
    return hp.expl_noise_min + (hp.expl_noise_max - hp.expl_noise_min) * draw


def redraw_exploration(
    spec: TrainSpec, draw: jax.Array, ended: jax.Array, key: PRNGKey
) -> jax.Array:
    """``draw [num_envs]`` with a fresh uniform draw where ``ended [num_envs]`` (an episode
    ended, terminated or truncated); unchanged without ``per_env_noise``."""
    if not spec.per_env_noise:
        return draw
    fresh = jax.random.uniform(jax.random.fold_in(key, NOISE_KEY_SALT), draw.shape)
    return jnp.where(ended, fresh, draw)


def safe_action(action: jax.Array) -> jax.Array:
    """``action`` with NaNs replaced by 0: a diverged member of a population keeps stepping its
    environments with finite actions (NaN physics can stall a simulator's solver loops, and
    under the member vmap every member would wait for it)."""
    return jnp.where(jnp.isnan(action), 0.0, action)


#: The environment metrics an iteration sums over its steps (see :func:`collect`).
EPISODE_METRICS = ("episodes", "return_sum", "length_sum", "reward_mean", "physics_overflow")


def _episode_metrics(result: envs.StepResult) -> Metrics:
    ended = result.terminated | result.truncated
    return {
        "episodes": jnp.sum(ended).astype(jnp.float32),
        "return_sum": jnp.sum(jnp.where(ended, result.finished_return, 0.0)),
        "length_sum": jnp.sum(jnp.where(ended, result.finished_length, 0)).astype(jnp.float32),
        "reward_mean": jnp.mean(result.reward),
        # environment steps whose physics ran out of a fixed buffer (MuJoCo Warp's contacts)
        "physics_overflow": jnp.sum(result.overflow).astype(jnp.float32),
    }


def _worlds_actions(spec: TrainSpec, state: TrainState, action: jax.Array) -> jax.Array:
    """``action [num_envs, ...]`` of the training worlds, with the evaluation worlds' actions
    (the round's frozen deterministic policy) joined in where they are stepped too."""
    if not spec.eval_in_chunk:
        return action
    evaluator = state.evaluator
    _, obs = eval_worlds.split(spec.layout, state.env_state.obs)
    evaluated = policy_action(spec, evaluator.actor_params, evaluator.obs_stats, obs)
    return eval_worlds.join(spec.layout, action, evaluated)


def _split_result(
    spec: TrainSpec, result: envs.StepResult
) -> tuple[envs.StepResult, envs.StepResult | None]:
    """``(training worlds' result, evaluation worlds' result or None)``."""
    if not spec.eval_in_chunk:
        return result, None
    parts = [eval_worlds.split(spec.layout, x) for x in result]
    return type(result)(*(p[0] for p in parts)), type(result)(*(p[1] for p in parts))


def collect_step(spec: TrainSpec, hp: Hyperparams, state: TrainState) -> tuple[TrainState, Metrics]:
    """One vectorised step: act, step every environment, write the transitions to the ring
    (and, with ``eval_in_chunk``, step the evaluation worlds alongside, their rewards counted
    in the round that :func:`start_evaluation_round` started)."""
    key, act_key = jax.random.split(state.key)
    obs = _training_rows(spec, state.env_state.obs)
    action, ou_state = explore(spec, hp, state, obs, act_key)
    env_state, result = envs.step(spec.env, state.env_state, _worlds_actions(spec, state, action),
                                  spec.axis_name, groups=spec.reset_groups)  # fmt: skip
    result, evaluated = _split_result(spec, result)
    transition = Transition(obs, action, result.reward, result.next_obs,
                            result.terminated.astype(jnp.float32))  # fmt: skip
    ended = result.terminated | result.truncated
    state = state.replace(
        buffer=replay.add_slices(state.buffer, (transition, ended)),
        env_state=env_state,
        obs_stats=normalization.update(state.obs_stats, obs),
        ou_state=noise.ou_reset(ou_state, ended[:, None], hp.ou),
        expl_draw=redraw_exploration(spec, state.expl_draw, ended, act_key),
        key=key,
        env_steps=state.env_steps + spec.num_envs,
    )
    if spec.scale_rewards:
        returns = return_scale.update(state.returns, result.reward, ended, hp.agent.discount)
        state = state.replace(returns=returns)
    metrics = _episode_metrics(result)
    if evaluated is not None:
        ended = evaluated.terminated | evaluated.truncated
        evaluator = eval_worlds.advance(state.evaluator, evaluated.reward, ended)
        state = state.replace(evaluator=evaluator)
        metrics["physics_overflow"] += jnp.sum(evaluated.overflow).astype(jnp.float32)
    return state, metrics


def _training_rows(spec: TrainSpec, x: jax.Array) -> jax.Array:
    """The training worlds' rows of ``x [worlds, ...]``."""
    return eval_worlds.split(spec.layout, x)[0] if spec.eval_in_chunk else x


def start_evaluation_round(spec: TrainSpec, state: TrainState) -> TrainState:
    """At the start of a chunk (with ``eval_in_chunk``), where the last round has finished:
    the next round starts, its worlds reset with :func:`round_key` and its policy the current
    one (of ``state.env_steps``). No reset runs while no member's round has finished."""
    evaluator = state.evaluator
    done = eval_worlds.finished(evaluator)

    def next_round(_, carry: tuple) -> tuple:  # run when some member's round is done
        env_state, evaluator = carry
        fresh = envs.reset(spec.env, round_key(state.eval_key, evaluator.rounds), spec.eval_envs)
        env_state = eval_worlds.put_evaluation(spec.layout, env_state, fresh, done)
        evaluator = eval_worlds.start(evaluator, state.agent.actor_params, state.obs_stats,
                                      state.env_steps, done)  # fmt: skip
        return env_state, evaluator

    trips = any_member(done, spec.axis_name).astype(jnp.int32)
    carry = jax.lax.fori_loop(0, trips, next_round, (state.env_state, evaluator))
    return state.replace(env_state=carry[0], evaluator=carry[1])


def collect(spec: TrainSpec, hp: Hyperparams, state: TrainState) -> tuple[TrainState, Metrics]:
    """``steps_per_iter`` :func:`collect_step` s; episode counts and sums, mean reward."""
    step = lambda s, _: collect_step(spec, hp, s)
    state, per_step = jax.lax.scan(step, state, None, length=spec.steps_per_iter)
    metrics = {k: jnp.sum(v) for k, v in per_step.items()}
    metrics["reward_mean"] = jnp.mean(per_step["reward_mean"])
    return state, metrics


def sample_batch(
    spec: TrainSpec, hp: Hyperparams, buffer: replay.ReplayBuffer, key: PRNGKey
) -> Transition:
    """One training batch ``[batch_size, ...]`` as the updates draw it (n-step folded;
    observation rows, not yet normalised nor split into the actor's and critics' inputs:
    :func:`agent_batch`)."""
    return replay.sample_slices(buffer, key, spec.batch_size, spec.n_step, spec.stride,
                                hp.agent.discount)  # fmt: skip


def agent_batch(
    spec: TrainSpec, stats: normalization.RunningStats, batch: Transition
) -> Transition:
    """A sampled batch of rows ``[batch, row_size]`` as the agent learns from it: normalised,
    the actor's observations in ``obs``/``next_obs`` and, where the critics see another
    observation, theirs in ``critic_obs``/``next_critic_obs`` (each input normalised by its own
    features' statistics)."""
    rows, next_rows = normalize(spec, stats, batch.obs), normalize(spec, stats, batch.next_obs)
    return batch._replace(
        obs=envs.actor_observation(spec.env, rows),
        next_obs=envs.actor_observation(spec.env, next_rows),
        critic_obs=envs.critic_observation(spec.env, rows),
        next_critic_obs=envs.critic_observation(spec.env, next_rows),
    )


def gradient_step(
    spec: TrainSpec,
    hp: Hyperparams,
    buffer: replay.ReplayBuffer,
    stats: normalization.RunningStats,
    scale: jax.Array,
    agent_state: AgentState,
    key: PRNGKey,
) -> tuple[AgentState, Metrics]:
    """One agent update on a fresh, normalised batch whose rewards are divided by ``scale``
    (:func:`reward_scale`)."""
    sample_key, update_key = jax.random.split(key)
    batch = agent_batch(spec, stats, sample_batch(spec, hp, buffer, sample_key))
    batch = batch._replace(reward=batch.reward / scale) if spec.scale_rewards else batch
    return ac.update(spec.agent, hp.agent, agent_state, batch, update_key, spec.axis_name)


def learn(
    spec: TrainSpec,
    hp: Hyperparams,
    agent_state: AgentState,
    buffer: replay.ReplayBuffer,
    stats: normalization.RunningStats,
    scale: jax.Array,
    key: PRNGKey,
) -> tuple[AgentState, Metrics]:
    """``updates_per_iter`` gradient steps (the buffer is only read; rewards divided by
    ``scale``); metrics summed over them, plus ``updates``, the number taken."""
    step = functools.partial(gradient_step, spec, hp, buffer, stats, scale)
    keys = jax.random.split(key, spec.updates_per_iter)
    agent_state, per_update = jax.lax.scan(step, agent_state, keys)
    metrics = {k: jnp.sum(v) for k, v in per_update.items()}
    metrics["updates"] = jnp.asarray(spec.updates_per_iter, jnp.float32)
    return agent_state, metrics


def skip_learning(agent_state: AgentState, *_) -> tuple[AgentState, Metrics]:
    """The branch of :func:`iteration` before learning starts: the agent's zero metrics."""
    return agent_state, {**ac.zero_metrics(), "updates": jnp.zeros((), jnp.float32)}


def reward_scale(spec: TrainSpec, hp: Hyperparams, state: TrainState) -> jax.Array:
    """What the learner divides rewards by: :func:`td3_jax.core.return_scale.scale` of the run's
    return statistics with ``scale_rewards``, else 1."""
    if not spec.scale_rewards:
        return jnp.ones((), jnp.float32)
    return return_scale.scale(state.returns, hp.return_bound)


def learning_started(spec: TrainSpec, state: TrainState) -> jax.Array:
    """Warm-up over, a batch stored, every slice holding a whole n-step run."""
    run_span = (spec.n_step - 1) * spec.stride
    return (
        (state.env_steps >= spec.warmup_steps)
        & (jnp.sum(state.buffer.size) >= spec.batch_size)
        & (jnp.min(state.buffer.size) > run_span)
    )


def iteration(spec: TrainSpec, hp: Hyperparams, state: TrainState) -> tuple[TrainState, Metrics]:
    """:func:`collect`, then :func:`learn` once learning has started (a real branch, also
    under the member vmap)."""
    state, env_metrics = collect(spec, hp, state)
    key, update_key = jax.random.split(state.key)
    agent_state, update_metrics = skip_learning(state.agent)
    if spec.updates_per_iter > 0:
        agent_state, update_metrics = jax.lax.cond(
            any_member(learning_started(spec, state), spec.axis_name),
            functools.partial(learn, spec, hp),
            skip_learning,
            state.agent,
            state.buffer,
            state.obs_stats,
            reward_scale(spec, hp, state),
            update_key,
        )
    state = state.replace(agent=agent_state, key=key, iteration=state.iteration + 1)
    return state, {**env_metrics, **update_metrics}


def all_finite(tree: Any) -> jax.Array:
    """Whether every floating-point leaf of ``tree`` is finite (a bool scalar). Each leaf is
    reduced as ``sum(x * 0)`` (NaN where any value is NaN or inf), which needs no mask of its
    size (a replay ring's, say)."""
    leaves = [jnp.isfinite(jnp.sum(x * 0)) for x in jax.tree.leaves(tree)
              if jnp.issubdtype(x.dtype, jnp.floating)]  # fmt: skip
    return jnp.all(jnp.stack(leaves))


def observations_finite(buffer: replay.ReplayBuffer) -> jax.Array:
    """Whether every observation in the replay ring ``buffer`` (``obs``, ``next_obs`` and any
    critic observations of the stored transitions) is finite (a bool scalar): the
    environment's side of a diverged run, checked when one is found."""
    stored: Transition = buffer.data[0]
    return all_finite((stored.obs, stored.next_obs, stored.critic_obs, stored.next_critic_obs))


def summarize(totals: Metrics, iterations: jax.Array, state: TrainState) -> Metrics:
    """A chunk's metrics from the sums of its per-iteration metrics over ``iterations``.

    Losses are means over the updates taken (the actor's over its own updates), training
    returns and lengths means over the episodes that ended (NaN when none did).
    """
    per_update = lambda name, count: totals[name] / jnp.maximum(totals[count], 1.0)
    episodes = totals["episodes"]
    per_episode = lambda name: jnp.where(episodes > 0, per_update(name, "episodes"), jnp.nan)
    return {
        "critic_loss": per_update("critic_loss", "updates"),
        "actor_loss": per_update("actor_loss", "actor_updated"),
        "q_mean": per_update("q_mean", "updates"),
        "target_mean": per_update("target_mean", "updates"),
        "chunk_updates": totals["updates"],
        "train_episodes": episodes,
        "train_return_mean": per_episode("return_sum"),
        "train_length_mean": per_episode("length_sum"),
        "reward_mean": totals["reward_mean"] / jnp.maximum(iterations, 1).astype(jnp.float32),
        "physics_overflow": totals["physics_overflow"],
        "params_finite": all_finite(state.agent).astype(jnp.float32),
        "env_steps": state.env_steps,
        "agent_steps": state.agent.step,
        **_evaluator_metrics(state),
    }


def _evaluator_metrics(state: TrainState) -> Metrics:
    """With in-chunk evaluation: ``eval_policy_env_steps``, the training env steps at which
    the last finished round's policy was taken (-1 before one)."""
    if state.evaluator is None:
        return {}
    return {"eval_policy_env_steps": state.evaluator.last_policy_env_steps}  # int32, exact


def _iteration_summed(spec: TrainSpec, hp: Hyperparams, _, carry: tuple) -> tuple:
    state, totals = carry
    state, metrics = iteration(spec, hp, state)
    return state, jax.tree.map(jnp.add, totals, metrics)


def chunk(
    spec: TrainSpec, hp: Hyperparams, state: TrainState, iterations: jax.Array | None = None
) -> tuple[TrainState, Metrics]:
    """``iterations`` :func:`iteration` s in one compiled loop: the unit the host loop calls.

    ``iterations`` (an int32 scalar, traced: any count runs the same compiled program) defaults
    to ``spec.iters_per_chunk``; a run's first chunk may be split in two (an early evaluation)
    without a second compile. With ``eval_in_chunk`` the chunk starts an evaluation round
    (:func:`start_evaluation_round`) and keeps it once finished (at the end of this chunk when
    it holds an episode, else of a later call). It is :func:`chunk_iterations` after
    :func:`start_evaluation_round`.
    """
    if spec.eval_in_chunk:
        state = start_evaluation_round(spec, state)
    return chunk_iterations(spec, hp, state, iterations)


def chunk_iterations(
    spec: TrainSpec, hp: Hyperparams, state: TrainState, iterations: jax.Array | None = None
) -> tuple[TrainState, Metrics]:
    """:func:`chunk` without starting an evaluation round: the same state and metrics where
    :func:`start_evaluation_round` ran on ``state`` first. The host loop compiles the two as
    programs of their own, side by side, so that the chunk's compile leaves out the round's
    reset of the environment (a second copy of it: the step's resets are the first)."""
    iterations = spec.iters_per_chunk if iterations is None else iterations
    zeros = {**{name: jnp.zeros((), jnp.float32) for name in EPISODE_METRICS},
             **skip_learning(state.agent)[1]}  # fmt: skip
    body = functools.partial(_iteration_summed, spec, hp)
    state, totals = jax.lax.fori_loop(0, iterations, body, (state, zeros))
    if spec.eval_in_chunk:
        state = state.replace(evaluator=eval_worlds.close(state.evaluator))
    metrics = summarize(totals, jnp.asarray(iterations), state)
    if spec.scale_rewards:  # what the last updates divided rewards by
        metrics["reward_scale"] = reward_scale(spec, hp, state)
    return state, metrics


class Recording(NamedTuple):
    """What :func:`evaluate_recorded` keeps of its first ``record`` environments, per step
    (``T = episode_length``): ``positions [T, record, nq]`` after the step (the environment's
    ``qpos_fn``), ``reward [T, record]``, and ``counted [T, record]``: the step belongs to the
    environment's first episode (its reward is in the return)."""

    positions: jax.Array
    reward: jax.Array
    counted: jax.Array


def _first(tree: Any, count: int) -> Any:
    return jax.tree.map(lambda x: x[:count], tree)


def _evaluation_step(
    spec: TrainSpec, state: TrainState, record: int, carry: tuple, _
) -> tuple[tuple, Recording | None]:
    """One deterministic-policy step of every evaluation environment; emits a
    :class:`Recording` step of the first ``record`` environments (``None`` when 0)."""
    env_state, returns, alive = carry
    action = policy_action(spec, state.agent.actor_params, state.obs_stats, env_state.obs)
    # Only each environment's first episode counts: no resets needed.
    env_state, result = envs.step(spec.env, env_state, action, auto_reset=False)
    returns = returns + jnp.where(alive, result.reward, 0.0)
    out = None
    if record:
        positions = jax.vmap(spec.env.qpos_fn)(_first(env_state.inner, record))
        out = Recording(positions, result.reward[:record], alive[:record])
    alive = alive & ~(result.terminated | result.truncated)
    return (env_state, returns, alive), out


def _evaluation(
    spec: TrainSpec, state: TrainState, key: PRNGKey, record: int
) -> tuple[jax.Array, Recording | None]:
    """``(returns [eval_envs], recording)``: one episode per evaluation environment. Without a
    recording, stepping stops once every episode has ended (the returns are the same: ended
    episodes add nothing), so evaluating a policy that falls early is cheap."""
    carry = (
        envs.reset(spec.env, key, spec.eval_envs),
        jnp.zeros((spec.eval_envs,), jnp.float32),
        jnp.ones((spec.eval_envs,), bool),
    )
    step = functools.partial(_evaluation_step, spec, state, record)
    if record:
        (_, returns, _), recording = jax.lax.scan(step, carry, None, spec.env.episode_length)
        return returns, recording

    def running(counted: tuple) -> jax.Array:
        t, (_, _, alive) = counted
        return (t < spec.env.episode_length) & jnp.any(alive)

    def advance(counted: tuple) -> tuple:
        t, inner = counted
        return t + 1, step(inner, None)[0]

    _, (_, returns, _) = jax.lax.while_loop(running, advance, (jnp.int32(0), carry))
    return returns, None


def evaluate(spec: TrainSpec, state: TrainState, key: PRNGKey) -> jax.Array:
    """Returns ``[eval_envs]``: one deterministic-policy episode per evaluation environment."""
    return _evaluation(spec, state, key, 0)[0]


def evaluate_recorded(
    spec: TrainSpec, state: TrainState, key: PRNGKey, record: int
) -> tuple[jax.Array, Recording]:
    """:func:`evaluate` (the same episodes and returns ``[eval_envs]``) that also records the
    first ``record`` environments step by step (:class:`Recording`), for rendering.

    Needs an environment with a ``qpos_fn``; ``record`` is static, at most ``eval_envs``.
    """
    if spec.env.qpos_fn is None:
        raise ConfigError(f"{spec.env.name} has no qpos_fn: nothing to record")
    if not 0 < record <= spec.eval_envs:
        raise ConfigError(f"record must be in 1..{spec.eval_envs}, got {record}")
    return _evaluation(spec, state, key, record)


def evaluation_key(spec: TrainSpec, state: TrainState) -> PRNGKey:
    """The evaluation key after the chunk that brought ``state`` to its iteration count."""
    return jax.random.fold_in(state.eval_key, state.iteration // spec.iters_per_chunk)


def scheduled_evaluate(spec: TrainSpec, state: TrainState) -> jax.Array:
    """:func:`evaluate` with the run's own key schedule (:func:`evaluation_key`); with
    ``eval_in_chunk``, the returns ``[eval_envs]`` of the last finished in-chunk round instead
    (NaN before one; its policy's env steps are the chunk metric ``eval_policy_env_steps``)."""
    if spec.eval_in_chunk:
        return state.evaluator.last_returns
    return evaluate(spec, state, evaluation_key(spec, state))


def chunk_and_evaluate(
    spec: TrainSpec, hp: Hyperparams, state: TrainState
) -> tuple[TrainState, Metrics]:
    """One chunk, then :func:`scheduled_evaluate` (``eval_returns [eval_envs]`` added to the
    chunk's metrics): the driver of every training run. The CLI's host loop runs the same two
    functions as two compiled programs (so it can check the chunk's metrics in between)."""
    state, metrics = chunk(spec, hp, state)
    return state, {**metrics, "eval_returns": scheduled_evaluate(spec, state)}


def make_train(
    spec: TrainSpec, hp: Hyperparams, num_chunks: int
) -> Callable[[PRNGKey], tuple[TrainState, Metrics]]:
    """The whole run as one pure function ``train(key) -> (final_state, metrics)``:
    :func:`init`, then ``num_chunks`` times :func:`chunk_and_evaluate`.

    ``metrics`` has a leading axis of ``num_chunks`` (one entry per evaluation) and holds the
    chunk metrics plus ``eval_returns [num_chunks, eval_envs]``; ``jax.vmap(train)(keys)``
    trains one independent agent per key in one program (with ``spec.axis_name`` the vmap's
    axis name, the reset and warm-up branches stay real branches). From a config:
    :func:`td3_jax.config.build.make_train`.
    """
    return functools.partial(_train, spec, hp, num_chunks)


def _train(spec: TrainSpec, hp: Hyperparams, num_chunks: int, key: PRNGKey):
    check_key(key)
    step = lambda s, _: chunk_and_evaluate(spec, hp, s)
    return jax.lax.scan(step, init(spec, key), None, length=num_chunks)


def check_key(key: Any) -> None:
    """A ``TypeError`` that says what to pass where ``key`` is not one PRNG key (a raw
    ``uint32`` key, e.g. :func:`key_for_seed`'s, or a typed ``jax.random.key``): an int seed,
    or a batch of keys given to the unbatched function (checked on shapes while tracing)."""
    shape, dtype = jnp.shape(key), getattr(key, "dtype", None)
    typed = dtype is not None and jnp.issubdtype(dtype, jax.dtypes.prng_key)
    if (typed and shape == ()) or (dtype == jnp.uint32 and len(shape) == 1):
        return
    what = f"{type(key).__name__} {key!r}" if not shape else f"an array of shape {shape}"
    raise TypeError(f"train takes one PRNG key (td3_jax.key_for_seed(seed) or "
                    f"jax.random.PRNGKey(seed)), got {what}; for several keys, "
                    "jax.vmap the function over them")  # fmt: skip


__all__ = [
    "EPISODE_METRICS",
    "Hyperparams",
    "Recording",
    "TrainSpec",
    "TrainState",
    "check_key",
    "chunk",
    "chunk_and_evaluate",
    "chunk_iterations",
    "collect",
    "collect_step",
    "evaluate",
    "evaluate_recorded",
    "init",
    "key_for_seed",
    "learn",
    "make_train",
    "policy_action",
    "round_key",
    "scheduled_evaluate",
    "start_evaluation_round",
]
