"""Evaluation inside the training chunk (``--eval-in-chunk``): evaluation worlds stepped in the
same batched physics call as the training environments.

A separate evaluation steps ``eval_envs`` environments for a whole episode, one step after the
other; on a physics whose step costs the same for 128 worlds as for 4096 (MuJoCo Warp: about
9 ms per step of a humanoid, mostly latency) that is seconds per evaluation while the GPU idles.
Here the environment batch holds the evaluation worlds beside the training ones (:class:`Layout`),
so they cost a few percent more physics work and no extra latency. They act with a frozen copy
of the deterministic policy (actor parameters and observation statistics taken when their round
started), count only each world's first episode, and are not written to the replay ring: the
training worlds see exactly what they see without them. A round starts at the start of a chunk
(from fresh resets, with the policy of that moment) and, the chunk being at least an episode
long, ends within it; at the chunk's end its returns are kept (:attr:`EvalRound.last_returns`)
with the env steps at which its policy was taken: a record after chunk ``c`` holds a separate
evaluation of the checkpoint after chunk ``c - 1``. Members of a population start and end
their rounds together.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from td3_jax.envs.base import batched, by_group


class Layout(NamedTuple):
    """Where the worlds of an environment batch are: ``groups`` contiguous groups (one per
    replay slice or device), each ``train / groups`` training worlds followed by
    ``evaluation / groups`` evaluation worlds (``evaluation`` 0: training worlds only)."""

    train: int
    evaluation: int
    groups: int = 1

    @property
    def worlds(self) -> int:
        """Worlds in the batch."""
        return self.train + self.evaluation


def split(layout: Layout, x: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``x [worlds, ...]`` as ``(training rows [train, ...], evaluation rows [evaluation, ...])``
    (each in group order)."""
    grouped = by_group(x, layout.groups)
    per_group = layout.train // layout.groups
    train = grouped[:, :per_group].reshape(layout.train, *x.shape[1:])
    return train, grouped[:, per_group:].reshape(layout.evaluation, *x.shape[1:])


def join(layout: Layout, train: jax.Array, evaluation: jax.Array) -> jax.Array:
    """The batch ``[worlds, ...]`` of ``train [train, ...]`` and ``evaluation [evaluation, ...]``
    rows (the inverse of :func:`split`)."""
    both = (by_group(train, layout.groups), by_group(evaluation.astype(train.dtype), layout.groups))
    return jnp.concatenate(both, axis=1).reshape(layout.worlds, *train.shape[1:])


def put_evaluation(layout: Layout, batch: Any, evaluation: Any, where: jax.Array) -> Any:
    """``batch`` (a pytree of ``[worlds, ...]`` leaves) with its evaluation rows replaced by
    ``evaluation``'s (the same pytree over ``[evaluation, ...]`` leaves) where ``where`` (a bool
    scalar). Leaves without the batch axis (MuJoCo Warp's shared buffers) are kept."""

    def put(full: jax.Array, part: jax.Array) -> jax.Array:
        if not batched(full, layout.worlds) or not batched(part, layout.evaluation):
            return full  # kept once for every environment (MuJoCo Warp's shared buffers)
        train, old = split(layout, full)
        return join(layout, train, jnp.where(where, part.astype(full.dtype), old))

    return jax.tree.map(put, batch, evaluation)


@struct.dataclass
class EvalRound:
    """The evaluation worlds' bookkeeping (in the train state).

    Attributes:
      actor_params, obs_stats: the evaluated policy, frozen when the round started.
      returns: ``[eval_envs]`` float32 returns of each world's first episode so far.
      alive: ``[eval_envs]`` bool, that first episode has not ended.
      policy_env_steps: int32 training env steps when the round's policy was taken.
      rounds: int32 rounds started (round ``r`` resets its worlds with ``fold_in(eval_key, r)``).
      last_returns: ``[eval_envs]`` the returns of the last finished round (NaN before one).
      last_policy_env_steps: int32 its ``policy_env_steps`` (-1 before one).
    """

    actor_params: Any
    obs_stats: Any
    returns: jax.Array
    alive: jax.Array
    policy_env_steps: jax.Array
    rounds: jax.Array
    last_returns: jax.Array
    last_policy_env_steps: jax.Array


def begin(actor_params: Any, obs_stats: Any, eval_envs: int) -> EvalRound:
    """No round yet (every episode counted as ended, so the first chunk starts round 0); the
    parameters only give the snapshot its structure."""
    return EvalRound(
        actor_params=actor_params,
        obs_stats=obs_stats,
        returns=jnp.zeros((eval_envs,), jnp.float32),
        alive=jnp.zeros((eval_envs,), bool),
        policy_env_steps=jnp.full((), -1, jnp.int32),
        rounds=jnp.zeros((), jnp.int32),
        last_returns=jnp.full((eval_envs,), jnp.nan, jnp.float32),
        last_policy_env_steps=jnp.full((), -1, jnp.int32),
    )


def advance(state: EvalRound, reward: jax.Array, ended: jax.Array) -> EvalRound:
    """After one step of the evaluation worlds (``reward``, ``ended``: ``[eval_envs]``): rewards
    added to the episodes still in their first episode, ended ones no longer counted."""
    returns = state.returns + jnp.where(state.alive, reward, 0.0)
    return state.replace(returns=returns, alive=state.alive & ~ended)


def finished(state: EvalRound) -> jax.Array:
    """Whether every first episode of the round has ended (a bool scalar)."""
    return ~jnp.any(state.alive)


def _pick(where: jax.Array, new: EvalRound, old: EvalRound) -> EvalRound:
    return jax.tree.map(lambda n, o: jnp.where(where, n, o), new, old)


def start(
    state: EvalRound, actor_params: Any, obs_stats: Any, env_steps: jax.Array, where: jax.Array
) -> EvalRound:
    """Where ``where`` (a bool scalar): a new round started with the policy
    ``actor_params``/``obs_stats`` of ``env_steps`` (its worlds reset by the caller)."""
    started = state.replace(
        actor_params=actor_params,
        obs_stats=obs_stats,
        returns=jnp.zeros_like(state.returns),
        alive=jnp.ones_like(state.alive),
        policy_env_steps=jnp.asarray(env_steps, jnp.int32),
        rounds=state.rounds + 1,
    )
    return _pick(where, started, state)


def close(state: EvalRound) -> EvalRound:
    """Where the round has finished (:func:`finished`): its returns and policy steps kept as the
    last finished round's."""
    closed = state.replace(last_returns=state.returns,
                           last_policy_env_steps=state.policy_env_steps)  # fmt: skip
    return _pick(finished(state), closed, state)


__all__ = [
    "EvalRound",
    "Layout",
    "advance",
    "begin",
    "close",
    "finished",
    "join",
    "put_evaluation",
    "split",
    "start",
]
