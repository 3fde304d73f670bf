"""Many independent runs (seeds x hyperparameter settings) as one compiled program.

A *population* is a list of members, each a seed plus optional overrides of float
hyperparameters. Its train state is the single-run :class:`~td3_jax.training.TrainState` with a
leading member axis; the chunk is ``jax.vmap`` of the single-run chunk, with each member's float
hyperparameters passed in as traced values (so a sweep is a vmap, not a recompile per value).
A population of one runs the single-run program unbatched (no vmap overhead) behind a leading
axis of size 1, so the host loop has one code path.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from td3_jax import envs
from td3_jax.config import ConfigError, TrainConfig, validate
from td3_jax.sharding import state_shardings
from td3_jax.training import TrainState, make_trainer

MEMBERS = "members"  # the vmap axis name of the population

#: Float settings a sweep may vary (each member gets its own value, traced inside one program).
SWEEPABLE = (
    "actor_lr",
    "critic_lr",
    "tau",
    "discount",
    "expl_noise",
    "policy_noise",
    "noise_clip",
    "ou_sigma",
    "ou_theta",
)


@dataclasses.dataclass(frozen=True)
class Member:
    seed: int
    overrides: tuple[tuple[str, float], ...] = ()

    def label(self) -> str:
        settings = " ".join(f"{k}={v:g}" for k, v in self.overrides)
        return f"{settings} seed={self.seed}".strip()


def members(cfg: TrainConfig, sweep: dict[str, Sequence[float]] | None = None) -> list[Member]:
    """Every combination of the swept values, times ``cfg.seeds`` seeds from ``cfg.seed``."""
    sweep = {k: list(v) for k, v in (sweep or {}).items() if v}
    unknown = sorted(set(sweep) - set(SWEEPABLE))
    if unknown:
        raise ConfigError(f"cannot sweep {unknown}; sweepable: {', '.join(SWEEPABLE)}")
    unused = {
        "policy_noise": cfg.algo == "ddpg",
        "noise_clip": cfg.algo == "ddpg",
        "expl_noise": cfg.exploration != "gaussian",
        "ou_sigma": cfg.exploration != "ou",
        "ou_theta": cfg.exploration != "ou",
    }
    idle = sorted(name for name in sweep if unused.get(name, False))
    if idle:
        raise ConfigError(
            f"sweeping {', '.join(idle)} changes nothing with --algo {cfg.algo} and "
            f"--exploration {cfg.exploration}"
        )
    names = sorted(sweep)
    combos = list(itertools.product(*(sweep[n] for n in names))) or [()]
    for combo in combos:
        validate(dataclasses.replace(cfg, **dict(zip(names, combo, strict=True))))
    return [
        Member(seed=cfg.seed + k, overrides=tuple(zip(names, map(float, combo), strict=True)))
        for combo in combos
        for k in range(cfg.seeds)
    ]


class Population(NamedTuple):
    """Pure functions over a population state (every leaf ``[num_members, ...]``).

    Attributes:
      init: ``init() -> state``.
      chunk: ``chunk(state) -> (state, metrics[num_members])``.
      evaluate: ``evaluate(state, keys[num_members]) -> returns[num_members, eval_envs]``.
      abstract_state: shapes and dtypes of the state (for restoring checkpoints).
    """

    members: list[Member]
    env: envs.Environment
    init: Callable[[], TrainState]
    chunk: Callable[[TrainState], tuple[TrainState, dict[str, jax.Array]]]
    evaluate: Callable[[TrainState, jax.Array], jax.Array]
    abstract_state: Any


def make_population(cfg: TrainConfig, population: list[Member], devices: int = 1) -> Population:
    """Builds the batched training functions of ``population`` (all sharing ``cfg``'s shapes).

    ``devices``: how many devices the environments will be split over; resets then gather and
    scatter within each device's environments (the numbers do not depend on it).
    """
    env = envs.make(cfg.env, backend=cfg.env_backend, episode_length=cfg.episode_length)
    keys = jnp.stack([jax.random.PRNGKey(m.seed) for m in population])
    names = sorted({k for m in population for k, _ in m.overrides})
    values = {
        n: jnp.asarray([dict(m.overrides)[n] for m in population], jnp.float32) for n in names
    }

    if len(population) == 1 and not names:
        single = make_trainer(cfg, env, env_groups=devices)
        add_axis = lambda tree: jax.tree.map(lambda x: x[None], tree)
        drop_axis = lambda tree: jax.tree.map(lambda x: x[0], tree)

        def init():
            return add_axis(single.init(keys[0]))

        def chunk(state):
            return add_axis(single.chunk(drop_axis(state)))

        def evaluate(state, eval_keys):
            return single.evaluate(drop_axis(state), eval_keys[0])[None]

    else:

        def trainer_for(hparams):
            return make_trainer(
                dataclasses.replace(cfg, **hparams), env, axis_name=MEMBERS, env_groups=devices
            )

        def init():
            return jax.vmap(lambda key, h: trainer_for(h).init(key))(keys, values)

        def chunk(state):
            return jax.vmap(lambda s, h: trainer_for(h).chunk(s), axis_name=MEMBERS)(state, values)

        def evaluate(state, eval_keys):
            return jax.vmap(lambda s, k, h: trainer_for(h).evaluate(s, k), axis_name=MEMBERS)(
                state, eval_keys, values
            )

    return Population(population, env, init, chunk, evaluate, jax.eval_shape(init))


class Compiled(NamedTuple):
    """A population's functions jitted for a device mesh (see :mod:`td3_jax.sharding`).

    ``chunk`` donates its state; metrics and evaluation returns come back replicated.
    """

    shardings: Any
    init: Callable[[], TrainState]
    chunk: Callable[[TrainState], tuple[TrainState, dict[str, jax.Array]]]
    evaluate: Callable[[TrainState, jax.Array], jax.Array]


def compile_for_mesh(program: Population, mesh: Any) -> Compiled:
    """Jits ``program`` with the state split over ``mesh`` (envs, replay), the rest replicated."""
    shardings = state_shardings(program.abstract_state, mesh)
    replicated = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
    return Compiled(
        shardings=shardings,
        init=jax.jit(program.init, out_shardings=shardings),
        chunk=jax.jit(
            program.chunk,
            in_shardings=(shardings,),
            out_shardings=(shardings, replicated),
            donate_argnums=0,
        ),
        evaluate=jax.jit(program.evaluate, out_shardings=replicated),
    )


def compile_ahead(
    compiled: Compiled, program: Population, keys_spec: Any, with_init: bool = True
) -> Compiled:
    """``compiled`` with its functions compiled now, side by side, instead of at their first call.

    Tracing is sequential (Python), but XLA compiles the chunk, the evaluation and the init in
    parallel threads, which shortens the start-up of a run (on MJX environments the chunk and
    the evaluation each take seconds to compile). The returned functions are the compiled
    executables: calling them with other shapes or shardings raises instead of recompiling.
    ``keys_spec``: shape and dtype of the evaluation keys (``[num_members, ...]``).
    """
    state_spec = jax.tree.map(
        lambda a, s: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=s, weak_type=a.weak_type),
        program.abstract_state,
        compiled.shardings,
    )
    replicated = jax.sharding.NamedSharding(
        jax.tree.leaves(compiled.shardings)[0].mesh, jax.sharding.PartitionSpec()
    )
    keys_spec = jax.ShapeDtypeStruct(keys_spec.shape, keys_spec.dtype, sharding=replicated)
    lowered = {
        "chunk": compiled.chunk.lower(state_spec),
        "evaluate": compiled.evaluate.lower(state_spec, keys_spec),
    }
    if with_init:
        lowered["init"] = compiled.init.lower()
    with ThreadPoolExecutor(max_workers=len(lowered)) as pool:
        futures = {name: pool.submit(low.compile) for name, low in lowered.items()}
        return compiled._replace(**{name: f.result() for name, f in futures.items()})
