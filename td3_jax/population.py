"""Many independent runs (seeds x hyperparameter settings) as one compiled program.

A *population* is a list of members, each a seed plus optional overrides of float
hyperparameters. Its train state is the single-run :class:`~td3_jax.training.TrainState` with a
leading member axis, its :class:`~td3_jax.training.Hyperparams` likewise; the chunk is
``jax.vmap`` of :func:`td3_jax.training.chunk` over ``(hp, state)`` with one shared static spec
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

from td3_jax import envs, training
from td3_jax.runtime import StopToken, in_background, result
from td3_jax.sharding import replicate, state_shardings
from td3_jax.training import TrainState

MEMBERS = "members"  # the vmap axis name of the population


@dataclasses.dataclass(frozen=True)
class Member:
    """One member of a population: its seed and the float settings it overrides (sorted
    ``(name, value)`` pairs; made from a config by :func:`td3_jax.build.members`)."""

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
      evaluate: ``evaluate(state, keys[num_members]) -> returns[num_members, eval_envs]``.
      scheduled_evaluate: ``scheduled_evaluate(state) -> returns[num_members, eval_envs]``,
        with the run's own key schedule (:func:`td3_jax.training.evaluation_key`).
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

    @property
    def env(self) -> envs.Environment:
        return self.spec.env


def member_keys(population: list[Member]) -> np.ndarray:
    """Every member's start key (``[members, 2]``, :func:`td3_jax.training.key_for_seed`),
    computed on the host."""
    return on_host(lambda: jnp.stack([training.key_for_seed(m.seed) for m in population]))


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


def _lone_chunk(spec: training.TrainSpec, hp: Any, state: Any, iterations: Any = None) -> Any:
    """:func:`_lone` of :func:`td3_jax.training.chunk` (``iterations`` has no member axis)."""
    return _add_axis(training.chunk(spec, _drop_axis(hp), _drop_axis(state), iterations))


def _members_chunk(spec: training.TrainSpec, hp: Any, state: Any, iterations: Any = None) -> Any:
    """:func:`td3_jax.training.chunk` vmapped over the members (``iterations`` shared)."""
    chunk = functools.partial(training.chunk, spec)
    return jax.vmap(chunk, in_axes=(0, 0, None), axis_name=MEMBERS)(hp, state, iterations)


def make_population(
    spec: training.TrainSpec, hyperparams: training.Hyperparams, population: list[Member]
) -> Population:
    """The batched training functions of ``population`` over one shared ``spec`` (its
    ``axis_name`` becomes :data:`MEMBERS` for several members, ``None`` for one) and
    ``hyperparams``, every member's float settings stacked (leaves ``[num_members]``, in the
    members' order). From a config: :func:`td3_jax.build.make_population`."""
    lone = len(population) == 1
    spec = dataclasses.replace(spec, axis_name=None if lone else MEMBERS)
    keys = member_keys(population)
    steps = [functools.partial(fn, spec) for fn in
             (training.init, training.evaluate, training.scheduled_evaluate)]  # fmt: skip
    batch = (lambda f: functools.partial(_lone, f)) if lone else (
        lambda f: jax.vmap(f, axis_name=MEMBERS))  # fmt: skip
    init_from_keys, evaluate, scheduled = map(batch, steps)
    chunk = _lone_chunk if lone else _members_chunk
    init = functools.partial(init_from_keys, keys)
    return Population(population, spec, hyperparams, init, functools.partial(chunk, spec),
                      evaluate, scheduled, abstract_state=jax.eval_shape(init), keys=keys,
                      init_from_keys=init_from_keys)  # fmt: skip


class Compiled(NamedTuple):
    """A population's functions jitted for a device mesh (see :mod:`td3_jax.sharding`).

    ``chunk(hp, state, iterations)`` donates its state; ``evaluate(state)`` evaluates with the
    run's key schedule; metrics and evaluation returns come back replicated. ``hyperparams``: the
    members' settings, replicated on the mesh (the ``hp`` to pass to ``chunk``).
    """

    shardings: Any
    hyperparams: training.Hyperparams
    init: Callable[[], TrainState]
    chunk: Callable[..., tuple[TrainState, dict[str, jax.Array]]]
    evaluate: Callable[[TrainState], jax.Array]


def compile_for_mesh(program: Population, mesh: Any) -> Compiled:
    """Jits ``program`` with the state split over ``mesh`` (envs, replay), the rest replicated."""
    shardings = state_shardings(program.abstract_state, mesh)
    replicated = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
    return Compiled(
        shardings=shardings,
        hyperparams=jax.tree.map(lambda x: replicate(x, mesh), program.hyperparams),
        init=jax.jit(program.init, out_shardings=shardings),
        chunk=jax.jit(
            program.chunk,
            in_shardings=(replicated, shardings, replicated),
            out_shardings=(shardings, replicated),
            donate_argnums=1,
        ),
        evaluate=jax.jit(program.scheduled_evaluate, out_shardings=replicated),
    )


def _with_sharding(abstract: Any, shardings: Any) -> Any:
    return jax.tree.map(
        lambda a, s: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=s, weak_type=a.weak_type),
        abstract,
        shardings,
    )


def chunk_argument_specs(program: Population, shardings: Any) -> tuple[Any, Any, Any]:
    """The chunk's abstract arguments ``(hp, state, iterations)`` placed on a mesh: the state
    by ``shardings`` (:func:`td3_jax.sharding.state_shardings`), the others replicated."""
    mesh = jax.tree.leaves(shardings)[0].mesh
    replicated = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
    hp = jax.eval_shape(lambda: program.hyperparams)
    hp_spec = _with_sharding(hp, jax.tree.map(lambda _: replicated, hp))
    iterations = jax.ShapeDtypeStruct((), jnp.int32, sharding=replicated)
    return hp_spec, _with_sharding(program.abstract_state, shardings), iterations


def compile_ahead(compiled: Compiled, program: Population, with_init: bool = True,
                  stop: StopToken | None = None) -> Compiled:  # fmt: skip
    """``compiled`` with its functions compiled now, side by side, instead of at their first call.

    Each program is traced (Python, one at a time) and handed to a thread that compiles it
    while the next is traced: the chunk first, as it takes longest. (Compiling the evaluation
    during the first chunk instead gained nothing on G1: its autotuning waits for the GPU,
    which the chunk holds.) The returned functions are the compiled executables: calling them
    with other shapes or shardings raises instead of recompiling. Once ``stop`` is set, the
    compiles are no longer waited for (KeyboardInterrupt).
    """
    stop = stop if stop is not None else StopToken()
    hp_spec, state_spec, iterations = chunk_argument_specs(program, compiled.shardings)
    programs = {
        "chunk": lambda: compiled.chunk.lower(hp_spec, state_spec, iterations),
        "evaluate": lambda: compiled.evaluate.lower(state_spec),
    }
    if with_init:
        programs["init"] = compiled.init.lower
    futures = {}
    for name, lower in programs.items():
        futures[name] = in_background(lower().compile)
        stop.raise_if_set()
    return compiled._replace(**{name: result(f, stop) for name, f in futures.items()})
