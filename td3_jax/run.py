"""The host loop: call the compiled chunk, evaluate, log, checkpoint. Nothing else."""

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
from td3_jax.training import Trainer, TrainState, make_trainer

CONFIG_FILE = "config.json"


class NonFiniteError(RuntimeError):
    """A loss or parameter became NaN/inf; the run stopped and kept its last good checkpoint."""


def save_config(cfg: TrainConfig, out_dir: Path) -> None:
    (Path(out_dir) / CONFIG_FILE).write_text(json.dumps(dataclasses.asdict(cfg), indent=2) + "\n")


def load_config(out_dir: Path) -> TrainConfig:
    """The resolved config a run directory was started with."""
    path = Path(out_dir) / CONFIG_FILE
    if not path.exists():
        raise ConfigError(f"{out_dir} holds no {CONFIG_FILE}: not a td3-jax run directory")
    raw = json.loads(path.read_text())
    if raw.get("hidden_sizes") is not None:
        raw["hidden_sizes"] = tuple(raw["hidden_sizes"])
    known = {f.name for f in dataclasses.fields(TrainConfig)}
    return TrainConfig(**{k: v for k, v in raw.items() if k in known})


def eval_key(cfg: TrainConfig, chunk_index: int) -> jax.Array:
    """The evaluation key after chunk ``chunk_index``: independent of stops and resumes."""
    return jax.random.fold_in(jax.random.PRNGKey(cfg.seed + 1_000_003), chunk_index)


def return_stats(returns: np.ndarray) -> dict[str, float]:
    returns = np.asarray(returns, np.float64)
    return {
        "eval_return_mean": float(returns.mean()),
        "eval_return_std": float(returns.std()),
        "eval_return_min": float(returns.min()),
        "eval_return_max": float(returns.max()),
    }


def restore_state(trainer: Trainer, out_dir: Path) -> tuple[TrainState, dict, int]:
    """The newest checkpoint of a run directory, checked against the trainer's state layout."""
    checkpointer = Checkpointer(Path(out_dir) / "checkpoints", trainer.config.keep_checkpoints)
    try:
        abstract = jax.eval_shape(trainer.init, jax.random.PRNGKey(0))
        return checkpointer.restore(abstract)
    finally:
        checkpointer.close()


def train(
    cfg: TrainConfig,
    out_dir: Path,
    *,
    resume: bool = False,
    progress: bool = True,
    stop_after_chunks: int | None = None,
    time_budget_s: float | None = None,
) -> list[dict[str, Any]]:
    """Trains ``cfg`` into ``out_dir``; returns the evaluation records written this call.

    Args:
      resume: continue from the newest checkpoint in ``out_dir`` (which must exist).
      progress: show a live progress display.
      stop_after_chunks: stop (as if interrupted) after this many chunks of this call; for tests.
      time_budget_s: stop after the first chunk that ends past this many seconds of the run's
        wall-clock (compile included; counted across resumes). The run stays resumable.
    """
    validate(cfg)
    out_dir = Path(out_dir)
    trainer = make_trainer(cfg)
    checkpointer = Checkpointer(out_dir / "checkpoints", cfg.keep_checkpoints)
    if resume:
        if checkpointer.latest_step() is None:
            raise CheckpointError(f"--resume given but {out_dir / 'checkpoints'} has no checkpoint")
        abstract = jax.eval_shape(trainer.init, jax.random.PRNGKey(0))
        state, meta, start_chunk = checkpointer.restore(abstract)
        state = jax.device_put(state, jax.devices()[0])
        wall_offset = float(meta["wall_time_s"])
    else:
        if checkpointer.latest_step() is not None:
            raise ConfigError(f"{out_dir} already holds a run; pass --resume or choose a new --out")
        out_dir.mkdir(parents=True, exist_ok=True)
        start_chunk, wall_offset = 0, 0.0
    save_config(cfg, out_dir)
    logger = MetricsLogger(
        out_dir, resume_env_steps=start_chunk * steps_per_chunk(cfg) if resume else None
    )

    start = time.perf_counter()
    if not resume:
        state = jax.device_put(
            jax.jit(trainer.init)(jax.random.PRNGKey(cfg.seed)), jax.devices()[0]
        )
    chunk = jax.jit(trainer.chunk, donate_argnums=0)
    evaluate = jax.jit(trainer.evaluate)
    records = []
    display = _Progress(cfg, start_chunk, enabled=progress)
    try:
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
            state, metrics = chunk(state)
            metrics = {k: float(v) for k, v in jax.device_get(metrics).items()}
            chunk_seconds = time.perf_counter() - chunk_start
            env_steps = int(state.env_steps)
            _check_finite(metrics, env_steps, checkpointer.latest_step(), cfg)
            returns = np.asarray(evaluate(state, eval_key(cfg, index)))
            record = {
                "env": cfg.env,
                "algo": cfg.algo,
                "seed": cfg.seed,
                "env_steps": env_steps,
                "updates": int(state.agent.step),
                "wall_time_s": wall_offset + time.perf_counter() - start,
                **return_stats(returns),
                "env_steps_per_s": steps_per_chunk(cfg) / chunk_seconds,
                **{k: v for k, v in metrics.items() if k != "params_finite"},
            }
            logger.write(record)
            records.append(record)
            last_chunk = (
                index + 1 == cfg.num_chunks
                or (stop_after_chunks is not None and index + 1 - start_chunk >= stop_after_chunks)
                or (time_budget_s is not None and record["wall_time_s"] >= time_budget_s)
            )
            if last_chunk or (index + 1) % cfg.checkpoint_every == 0:
                checkpointer.save(
                    index + 1, state, {"wall_time_s": record["wall_time_s"], "env_steps": env_steps}
                )
            display.update(record)
    finally:
        display.close()
        logger.close()
        checkpointer.close()
        plot_curve(out_dir)
    return records


def steps_per_chunk(cfg: TrainConfig) -> int:
    return cfg.iters_per_chunk * cfg.env_steps_per_iter


def _check_finite(metrics: dict, env_steps: int, last_checkpoint: int | None, cfg: TrainConfig):
    bad = [k for k in ("critic_loss", "actor_loss", "q_mean") if not math.isfinite(metrics[k])]
    if metrics["params_finite"] < 1.0:
        bad.append("parameters")
    if bad:
        kept = (
            f"the last good checkpoint (after {last_checkpoint * steps_per_chunk(cfg)} env steps) "
            "is kept"
            if last_checkpoint
            else "no checkpoint had been written yet"
        )
        raise NonFiniteError(
            f"non-finite {', '.join(bad)} in the chunk ending at env step {env_steps}; "
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
