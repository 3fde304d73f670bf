"""The small environment interface and correct auto-reset, shared by every adapter.

An adapter (Brax, Playground, gymnax) supplies an :class:`Environment`: two pure functions over
one environment, ``reset_fn(key) -> (inner, obs)`` and ``step_fn(inner, action, key) -> (inner,
obs, reward, terminated)``, plus sizes, the episode length and the action bounds. This module
adds what every source needs, in one place:

* actions: the agent acts in ``[-1, 1]^action_size``; :func:`step` rescales to the
  environment's ``[low, high]`` bounds per dimension,
  ``low + (clip(a, -1, 1) + 1) / 2 * (high - low)``;
* time limit: after ``episode_length`` steps an episode is *truncated* (``done = 0`` in the
  stored transition, so the target bootstraps); a *termination* from the environment gives
  ``done = 1``;
* auto-reset: an episode that ends restarts from a fresh random state drawn with a new key
  (never a cached first state), while the returned transition keeps the true last observation;
* episode return and length of finished episodes;
* an asymmetric actor-critic: an environment whose critics learn from another observation
  than the actor (a robot's privileged state) keeps one flat *row* per environment holding
  both, the actor's observation once: ``row[:observation_size]`` is the actor's and
  ``row[critic_offset:critic_offset + critic_observation_size]`` the critics'
  (:func:`actor_observation`, :func:`critic_observation`). Where the actor's observation is a
  prefix of the critics' the row is the critics' observation itself (offset 0); otherwise the
  two side by side (offset ``observation_size``). Flat environments: the row is the observation.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from td3_jax.common.axes import max_member
from td3_jax.common.errors import EnvironmentOptionError

ResetFn = Callable[[jax.Array], tuple[Any, jax.Array]]
StepFn = Callable[[Any, jax.Array, jax.Array], tuple[Any, jax.Array, jax.Array, jax.Array]]


@dataclasses.dataclass(frozen=True, eq=False)
class Environment:
    """One environment of a source, as pure functions (vmapped by :func:`reset` / :func:`step`).

    Compared and hashed by identity, so a spec holding it can be a static ``jit`` argument.

    Attributes:
      name: ``SOURCE/NAME`` as given on the command line.
      observation_size: length of the actor's observation vector.
      action_size: length of the action vector.
      episode_length: the time limit in steps (truncation, not termination).
      action_low, action_high: ``[action_size]`` bounds of the environment's own action space.
      reset_fn: ``reset_fn(key) -> (inner_state, row[row_size])``.
      step_fn: ``step_fn(inner, env_action[action_size], key) -> (inner, row, reward,
        terminated)``; ``terminated`` is a true termination, not a time limit.
      critic_observation_size: length of the critics' observation, or ``None``: the critics
        see the actor's observation (the row is the observation).
      critic_offset: where the critics' observation starts in the row (0 when the actor's
        observation is a prefix of it).
      mj_model: the ``mujoco.MjModel`` a MuJoCo renderer draws (``None``: not a MuJoCo scene);
        for rendering only (:mod:`td3_jax.tools.render`), training never reads it.
      qpos_fn: ``qpos_fn(inner) -> [nq]`` the positions a frame is drawn from (MuJoCo's
        ``qpos``; gymnax's Pendulum: its angle), or ``None`` (not renderable).
      overflow_fn: ``overflow_fn(inner) -> bool``: the physics ran out of a fixed buffer in
        the step that produced ``inner`` (MuJoCo Warp's contacts or constraints: dropped, so
        the physics is wrong), or ``None`` (it cannot).
      per_device: its batched physics cannot be split over devices by XLA (MuJoCo Warp's
        calls): a batch spread over several devices is stepped on each device apart
        (:func:`td3_jax.envs.per_device.over_devices`).
      batch_map: ``batch_map(batched, size) -> batched``: how every batched physics call
        (``jax.vmap`` of ``reset_fn`` or ``step_fn`` over ``size`` environments) runs;
        ``None``: as it is (:func:`td3_jax.envs.per_device.over_devices` sets it).
    """

    name: str
    observation_size: int
    action_size: int
    episode_length: int
    action_low: np.ndarray
    action_high: np.ndarray
    reset_fn: ResetFn = dataclasses.field(repr=False)
    step_fn: StepFn = dataclasses.field(repr=False)
    critic_observation_size: int | None = None
    critic_offset: int = 0
    mj_model: Any = dataclasses.field(default=None, repr=False)
    qpos_fn: Callable[[Any], jax.Array] | None = dataclasses.field(default=None, repr=False)
    overflow_fn: Callable[[Any], jax.Array] | None = dataclasses.field(default=None, repr=False)
    per_device: bool = False
    batch_map: Callable[[Callable, int], Callable] | None = dataclasses.field(default=None,
                                                                              repr=False)

    @property
    def row_size(self) -> int:
        """Length of the stored observation row (:attr:`observation_size` for a flat one)."""
        if self.critic_observation_size is None:
            return self.observation_size
        return max(self.observation_size, self.critic_offset + self.critic_observation_size)

    def to_env_action(self, action: jax.Array) -> jax.Array:
        """Maps an agent action in ``[-1, 1]`` to ``[low, high]`` per dimension."""
        low = jnp.asarray(self.action_low, jnp.float32)
        high = jnp.asarray(self.action_high, jnp.float32)
        return low + (jnp.clip(action, -1.0, 1.0) + 1.0) * 0.5 * (high - low)


@dataclasses.dataclass(frozen=True)
class EnvOptions:
    """Options of MuJoCo Playground's locomotion tasks (other sources refuse non-defaults).

    Attributes:
      menagerie: a MuJoCo Menagerie root holding the robot's folder (default: the
        ``MENAGERIE_ROOT`` variable, then the asset packages; :mod:`td3_jax.envs.menagerie`).
      domain_randomization: the task's own randomiser draws each environment's physics
        (friction, masses, gains, ...) at every reset.
      pushes: the task's push perturbations on or off; ``None``: the task's default.
      actor_obs_key, critic_obs_key: the keys of a dict observation that the actor and the
        critics see (equal keys: a symmetric actor-critic). Flat observations ignore them.
      impl: the physics of every Playground task, MJX's ``jax`` or MuJoCo ``warp``
        (:mod:`td3_jax.envs.physics`); ``None``: Warp where it can run, else JAX.
      worlds: the most environments stepped together (all members' together): Warp's
        contact buffer is sized for them.
      nconmax, njmax: Warp's contacts and constraints per environment (``None``: the task's).
    """

    menagerie: str | None = None
    domain_randomization: bool = False
    pushes: bool | None = None
    actor_obs_key: str = "state"
    critic_obs_key: str = "privileged_state"
    impl: str | None = "jax"
    worlds: int = 1
    nconmax: int | None = None
    njmax: int | None = None

    def locomotion_only(self) -> list[str]:
        """The options set away from their defaults that only locomotion tasks take."""
        given = []
        if self.domain_randomization:
            given.append("--domain-randomization")
        if self.pushes is not None:
            given.append("--pushes" if self.pushes else "--no-pushes")
        return given


def refuse_locomotion_options(name: str, options: EnvOptions) -> None:
    """Raises :class:`EnvironmentOptionError` when ``options`` set what only Playground's
    locomotion tasks take, for the environment ``name`` (which is not one)."""
    refused = options.locomotion_only()
    if refused:
        verb = "applies" if len(refused) == 1 else "apply"
        raise EnvironmentOptionError(
            f"{', '.join(refused)} {verb} to Playground's locomotion tasks, not {name}"
        )


def action_bound(value: Any, size: int) -> np.ndarray:
    """``[size]`` float32 action bound from one number or ``size`` numbers (a ``ValueError``
    for another shape)."""
    return np.broadcast_to(np.asarray(value, np.float32), (size,)).copy()


def from_mjx_style(
    name: str,
    env: Any,
    episode_length: int,
    *,
    mj_model: Any = None,
    qpos_fn: Callable[[Any], jax.Array] | None = None,
    overflow_fn: Callable[[Any], jax.Array] | None = None,
    per_device: bool = False,
) -> Environment:
    """Wraps an environment with Brax's API (``reset(key)``/``step(state, action)`` returning a
    state with ``obs``, ``reward`` and ``done``; actions in ``[-1, 1]``), as Brax and MuJoCo
    Playground environments have. Without their episode wrappers, ``done`` is a termination.
    ``mj_model`` and ``qpos_fn`` (of the source's state) are kept for rendering only;
    ``overflow_fn`` (of the source's state) is :attr:`Environment.overflow_fn`;
    ``per_device``: :attr:`Environment.per_device` (MuJoCo Warp's physics).
    """

    def reset_fn(key):
        state = env.reset(key)
        return state, state.obs

    def step_fn(state, action, key):
        del key  # these environments step deterministically
        state = env.step(state, action)
        return state, state.obs, state.reward, state.done > 0.5

    # Jitted, the physics is traced once per input shape and the trace is reused by every program
    # that steps or resets one environment (init, chunk, evaluation): MJX traces take seconds.
    reset_fn, step_fn = jax.jit(reset_fn), jax.jit(step_fn)
    # Brax's env.observation_size runs an unjitted reset op by op (tens of seconds for MJX);
    # the shape of a traced reset gives the same number without running anything.
    obs_shape = jax.eval_shape(reset_fn, jax.random.PRNGKey(0))[1].shape
    return Environment(
        name=name,
        observation_size=int(obs_shape[-1]),
        action_size=int(env.action_size),
        episode_length=int(episode_length),
        action_low=-np.ones(env.action_size, np.float32),
        action_high=np.ones(env.action_size, np.float32),
        reset_fn=reset_fn,
        step_fn=step_fn,
        mj_model=mj_model,
        qpos_fn=qpos_fn,
        overflow_fn=overflow_fn,
        per_device=per_device,
    )


def actor_observation(env: Environment, row: jax.Array) -> jax.Array:
    """The actor's observation ``[..., observation_size]`` of rows ``[..., row_size]``."""
    return row if env.row_size == env.observation_size else row[..., : env.observation_size]


def critic_observation(env: Environment, row: jax.Array) -> jax.Array | None:
    """The critics' observation ``[..., critic_observation_size]`` of rows ``[..., row_size]``,
    or ``None`` when the critics see the actor's observation."""
    if env.critic_observation_size is None:
        return None
    start = env.critic_offset
    return row[..., start : start + env.critic_observation_size]


@struct.dataclass
class EnvState:
    """State of a batch of environments (every leaf has a leading ``num_envs`` axis, except
    what a physics keeps once for the whole batch: MuJoCo Warp's contact buffer and counters).

    Attributes:
      inner: the source's own state (physics data, ...).
      obs: ``[num_envs, row_size]`` current observation row (the observation of a flat
        environment; see :func:`actor_observation` and :func:`critic_observation`).
      key: ``[num_envs]`` PRNG keys, split at every step (stochastic steps and fresh resets).
      steps: ``[num_envs]`` int32 steps taken in the current episode.
      episode_return: ``[num_envs]`` float32 return so far in the current episode.
    """

    inner: Any
    obs: jax.Array
    key: jax.Array
    steps: jax.Array
    episode_return: jax.Array


class StepResult(NamedTuple):
    """What one batched step returns besides the new state (all ``[num_envs, ...]``).

    ``next_obs [num_envs, row_size]`` is the observation row the step produced; where an
    episode ended it is the true last observation, while the new state's ``obs`` is already the
    first one of the next episode.
    ``finished_return``/``finished_length`` are meaningful where ``terminated | truncated``.
    ``overflow``: the environments whose physics ran out of a fixed buffer in this step
    (:attr:`Environment.overflow_fn`; all false for a physics without one).
    """

    next_obs: jax.Array
    reward: jax.Array
    terminated: jax.Array
    truncated: jax.Array
    finished_return: jax.Array
    finished_length: jax.Array
    overflow: jax.Array | None = None


def _strong(tree: Any) -> Any:
    """Same values with strong (non-weak) dtypes, so reset and step states type-match exactly."""
    return jax.tree.map(lambda x: jax.lax.convert_element_type(x, jnp.result_type(x)), tree)


def batched_physics(env: Environment, fn: Callable, size: int) -> Callable:
    """``fn`` (``env.reset_fn`` or ``env.step_fn``) over a batch of ``size`` environments:
    ``jax.vmap``, run as :attr:`Environment.batch_map` says (e.g. on each device apart)."""
    batched = jax.vmap(fn)
    return batched if env.batch_map is None else env.batch_map(batched, size)


def _reset_batch(env: Environment, keys: jax.Array) -> tuple[Any, jax.Array]:
    inner, obs = batched_physics(env, env.reset_fn, keys.shape[0])(keys)
    return _strong(inner), obs.astype(jnp.float32)


def reset_keys(key: jax.Array, num_envs: int) -> tuple[jax.Array, jax.Array]:
    """``(reset_keys, state_keys)``, each ``[num_envs]``: the keys :func:`reset` draws
    ``num_envs`` initial states and their step-key chains from."""
    return tuple(jnp.split(jax.random.split(key, 2 * num_envs), 2))


def reset_from_keys(env: Environment, keys: tuple[jax.Array, jax.Array]) -> EnvState:
    """Environments from ``keys = (reset_keys, state_keys)`` (each ``[num_envs]``, as
    :func:`reset_keys` draws them; keys of several draws may be concatenated to reset their
    environments in one batch)."""
    reset_keys, state_keys = keys
    num_envs = reset_keys.shape[0]
    inner, obs = _reset_batch(env, reset_keys)
    return EnvState(
        inner=inner,
        obs=obs,
        key=state_keys,
        steps=jnp.zeros((num_envs,), jnp.int32),
        episode_return=jnp.zeros((num_envs,), jnp.float32),
    )


def reset(env: Environment, key: jax.Array, num_envs: int) -> EnvState:
    """``num_envs`` environments, each from its own random initial state."""
    return reset_from_keys(env, reset_keys(key, num_envs))


def default_reset_slots(num_envs: int) -> int:
    """How many ended environments :func:`reset_ended` resets together, per round.

    A sixteenth of the batch (at least one): on a step where at most that many episodes ended
    (the usual case), one round resets just those; when the whole batch ends at once (a shared
    time limit) 16 rounds do.
    """
    return max(1, num_envs // 16)


def by_group(x: jax.Array, groups: int) -> jax.Array:
    """``[num_envs, ...] -> [groups, num_envs / groups, ...]``."""
    return x.reshape(groups, x.shape[0] // groups, *x.shape[1:])


def batched(x: jax.Array, size: int) -> bool:
    """Whether ``x`` has a leading batch axis of ``size`` (MuJoCo Warp keeps some of its data,
    e.g. its contact buffer, once for all the environments stepped together: no batch axis)."""
    return jnp.ndim(x) > 0 and jnp.shape(x)[0] == size


def _ended_in_round(ended: jax.Array, first: jax.Array, slots: int) -> jax.Array:
    """``[size]`` indices of the ended environments ranked ``first .. first + slots - 1`` in
    ``ended [size]`` (in index order), padded with ``size`` (out of range: scatters drop it)."""
    rank = jnp.cumsum(ended) - 1
    picked = ended & (rank >= first) & (rank < first + slots)
    return jnp.nonzero(picked, size=slots, fill_value=ended.shape[0])[0]


def _reset_round(env, ended, keys, groups, slots, round_index, carry):
    """Round ``round_index`` of :func:`reset_ended`: gathers the next ``slots`` ended
    environments of each group, resets them with their own keys and scatters them back."""
    inner, obs = carry
    num_envs = ended.shape[0]
    size = num_envs // groups
    first = round_index * slots
    index = jax.vmap(lambda e: _ended_in_round(e, first, slots))(by_group(ended, groups))
    picked = jax.vmap(lambda k, i: k[jnp.minimum(i, size - 1)])(by_group(keys, groups), index)
    fresh_inner, fresh_obs = _reset_batch(env, picked.reshape(groups * slots, *picked.shape[2:]))

    def put(full, part):
        if not batched(full, num_envs) or not batched(part, groups * slots):
            return full  # kept once for every environment (MuJoCo Warp's contacts, counters)
        full = by_group(full, groups)
        part = part.reshape(groups, slots, *part.shape[1:]).astype(full.dtype)
        scatter = lambda f, i, p: f.at[i].set(p, mode="drop")
        return jax.vmap(scatter)(full, index, part).reshape(num_envs, *full.shape[2:])

    return jax.tree.map(put, inner, fresh_inner), put(obs, fresh_obs)


def reset_ended(
    env: Environment,
    ended: jax.Array,
    keys: jax.Array,
    inner: Any,
    obs: jax.Array,
    axis_name: str | None = None,
    *,
    reset_slots: int | None = None,
    groups: int = 1,
) -> tuple[Any, jax.Array]:
    """``(inner, obs)`` with every ended environment (``ended [num_envs]``) restarted from a
    fresh random state drawn with its own key (``keys [num_envs]``).

    One reset path, so the environment's reset is compiled once: a loop of rounds, each
    gathering up to ``reset_slots`` ended environments per group (default
    :func:`default_reset_slots`), resetting them and scattering them back; no round runs when no
    episode ended. Every environment gets the reset of its own key whatever the number of
    rounds (bit for bit on CPU). Under a ``jax.vmap`` with ``axis_name`` the number of rounds is
    the largest over that axis, so it stays a real loop. ``groups``: the batch is that many
    equal, contiguous groups (e.g. one per device) and gathers and scatters stay inside each.
    """
    num_envs = ended.shape[0]
    if groups <= 0 or num_envs % groups:
        raise ValueError(f"{num_envs} environments cannot form {groups} equal groups")
    size = num_envs // groups
    slots = default_reset_slots(size) if reset_slots is None else int(reset_slots)
    if slots <= 0:
        raise ValueError(f"reset_slots must be positive, got {slots}")
    slots = min(slots, size)
    count = max_member(jnp.max(jnp.sum(by_group(ended, groups).astype(jnp.int32), axis=1)),
                       axis_name)  # fmt: skip
    rounds = (count + slots - 1) // slots
    body = functools.partial(_reset_round, env, ended, keys, groups, slots)
    return jax.lax.fori_loop(0, rounds, body, (inner, obs))


def step(
    env: Environment,
    state: EnvState,
    action: jax.Array,
    axis_name: str | None = None,
    *,
    auto_reset: bool = True,
    reset_slots: int | None = None,
    groups: int = 1,
) -> tuple[EnvState, StepResult]:
    """Steps every environment with ``action [num_envs, action_size]`` in ``[-1, 1]``.

    Environments whose episode ended (termination or time limit) restart from a fresh random
    state drawn with their own new key (:func:`reset_ended`, which ``axis_name``,
    ``reset_slots`` and ``groups`` are passed to; the result does not depend on them).

    ``auto_reset=False`` skips resets entirely (ended environments keep stepping from their last
    state; ``steps`` and ``episode_return`` still restart): for evaluation, which only counts
    each environment's first episode.
    """
    keys = jax.vmap(lambda k: jax.random.split(k, 3))(state.key)
    next_key, step_key, reset_key = keys[:, 0], keys[:, 1], keys[:, 2]
    physics = batched_physics(env, env.step_fn, step_key.shape[0])
    inner, obs, reward, terminated = physics(state.inner, env.to_env_action(action), step_key)
    inner, obs = _strong(inner), obs.astype(jnp.float32)
    reward, terminated = reward.astype(jnp.float32), terminated.astype(bool)
    steps = state.steps + 1
    truncated = (steps >= env.episode_length) & ~terminated
    ended = terminated | truncated
    episode_return = state.episode_return + reward
    new_inner, new_obs = inner, obs
    if auto_reset:
        new_inner, new_obs = reset_ended(env, ended, reset_key, inner, obs, axis_name,
                                         reset_slots=reset_slots, groups=groups)  # fmt: skip
    new_state = EnvState(inner=new_inner, obs=new_obs, key=next_key,
                         steps=jnp.where(ended, 0, steps),
                         episode_return=jnp.where(ended, 0.0, episode_return))  # fmt: skip
    overflow = (jnp.zeros_like(terminated) if env.overflow_fn is None
                else jax.vmap(env.overflow_fn)(inner).astype(bool))  # fmt: skip
    return new_state, StepResult(obs, reward, terminated, truncated, episode_return, steps,
                                 overflow)  # fmt: skip


__all__ = [
    "EnvOptions",
    "EnvState",
    "Environment",
    "EnvironmentOptionError",
    "StepResult",
    "action_bound",
    "actor_observation",
    "batched",
    "batched_physics",
    "by_group",
    "critic_observation",
    "default_reset_slots",
    "from_mjx_style",
    "refuse_locomotion_options",
    "reset",
    "reset_ended",
    "reset_from_keys",
    "reset_keys",
    "step",
]
