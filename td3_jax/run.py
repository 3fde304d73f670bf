"""The host loop: call the compiled chunk, evaluate, log, checkpoint. Nothing else.

A run trains a *population* (:mod:`td3_jax.population`): one seed by default, ``--seeds K``
seeds, or every combination of a sweep times the seeds, all in one compiled program.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np

from td3_jax.checkpoint import Checkpointer
from td3_jax.config import TrainConfig, validate
from td3_jax.logger import MetricsLogger, plot_curve
from td3_jax.population import (
    Population,
    compile_ahead,
    compile_for_mesh,
    make_population,
    members,
)
from td3_jax.rundir import (  # (re-exported: run.py was their home)
    CONFIG_FILE,
    MEMBERS_FILE,
    check_fresh,
    check_resume,
    load_config,
    load_members,
    open_run_dir,
    run_info,
    save_config,
)
from td3_jax.sharding import check_divisible, host_value, make_mesh
from td3_jax.stats import population_stats, return_stats

__all__ = [
    "CONFIG_FILE",
    "MEMBERS_FILE",
    "NonFiniteError",
    "load_config",
    "load_members",
    "restore_state",
    "save_config",
    "train",
]


class NonFiniteError(RuntimeError):
    """A loss or parameter became NaN/inf; the run stopped and kept its last good checkpoint."""


def restore_state(population: Population, out_dir: Path, keep: int = 3, shardings=None):
    """The newest checkpoint of a run directory, checked against the population's state layout."""
    checkpointer = Checkpointer(Path(out_dir) / "checkpoints", keep)
    try:
        return checkpointer.restore(population.abstract_state, shardings=shardings)
    finally:
        checkpointer.close()


def train(
    cfg: TrainConfig,
    out_dir: Path,
    *,
    resume: bool = False,
    progress: bool = True,
    sweep: dict[str, list[float]] | None = None,
    stop_after_chunks: int | None = None,
    time_budget_s: float | None = None,
    devices: int | None = None,
    preset: str | None = None,
) -> list[dict[str, Any]]:
    """Trains ``cfg`` (its ``seeds`` x the ``sweep`` combinations) into ``out_dir``.

    Returns the evaluation records written by this call (also appended to metrics.jsonl). The
    run holds ``out_dir``'s lock throughout (see :mod:`td3_jax.rundir`); a directory in use,
    or one holding a previous run when ``resume`` is off, is refused before anything is written.

    Args:
      resume: continue from the newest checkpoint in ``out_dir`` (which must exist); the
        members are those saved in the run directory. ``cfg`` must equal the saved config but
        for ``total_steps``, ``keep_checkpoints``, ``checkpoint_every`` and ``eval_envs``
        (recorded in config.json under ``resume_changes``).
      progress: show a live progress display.
      sweep: float settings to vary, e.g. ``{"actor_lr": [1e-3, 3e-4]}``; every combination
        trains ``cfg.seeds`` seeds, all in one program.
      stop_after_chunks: stop (as if interrupted) after this many chunks of this call; for tests.
      time_budget_s: stop after the first chunk that ends past this many seconds of the run's
        wall-clock (compile included; counted across resumes). The run stays resumable.
      devices: data-parallel over this many devices (default: all; see :mod:`td3_jax.sharding`).
        num_envs and batch_size stay global, so the numbers do not depend on the device count.
      preset: the name of the preset ``cfg`` came from, recorded in config.json.
    """
    validate(cfg)
    mesh = make_mesh(devices)
    check_divisible(cfg, mesh.size)
    writer = jax.process_index() == 0  # several processes: one writes the logs
    out_dir = Path(out_dir)
    if resume:
        population, changes = check_resume(out_dir, cfg, sweep, writer=writer)
    else:
        check_fresh(out_dir, writer=writer)
        population, changes = members(cfg, sweep), {}
    program = make_population(cfg, population, devices=mesh.size)
    compiled = compile_for_mesh(program, mesh)
    run_lock = open_run_dir(out_dir, resume=resume, writer=writer)
    checkpointer = display = logger = None
    try:
        checkpointer = Checkpointer(out_dir / "checkpoints", cfg.keep_checkpoints)
        start = time.perf_counter()
        if resume:
            state, meta, start_chunk = checkpointer.restore(
                program.abstract_state, shardings=compiled.shardings
            )
            wall_offset = float(meta["wall_time_s"])
        else:
            start_chunk, wall_offset = 0, 0.0
        display = _Progress(cfg, start_chunk, enabled=progress and writer)
        compiled = compile_ahead(compiled, program, with_init=not resume)
        if not resume:
            state = compiled.init()
        if writer:
            at = start_chunk * steps_per_chunk(cfg)
            info = run_info(out_dir, resume=resume, preset=preset, changes=changes, at_env_steps=at)
            save_config(cfg, population, out_dir, info)
        logger = MetricsLogger(
            out_dir, resume_env_steps=start_chunk * steps_per_chunk(cfg), enabled=writer
        )
        chunk, evaluate = compiled.chunk, compiled.evaluate
        records: list[dict[str, Any]] = []
        for index in range(start_chunk, cfg.num_chunks):
            if stop_after_chunks is not None and index - start_chunk >= stop_after_chunks:
                break
            if (
                records
                and time_budget_s is not None
                and records[-1]["wall_time_s"] >= time_budget_s
            ):
                break
            chunk_start = time.perf_counter()
            state, metrics = chunk(compiled.hyperparams, state)
            metrics = {k: host_value(v) for k, v in metrics.items()}
            chunk_seconds = time.perf_counter() - chunk_start
            env_steps = int(metrics.pop("env_steps")[0])
            updates = int(metrics.pop("agent_steps")[0])
            metrics = {k: v.astype(np.float64) for k, v in metrics.items()}
            _check_finite(metrics, population, env_steps, checkpointer.latest_step(), cfg)
            returns = host_value(evaluate(state))
            record = _record(cfg, population, updates, metrics, returns, env_steps)
            record["wall_time_s"] = wall_offset + time.perf_counter() - start
            record["env_steps_per_s"] = len(population) * steps_per_chunk(cfg) / chunk_seconds
            record["devices"] = mesh.size
            logger.write(record)
            records.append(record)
            last = (
                index + 1 == cfg.num_chunks
                or (stop_after_chunks is not None and index + 1 - start_chunk >= stop_after_chunks)
                or (time_budget_s is not None and record["wall_time_s"] >= time_budget_s)
            )
            if last or (index + 1) % cfg.checkpoint_every == 0:
                meta = {"wall_time_s": record["wall_time_s"], "env_steps": env_steps}
                checkpointer.save(index + 1, state, meta)
            display.update(record)
    finally:
        if display is not None:
            display.close()
        if logger is not None:
            logger.close()
        if checkpointer is not None:
            checkpointer.close()
        if writer and logger is not None:
            plot_curve(out_dir)
        run_lock.release()
    return records


