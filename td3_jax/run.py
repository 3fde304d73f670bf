"""The host loop: call the compiled chunk, evaluate, log, checkpoint. Nothing else.

A run trains a *population* (:mod:`td3_jax.population`): one seed by default, ``--seeds K``
seeds, or every combination of a sweep times the seeds, all in one compiled program.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np

from td3_jax.checkpoint import Checkpointer, CheckpointError
from td3_jax.config import ConfigError, TrainConfig, validate
from td3_jax.logger import MetricsLogger, plot_curve
from td3_jax.population import (
    Member,
    Population,
    compile_ahead,
    compile_for_mesh,
    make_population,
    members,
)
from td3_jax.sharding import check_divisible, host_value, make_mesh
from td3_jax.stats import population_stats, return_stats

CONFIG_FILE = "config.json"
MEMBERS_FILE = "members.json"


class NonFiniteError(RuntimeError):
    """A loss or parameter became NaN/inf; the run stopped and kept its last good checkpoint."""


def save_config(cfg: TrainConfig, population: list[Member], out_dir: Path) -> None:
    out_dir = Path(out_dir)
    (out_dir / CONFIG_FILE).write_text(json.dumps(dataclasses.asdict(cfg), indent=2) + "\n")
    listing = [{"seed": m.seed, "overrides": dict(m.overrides)} for m in population]
    (out_dir / MEMBERS_FILE).write_text(json.dumps(listing, indent=2) + "\n")


def load_config(out_dir: Path) -> TrainConfig:
    """The resolved config a run directory was started with."""
    path = Path(out_dir) / CONFIG_FILE
    if not path.exists():
        raise ConfigError(f"{out_dir} holds no {CONFIG_FILE}: not a td3-jax run directory")
    try:
        raw = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ConfigError(f"{path} is not valid JSON ({err})") from err
    if raw.get("hidden_sizes") is not None:
        raw["hidden_sizes"] = tuple(raw["hidden_sizes"])
    known = {f.name for f in dataclasses.fields(TrainConfig)}
    return TrainConfig(**{k: v for k, v in raw.items() if k in known})


def load_members(out_dir: Path, cfg: TrainConfig) -> list[Member]:
    """The members of a run directory (its seeds and swept settings)."""
    path = Path(out_dir) / MEMBERS_FILE
    if not path.exists():
        return members(cfg)
    return [
        Member(seed=int(m["seed"]), overrides=tuple(sorted(m["overrides"].items())))
        for m in json.loads(path.read_text())
    ]


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
) -> list[dict[str, Any]]:
    """Trains ``cfg`` (its ``seeds`` x the ``sweep`` combinations) into ``out_dir``.

    Returns the evaluation records written by this call (also appended to metrics.jsonl).

    Args:
      resume: continue from the newest checkpoint in ``out_dir`` (which must exist); the
        members are those saved in the run directory.
      progress: show a live progress display.
      sweep: float settings to vary, e.g. ``{"actor_lr": [1e-3, 3e-4]}``; every combination
        trains ``cfg.seeds`` seeds, all in one program.
      stop_after_chunks: stop (as if interrupted) after this many chunks of this call; for tests.
      time_budget_s: stop after the first chunk that ends past this many seconds of the run's
        wall-clock (compile included; counted across resumes). The run stays resumable.
      devices: data-parallel over this many devices (default: all; see :mod:`td3_jax.sharding`).
        num_envs and batch_size stay global, so the numbers do not depend on the device count.
    """
    validate(cfg)
    mesh = make_mesh(devices)
    check_divisible(cfg, mesh.size)
    writer = jax.process_index() == 0  # several processes: one writes the logs
    out_dir = Path(out_dir)
    population = load_members(out_dir, cfg) if resume else members(cfg, sweep)
    program = make_population(cfg, population, devices=mesh.size)
    compiled = compile_for_mesh(program, mesh)
    checkpointer = Checkpointer(out_dir / "checkpoints", cfg.keep_checkpoints)
    display = logger = None
    try:
        start = time.perf_counter()
        if resume:
            if checkpointer.latest_step() is None:
                raise CheckpointError(
                    f"--resume given but {out_dir / 'checkpoints'} has no checkpoint"
                )
            state, meta, start_chunk = checkpointer.restore(
                program.abstract_state, shardings=compiled.shardings
            )
            wall_offset = float(meta["wall_time_s"])
        else:
            if checkpointer.latest_step() is not None:
                raise ConfigError(
                    f"{out_dir} already holds a run; pass --resume or choose a new --out"
                )
            out_dir.mkdir(parents=True, exist_ok=True)
            start_chunk, wall_offset = 0, 0.0
        display = _Progress(cfg, start_chunk, enabled=progress and writer)
        compiled = compile_ahead(compiled, program, with_init=not resume)
        if not resume:
            state = compiled.init()
        if writer:
            save_config(cfg, population, out_dir)
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
        checkpointer.close()
        if writer and logger is not None:
            plot_curve(out_dir)
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
