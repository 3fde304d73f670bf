"""Reading a finished run back (``td3-jax eval``, ``render`` and ``export``): its program, its
newest checkpoint restored onto one device and its members evaluated, once a factory's
environment is known to be the one the run trained on
(:func:`td3_jax.runner.rundir.check_environment_unchanged`).

Nothing here writes into the run directory; its files, lock and config record are
:mod:`td3_jax.runner.rundir`'s.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import jax
import numpy as np

from td3_jax.common.runtime import awaiting_device
from td3_jax.config.build import bind_environment, make_population
from td3_jax.config.schema import ConfigError, TrainConfig
from td3_jax.core import population as pop
from td3_jax.core.population import Member, Population
from td3_jax.core.training import ring_as_saved
from td3_jax.envs.custom import OBJECT_PREFIX
from td3_jax.runner.checkpoint import Checkpointer
from td3_jax.runner.programs import run_compiled
from td3_jax.runner.rundir import (
    CHECKPOINTS,
    CONFIG_FILE,
    check_config_unedited,
    check_environment_unchanged,
    check_unedited,
    checkpoint_steps,
    load_config,
    load_members,
    no_checkpoint_error,
)
from td3_jax.runner.sharding import make_mesh, state_shardings

__all__ = [
    "evaluate_run",
    "restore_on_one_device",
    "restore_state",
    "run_program",
]


def restore_state(population: Population, out_dir: Path, keep: int = 3, shardings: Any = None):
    """``(state, meta, step)`` of the newest good checkpoint of a run directory, checked against
    the population's state layout (every leaf ``[members, ...]``; nothing is created in
    ``out_dir``)."""
    checkpointer = Checkpointer(Path(out_dir) / CHECKPOINTS, keep, create=False)
    try:
        return checkpointer.restore(population.abstract_state, shardings=shardings,
                                    resize=ring_as_saved)  # fmt: skip
    finally:
        checkpointer.close()


def run_program(
    out_dir: Path, eval_envs: int | None = None, env: Any = None
) -> tuple[TrainConfig, list[Member], Population]:
    """``(config, members, program)`` of a run directory; nothing is compiled or restored yet.
    The program's state is the run's own (its checkpoints restore into it); with ``eval_envs``
    its evaluation runs that many episodes after the chunk, also for a run that evaluated
    inside its chunks (whose checkpoints hold its own evaluation worlds). ``env``: the
    environment object of a run trained on one (``object/<name>``: none can be made from
    config.json). A factory's or object's environment must be the one the run trained on
    (:func:`check_environment_unchanged`), and config.json's settings those its newest intact
    checkpoint was written with (:func:`check_config_unedited`)."""
    cfg = _physics_here(load_config(out_dir))
    check_config_unedited(out_dir, cfg)  # (before the environment is made from it)
    population = load_members(out_dir, cfg)
    made = _handed_environment(cfg, env)
    program = make_population(cfg, population, env=made)
    check_environment_unchanged(out_dir, cfg.env, program.spec.env)
    if eval_envs is None:
        return cfg, population, program
    spec = dataclasses.replace(program.spec, eval_envs=eval_envs, eval_in_chunk=False)
    evaluating = pop.make_population(spec, program.hyperparams, population)
    evaluating = evaluating._replace(abstract_state=program.abstract_state)
    return dataclasses.replace(cfg, eval_envs=eval_envs), population, evaluating


def _handed_environment(cfg: TrainConfig, env: Any) -> Any:
    """The environment ``env`` made for ``cfg``'s run (``None``: none handed, made from
    config.json); a ConfigError where the run did not train on an object."""
    if env is None:
        return None
    if not cfg.env.startswith(OBJECT_PREFIX):
        raise ConfigError(
            f"env= is for a run trained on an environment object; this run trained on "
            f"{cfg.env}, which td3-jax makes itself: leave env= out"
        )
    bound, made = bind_environment(cfg, env)
    if bound.env != cfg.env:
        raise ConfigError(f"this run trained on {cfg.env}; the environment handed over is "
                          f"{bound.env}: hand over the run's own")  # fmt: skip
    return made


def _physics_here(cfg: TrainConfig) -> TrainConfig:
    """``cfg``, checked: a run trained on MuJoCo Warp holds Warp's data in its checkpoints, so
    it is read back only where Warp runs (a :class:`ConfigError` naming what is missing)."""
    from td3_jax.envs import physics

    missing = physics.warp_missing() if cfg.impl == "warp" else None
    if missing:
        raise ConfigError(f"the run trained on MuJoCo Warp, whose data its checkpoints hold, "
                          f"and {missing}; read it where Warp runs")  # fmt: skip
    return cfg


def restore_on_one_device(program: Population, out_dir: Path) -> tuple[Any, dict]:
    """``(state, meta)`` of the newest good checkpoint of ``out_dir`` on one device, whatever
    device count wrote it (every leaf ``[members, ...]``); where it has none, a ConfigError
    that says why (:func:`~td3_jax.runner.rundir.no_checkpoint_error`), as where config.json was
    edited since the checkpoint (:func:`~td3_jax.runner.rundir.check_unedited`, as a resume
    does)."""
    if not checkpoint_steps(out_dir):
        raise no_checkpoint_error(out_dir)
    shardings = state_shardings(program.abstract_state, make_mesh(1))
    state, meta, _ = restore_state(program, out_dir, shardings=shardings)
    path = Path(out_dir) / CONFIG_FILE
    check_unedited(meta.get("settings"), load_config(out_dir), path)
    return state, meta


def evaluate_run(
    out_dir: Path, episodes: int, seed: int, env: Any = None
) -> tuple[TrainConfig, list[Member], dict, np.ndarray]:
    """Re-evaluates every member of a run's newest checkpoint on ``episodes`` episodes.

    Returns ``(config, members, checkpoint meta, returns [members, episodes])``; member ``k``
    uses the ``k``-th key of ``jax.random.split(PRNGKey(seed), members)``. Restores onto one
    device, whatever device count wrote the checkpoint. ``env``: the environment object of a
    run trained on one (:func:`run_program`).
    """
    cfg, population, program = run_program(out_dir, eval_envs=episodes, env=env)
    state, meta = restore_on_one_device(program, out_dir)
    keys = jax.random.split(jax.random.PRNGKey(seed), len(population))
    with awaiting_device():  # (a Ctrl-C leaves the evaluation running on the device)
        returns = run_compiled(
            cfg,
            program.evaluate,
            state,
            keys,
            doing=f"evaluating {episodes:,} episodes of each member",
        )
        returns = np.asarray(returns)
    return cfg, population, meta, returns
