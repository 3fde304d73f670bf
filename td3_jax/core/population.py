"""Many independent runs (seeds x hyperparameter settings) as one compiled program.

A *population* is a list of members, each a seed plus optional overrides of float
hyperparameters. Its train state is the single-run :class:`~td3_jax.core.training.TrainState` with a
leading member axis, its :class:`~td3_jax.core.training.Hyperparams` likewise; the chunk is
``jax.vmap`` of :func:`td3_jax.core.training.chunk` over ``(hp, state)`` with one shared static spec
(a sweep is a vmap over traced values, not a recompile per value, and no trainer is rebuilt per
member). A population of one runs the single-run program unbatched (no vmap overhead) behind a
leading axis of size 1, so the host loop has one code path.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from td3_jax import envs
from td3_jax.core import training
from td3_jax.core.training import TrainState

__all__ = ["MEMBERS", "Member", "Population", "make_population", "member_keys", "on_host"]

MEMBERS = "members"  # the vmap axis name of the population


@dataclasses.dataclass(frozen=True)
class Member:
    """One member of a population: its seed and the float settings it overrides (sorted
    ``(name, value)`` pairs; made from a config by :func:`td3_jax.config.build.members`)."""

    seed: int
    overrides: tuple[tuple[str, float], ...] = ()

    def label(self) -> str:
        settings = " ".join(f"{k}={v:g}" for k, v in self.overrides)
        return f"{settings} seed={self.seed}".strip()


class Population(NamedTuple):
    """Pure functions over a population state (every leaf ``[num_members, ...]``).

    Attributes:
      members: the members, in the order of the leading axis.
      spec: the shared static spec (its ``axis_name`` is :data:`MEMBERS` for several members).
      hyperparams: every member's float settings (leaves ``[num_members]``).
      init: ``init() -> state``.
      chunk: ``chunk(hp, state, iterations=None) -> (state, metrics[num_members])``:
        ``iterations`` (an int32 scalar shared by the members; default ``iters_per_chunk``)
        iterations of every member.
      iterate: ``iterate(hp, state, iterations=None)``: ``chunk`` without starting an
        evaluation round (:func:`td3_jax.core.training.chunk_iterations`; ``chunk`` itself
        without ``eval_in_chunk``), so that ``start_round`` and it compile apart.
      start_round: ``start_round(state) -> state``, with ``eval_in_chunk``: the evaluation
        round that ``chunk`` starts (:func:`td3_jax.core.training.start_evaluation_round`);
        ``None`` without.
      evaluate: ``evaluate(state, keys[num_members]) -> returns[num_members, eval_envs]``.
      scheduled_evaluate: ``scheduled_evaluate(state) -> returns[num_members, eval_envs]``,
        with the run's own key schedule (:func:`td3_jax.core.training.evaluation_key`); with
        ``eval_in_chunk`` the returns of the chunk's evaluation round.
      abstract_state: shapes and dtypes of the state (for restoring checkpoints).
      keys: the members' start keys (``[num_members, 2]``, from their seeds).
      init_from_keys: ``init_from_keys(keys) -> state`` (``init`` is it of ``keys``).
    """

    members: list[Member]
    spec: training.TrainSpec
    hyperparams: training.Hyperparams
    init: Callable[[], TrainState]
    chunk: Callable[..., tuple[TrainState, dict[str, jax.Array]]]
    evaluate: Callable[[TrainState, jax.Array], jax.Array]
    scheduled_evaluate: Callable[[TrainState], jax.Array]
    abstract_state: Any
    keys: np.ndarray
    init_from_keys: Callable[[jax.Array], TrainState]
    iterate: Callable[..., tuple[TrainState, dict[str, jax.Array]]]
    start_round: Callable[[TrainState], TrainState] | None = None

    @property
    def env(self) -> envs.Environment:
        return self.spec.env


def member_keys(population: list[Member]) -> np.ndarray:
    """Every member's start key (``[members, 2]``, :func:`td3_jax.core.training.key_for_seed`),
    computed on the host, all at once (seeds are in ``[0, 2**32 - 1]``: uint32 holds them,
    and gives the keys of the Python ints)."""
    seeds = np.array([m.seed for m in population], np.uint32)
    return on_host(lambda: jax.vmap(training.key_for_seed)(jnp.asarray(seeds)))


def on_host(make: Callable[[], Any]) -> Any:
    """``make()`` computed on the CPU, as numpy arrays: a few tiny operations that would each
    be compiled (or looked up in the compilation cache) for the accelerator otherwise."""
    try:
        cpu = jax.local_devices(backend="cpu")[0]  # this process's own (several processes)
    except RuntimeError:  # no CPU backend (JAX_PLATFORMS names only the accelerator)
        return jax.tree.map(np.asarray, make())
    with jax.default_device(cpu):
        return jax.tree.map(np.asarray, make())


def _add_axis(tree: Any) -> Any:
    return jax.tree.map(lambda x: x[None], tree)


def _drop_axis(tree: Any) -> Any:
    return jax.tree.map(lambda x: x[0], tree)


def _lone(fn: Callable, *args: Any) -> Any:
    """``fn`` of the only member, unbatched (no vmap overhead), behind a leading axis of 1."""
    return _add_axis(fn(*map(_drop_axis, args)))


def _lone_chunk(fn: Callable, spec: training.TrainSpec, hp: Any, state: Any,
                iterations: Any = None) -> Any:  # fmt: skip
    """:func:`_lone` of a chunk function ``fn`` (:func:`td3_jax.core.training.chunk` or
    :func:`~td3_jax.core.training.chunk_iterations`; ``iterations`` has no member axis)."""
    return _add_axis(fn(spec, _drop_axis(hp), _drop_axis(state), iterations))


def _members_chunk(fn: Callable, spec: training.TrainSpec, hp: Any, state: Any,
                   iterations: Any = None) -> Any:  # fmt: skip
    """A chunk function ``fn`` vmapped over the members (``iterations`` shared)."""
    chunk = functools.partial(fn, spec)
    return jax.vmap(chunk, in_axes=(0, 0, None), axis_name=MEMBERS)(hp, state, iterations)


def make_population(
    spec: training.TrainSpec, hyperparams: training.Hyperparams, population: list[Member]
) -> Population:
    """The batched training functions of ``population`` over one shared ``spec`` (its
    ``axis_name`` becomes :data:`MEMBERS` for several members, ``None`` for one) and
    ``hyperparams``, every member's float settings stacked (leaves ``[num_members]``, in the
    members' order). From a config: :func:`td3_jax.config.build.make_population`."""
    lone = len(population) == 1
    spec = dataclasses.replace(spec, axis_name=None if lone else MEMBERS)
    keys = member_keys(population)
    steps = [functools.partial(fn, spec) for fn in
             (training.init, training.evaluate, training.scheduled_evaluate)]  # fmt: skip
    batch = (lambda f: functools.partial(_lone, f)) if lone else (
        lambda f: jax.vmap(f, axis_name=MEMBERS))  # fmt: skip
    init_from_keys, evaluate, scheduled = map(batch, steps)
    batched_chunk = _lone_chunk if lone else _members_chunk
    start_round = None
    if spec.eval_in_chunk:
        start_round = batch(functools.partial(training.start_evaluation_round, spec))
    init = functools.partial(init_from_keys, keys)
    return Population(population, spec, hyperparams, init,
                      functools.partial(batched_chunk, training.chunk, spec), evaluate, scheduled,
                      abstract_state=jax.eval_shape(init), keys=keys,
                      init_from_keys=init_from_keys,
                      iterate=functools.partial(batched_chunk, training.chunk_iterations, spec),
                      start_round=start_round)  # fmt: skip