def steps_per_chunk(cfg: TrainConfig) -> int:
    """Environment steps of one member in one chunk."""
    return cfg.steps_per_chunk


def _record(cfg, population, updates, metrics, returns, env_steps) -> dict[str, Any]:
    record: dict[str, Any] = {
        "env": cfg.env,
        "algo": cfg.algo,
        "seed": cfg.seed,
        "members": len(population),
        "env_steps": env_steps,
        "updates": updates,
    }
    scalars = {k: float(np.mean(v)) for k, v in metrics.items() if k != "params_finite"}
    if len(population) == 1:
        return {**record, **return_stats(returns[0]), **scalars}
    record.update(population_stats(returns))
    record.update(scalars)
    record["per_member"] = [
        {
            "seed": m.seed,
            "settings": dict(m.overrides),
            **return_stats(returns[i]),
            "critic_loss": float(metrics["critic_loss"][i]),
            "actor_loss": float(metrics["actor_loss"][i]),
        }
        for i, m in enumerate(population)
    ]
    return record


def _check_finite(metrics, population, env_steps, last_checkpoint, cfg) -> None:
    bad = []
    for i, member in enumerate(population):
        names = [
            k for k in ("critic_loss", "actor_loss", "q_mean") if not math.isfinite(metrics[k][i])
        ]
        if metrics["params_finite"][i] < 1.0:
            names.append("parameters")
        if names:
            who = f" ({member.label()})" if len(population) > 1 else ""
            bad.append(", ".join(names) + who)
    if bad:
        kept = (
            f"the last good checkpoint (after {last_checkpoint * steps_per_chunk(cfg)} env steps) "
            "is kept"
            if last_checkpoint
            else "no checkpoint had been written yet"
        )
        raise NonFiniteError(
            f"non-finite {'; '.join(bad)} in the chunk ending at env step {env_steps}; "
            f"stopped, {kept}"
        )


class _Progress:
    """A rich progress bar: env steps, env steps/s, last evaluation return, time left."""

    def __init__(self, cfg: TrainConfig, start_chunk: int, enabled: bool):
        self.enabled = enabled
        if not enabled:
            return
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

        self._progress = Progress(
            TextColumn("[bold]{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("env steps"),
            TextColumn("{task.fields[rate]}"),
            TextColumn("eval {task.fields[ret]}"),
            TimeElapsedColumn(),
            TimeRemainingColumn(),
        )
        total = cfg.num_chunks * steps_per_chunk(cfg)
        self._task = self._progress.add_task(
            f"{cfg.algo} {cfg.env}",
            total=total,
            completed=start_chunk * steps_per_chunk(cfg),
            rate="compiling...",
            ret="-",
        )
        self._progress.start()

    def update(self, record: dict) -> None:
        if self.enabled:
            self._progress.update(
                self._task,
                completed=record["env_steps"],
                rate=f"{record['env_steps_per_s']:,.0f}/s",
                ret=f"{record['eval_return_mean']:.1f}",
            )

    def close(self) -> None:
        if self.enabled:
            self._progress.stop()
