"""The host loop: call the compiled chunk, evaluate, log, checkpoint. Nothing else.

A run trains a *population* (:mod:`td3_jax.core.population`): one seed by default, ``--seeds K``
seeds, or every combination of a sweep times the seeds, all in one compiled program.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import math
import os
import re
import sys
import time
import warnings
from collections.abc import Callable
from concurrent.futures import Future
from functools import partial
from pathlib import Path
from typing import Any

import jax
import numpy as np

from td3_jax.common.errors import (
    WRITE_ERRNOS,
    ConfigError,
    NonFiniteError,
    OutputWriteError,
    PhysicsOverflowError,
    ProcessLostError,
    outside_stacklevel,
)
from td3_jax.common.keywords import parameters_named
from td3_jax.common.library_noise import filtered_stderr
from td3_jax.common.runtime import StopToken, awaiting_device, result
from td3_jax.config import presets
from td3_jax.config.build import bind_environment, members, validated
from td3_jax.config.python_names import field_names
from td3_jax.config.schema import (
    TrainConfig,
    check_is_config,
    eval_every_within_run,
    rounding_note,
)
from td3_jax.core.population import Member
from td3_jax.core.stats import population_stats, return_stats
from td3_jax.core.training import observations_finite, ring_as_saved
from td3_jax.envs import warp_kernels
from td3_jax.runner import programs, tracking
from td3_jax.runner.checkpoint import Checkpointer, CheckpointWriteError
from td3_jax.runner.critic_growth import growth_warning
from td3_jax.runner.curves import plot_curve
from td3_jax.runner.logger import MetricsLogger, returns_by_setting, setting_label
from td3_jax.runner.memory import working_bytes
from td3_jax.runner.programs import Programs, Source
from td3_jax.runner.rundir import (
    CHECKPOINTS,
    CONFIG_FILE,
    check_environment_unchanged,
    check_fresh,
    check_resume,
    check_total_steps_reach,
    check_unedited,
    checkpoint_steps,
    ended_before_recording,
    environment_record,
    eval_every_as_saved,
    fixed_settings,
    load_config,
    nothing_to_do,
    open_run_dir,
    previous_outputs,
    resume_command,
    run_info,
    save_config,
)
from td3_jax.runner.sharding import (
    check_memory,
    host_value,
    make_mesh,
    prepared_agreed,
    replay_layout_warning,
    start_agreed,
    state_shardings,
    stop_agreed,
    stop_before_training,
    stop_failed,
)

__all__ = ["RunCompleteWarning", "stop_before_next_training", "train"]


class _CallCounter:
    """Counts this process's training calls: the processes of a ``jax.distributed`` run make
    the same calls, so the count names a call's stop decisions apart from an earlier call's."""

    def __init__(self) -> None:
        self.made = 0

    def __next__(self) -> int:
        self.made += 1
        return self.made - 1


_TRAIN_CALLS = _CallCounter()


def stop_before_next_training(reason: str) -> None:
    """Tells the other processes of this ``jax.distributed`` run that this one stops before its
    next training call (``"token"``: stopped; ``"error"``: failed): a process that fails between
    joining and training (a check of its own host's run directory, say) leaves none waiting for
    it (:func:`~td3_jax.runner.sharding.stop_before_training`). Nothing in one process."""
    stop_before_training(reason, call=_TRAIN_CALLS.made)


@parameters_named
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
    on_prepared: Callable[[], None] | None = None,
    program_dir: Path | None = None,
    stop: StopToken | None = None,
    env: Any = None,
    on_started: Callable[[int], None] | None = None,
) -> list[dict[str, Any]]:
    """Trains ``cfg`` (its ``seeds`` x the ``sweep`` combinations) into ``out_dir``, locked
    throughout (:mod:`~td3_jax.runner.rundir`; a busy one, or a used one without ``resume``, is
    refused), until ``cfg.total_steps`` rounded up to a whole iteration
    (:attr:`TrainConfig.run_steps`). Returns this call's records (also in metrics.jsonl; none
    for a resumed run already complete, which warns: :class:`RunCompleteWarning`). A full disk
    stops it with ``OutputWriteError``; a ``cfg`` or ``out_dir`` of a wrong type, ``TypeError``.

    Args:
      resume: continue from the newest good checkpoint in ``out_dir``; ``cfg`` may differ from
        the saved config only in :data:`td3_jax.runner.rundir.SAFE_ON_RESUME` (and
        ``eval_every`` as :func:`~td3_jax.runner.rundir.eval_every_as_saved` takes it).
      progress: show progress (one line per evaluation; on a terminal, a live bar below).
      sweep: float settings to vary (``{"actor_lr": [1e-3, 3e-4]}``), ``cfg.seeds`` seeds of
        each in one program; a member gone non-finite is marked diverged (all: the run stops).
      stop_after_chunks: stop (as if interrupted) after this many chunks of this call.
      time_budget_s: stop after the first chunk that ends past this many seconds of the run's
        wall-clock, counted across resumes (the run stays resumable).
      devices: data-parallel over this many devices (default: all); the numbers do not change.
      preset: the preset ``cfg`` came from, a label for config.json that changes no setting
        (those: ``td3_jax.config.presets.preset(NAME)``); no preset's name: a ConfigError.
      program_dir: the traced programs' store (:mod:`td3_jax.runner.program_cache`).
      on_prepared: called once settings and environment are checked (nothing compiled yet); its
        caller says how ``eval_every`` rounds (the command), the run then does not.
      on_started: called with the env steps the run starts from (0 when fresh).
      stop: a :class:`~td3_jax.common.runtime.StopToken` that stops the run as a Ctrl-C would.
      env: an environment object instead of ``cfg.env`` (recorded as ``object/<name>``).
    """
    out_dir, writer = _checked(cfg, out_dir, time_budget_s, preset), jax.process_index() == 0
    stop, call = stop if stop is not None else StopToken(), next(_TRAIN_CALLS)
    cfg = _eval_every_within_run(cfg, out_dir, resume, progress and writer and on_prepared is None)
    prepared, run_lock = _prepared_and_opened(cfg, out_dir, resume, sweep, devices, writer,
                                              program_dir, env, stop, call)  # fmt: skip
    cfg, population, changes, source = prepared
    run = _Run(cfg, out_dir, population, source.mesh.size, writer, stop_after_chunks, time_budget_s,
               stop, env=source.env, call=call)  # fmt: skip
    try:
        _agree_prepared(run)
        _start_and_train(run, source, resume, progress, preset=preset, changes=changes,
                         on_prepared=on_prepared, on_started=on_started)  # fmt: skip
    finally:
        warp_kernels.drop_pending()  # (a run that ended before its first physics step)
        _finish(run, run_lock)
    return run.records


def _prepared_and_opened(
    cfg: TrainConfig, out_dir: Path, resume: bool, sweep: Any, devices: int | None,
    writer: bool, program_dir: Path | None, env: Any, stop: StopToken, call: int,
) -> tuple[tuple, Any]:  # fmt: skip
    """:func:`_prepare` (Warp's kernels may compile beside XLA's programs) and
    :func:`_open_run_dir`; a check of the writing process alone may stop it there, so the
    other processes are told (:func:`~td3_jax.runner.sharding.stop_before_training`)."""
    try:
        with warp_kernels.beside_compile():
            prepared = _prepare(cfg, out_dir, resume, sweep, make_mesh(devices), writer,
                                program_dir, env)  # fmt: skip
        return prepared, _open_run_dir(out_dir, resume, writer, prepared[:2])
    except BaseException:
        stop_before_training("token" if stop.is_set() else "error", call=call)
        raise


def _checked(cfg: Any, out_dir: Any, time_budget_s: float | None, preset: str | None) -> Path:
    """:func:`train`'s own arguments checked (``cfg`` a :class:`TrainConfig`, the budget
    positive, ``preset`` a preset's name); ``out_dir`` as a ``Path``, where it is one (a
    ``TypeError`` that names it)."""
    check_is_config(cfg)
    check_time_budget(time_budget_s)
    if preset is not None and preset not in presets.PRESETS:
        presets.preset(preset)  # (a ConfigError naming the closest presets)
    if isinstance(out_dir, (str, os.PathLike)) and os.fspath(out_dir):
        return Path(out_dir)
    raise TypeError(f"out_dir must be a directory's path (str or os.PathLike), got "
                    f"{out_dir!r} ({type(out_dir).__name__})")  # fmt: skip


def _eval_every_within_run(cfg: TrainConfig, out_dir: Path, resume: bool,
                           say: bool) -> TrainConfig:  # fmt: skip
    """A fresh run's ``cfg`` with ``eval_every`` as whole iterations and at most the run
    (:func:`~td3_jax.config.schema.eval_every_within_run`; a resume keeps the chunk its checkpoints
    were written with: :func:`~td3_jax.runner.rundir.eval_every_as_saved`); ``say``: print how
    it runs where it changed or is not whole iterations (the command says so itself)."""
    if resume:  # (without a config.json: the resume says there is nothing to resume)
        saved = Path(out_dir) / CONFIG_FILE
        return eval_every_as_saved(cfg, load_config(out_dir)) if saved.is_file() else cfg
    changed = eval_every_within_run(cfg)
    whole = cfg.env_steps_per_iter > 0 and cfg.eval_every % cfg.env_steps_per_iter == 0
    note = rounding_note(changed, cfg.eval_every)
    if say and note and (changed.eval_every != cfg.eval_every or not whole):
        print(field_names(note), flush=True)
    return changed


def _open_run_dir(out_dir: Path, resume: bool, writer: bool, run: tuple) -> Any:
    """:func:`~td3_jax.runner.rundir.open_run_dir` (``run``: the run's ``(cfg, population)``); a
    refusal also drops a Warp precompile started for the run
    (:func:`~td3_jax.envs.warp_kernels.drop_pending`)."""
    try:
        return open_run_dir(out_dir, resume=resume, writer=writer, run=run)
    except BaseException:
        warp_kernels.drop_pending()
        raise


def check_time_budget(seconds: float | None) -> None:
    """A one-line ConfigError for a time budget (``--time-budget-s``) that is not a positive,
    finite number of seconds (a negative one trained a chunk, then stopped)."""
    if seconds is not None and not (math.isfinite(seconds) and seconds > 0):
        raise ConfigError(f"--time-budget-s must be a positive number of seconds, got {seconds}")


def _start_and_train(run: _Run, source: Source, resume: bool, progress: bool, *,
                     preset: str | None, changes: Any,
                     on_prepared: Callable[[], None] | None = None,
                     on_started: Callable[[int], None] | None = None) -> None:  # fmt: skip
    """The run's start (restored, else fresh), its programs compiled and its chunks trained;
    a run already complete compiles and rewrites nothing, and one stopped before its first
    chunk writes no outputs (so the same command starts it again). A process of several that
    stops before training says so to the others (:func:`~td3_jax.runner.sharding.
    stop_before_training`), which stop where they would have started."""
    try:
        if on_prepared is not None:
            on_prepared()
        state = _start(run, source, resume)
        if on_started is not None:
            on_started(run.start_steps)
        if run.start_steps >= run.cfg.run_steps:
            if run.writer:
                said = nothing_to_do(run.out_dir, run.cfg, python=True)
                warnings.warn(said, RunCompleteWarning, stacklevel=outside_stacklevel())
            return
        _say_resuming(run)
        run.tracker = tracking.start(run.cfg, run.out_dir, resume=resume, enabled=run.writer)
        compiled, state = _compiled_and_state(run, source, state, say=progress and run.writer)
        if jax.process_count() == 1:  # (several agreed to start: their first chunk stops)
            run.stop.raise_if_set()  # (stopped as the state was made: nothing written yet)
        _write_and_train(run, compiled, state, progress, resume=resume, preset=preset,
                         changes=changes)  # fmt: skip
    except BaseException:
        _tell_the_others(run)
        raise


class RunCompleteWarning(UserWarning):
    """A resume (``resume=True``) found its run complete: :func:`train` trained nothing and
    returns no record (the command line says so in its own words instead)."""


def _tell_the_others(run: _Run) -> None:
    """Several processes: why this one stops where the others would wait for it. Before they
    agreed to start, where they agree (a stop, or an error: :func:`~td3_jax.runner.sharding.
    stop_before_training`); after, at the chunk it was in or would have started
    (:func:`~td3_jax.runner.sharding.stop_failed`; in the loop :func:`_loop` has said so)."""
    if not run.started_together:
        stop_before_training("token" if run.stop.is_set() else "error", call=run.call)
    else:
        stop_failed(run.last_chunk if run.last_chunk is not None else run.start_chunk,
                    call=run.call)  # fmt: skip


def _agree_prepared(run: _Run) -> None:
    """Once this process is prepared, before anything needs the others: where another was
    refused by its own checks, :class:`ProcessLostError` names it; where one was stopped, all
    stop here as interrupted (KeyboardInterrupt), before compiling
    (:func:`~td3_jax.runner.sharding.prepared_agreed`)."""
    if prepared_agreed("token" if run.stop.is_set() else "", call=run.call) == "token":
        run.stop.set()
        raise KeyboardInterrupt


def _agree_to_start(run: _Run) -> None:
    """Before any program of the run executes: KeyboardInterrupt where this process or (of
    several) another was asked to stop while they started (:func:`~td3_jax.runner.sharding.
    start_agreed`), so that all stop there, as interrupted, with nothing written."""
    if start_agreed("token" if run.stop.is_set() else "", call=run.call) == "token":
        run.stop.set()
    run.stop.raise_if_set()
    run.started_together = True


def _say_resuming(run: _Run) -> None:
    """The line a resumed run starts with (by the writing process; nothing for a fresh run)."""
    if not (run.writer and run.start_chunk):
        return
    path = run.out_dir / CHECKPOINTS / str(run.start_chunk)
    print(f"resuming from checkpoint {path} (env step {run.start_steps})", flush=True)


#: What shrinks the training programs' working memory (the train state's own size is checked
#: before they compile: :func:`td3_jax.runner.sharding.check_memory`).
_MEMORY_ADVICE = "fewer --eval-envs or --num-envs, or a smaller --batch-size"


def _write_and_train(run: _Run, compiled: Programs, state: Any, progress: bool, *, resume: bool,
                     preset: str | None, changes: Any) -> None:  # fmt: skip
    """config.json, the progress display, metrics.jsonl, TensorBoard and W&B, then the chunks;
    a write the disk refuses (of those or of a checkpoint) is kept in ``run.failed_write``
    for :func:`_finish` and re-raised."""
    try:
        _write_config(run, resume=resume, preset=preset, changes=changes)
        run.display = _Progress(run.cfg, run.start_steps, enabled=progress and run.writer)
        run.logger = MetricsLogger(run.out_dir, run.start_steps, enabled=run.writer,
                                   mirror=run.tracker)  # fmt: skip
        with programs.out_of_memory_as_config_error(jax.local_devices()[0], "training",
                                                    _MEMORY_ADVICE):  # fmt: skip
            _loop(run, compiled, state)
    except (OSError, CheckpointWriteError) as err:
        if isinstance(err, OSError) and not _refused_write(err):
            raise
        run.failed_write = err
        raise


def _finish(run: _Run, run_lock: Any) -> None:
    """Closes the run's outputs and unlocks its directory; a run stopped by a failed write
    then raises :class:`OutputWriteError` (once a checkpoint still being written has finished
    or failed, so the last good one is known)."""
    try:
        run.close()
    finally:
        run_lock.unlock()
    if run.failed_write is not None:
        raise _write_failure(run, run.failed_write) from run.failed_write


def _write_failure(run: _Run, err: Exception) -> OutputWriteError:
    """What ``err`` could not write, the run's last good checkpoint and how to go on, in one
    line (a checkpoint's error names the last good one too: that part is said once)."""
    out = run.out_dir
    if isinstance(err, OSError):
        what = f"could not write {err.filename or out}: {err.strerror or err}"
    else:
        what = re.split(r"; (?:the last good checkpoint is|there is no earlier checkpoint)",
                        str(err))[0]  # fmt: skip
    text, code = str(err).lower(), getattr(err, "errno", None)
    if code in (errno.ENOSPC, errno.EDQUOT) or "no space" in text or "quota" in text:
        fix = f"free space on the disk holding {out}"
    elif code in (errno.EROFS, errno.EACCES, errno.EPERM) or "read-only" in text or "permi" in text:
        fix = f"make {out} writable"
    else:
        fix = "fix that"
    steps = checkpoint_steps(out)
    if steps:
        newest = steps[-1]
        last = f"{out / CHECKPOINTS / str(newest)} (env step {_steps_after(run, newest)})"
        return OutputWriteError(f"{what}; the last good checkpoint is {last}; {fix}, then "
                                f"continue with: {resume_command(out)}")  # fmt: skip
    if previous_outputs(out):
        return OutputWriteError(f"{what}; no checkpoint was written, so there is nothing to "
                                f"resume: {fix}, then remove {out} (or choose another --out) "
                                "and start the run again")  # fmt: skip
    return OutputWriteError(f"{what}; no checkpoint was written (nor anything else to keep): "
                            f"{fix}, then start the run again")  # fmt: skip


def _compiled_and_state(run: _Run, source: Source, state: Any, say: bool = False
                        ) -> tuple[Programs, Any]:  # fmt: skip
    """The run's compiled programs, the state's room checked as soon as its shapes are known
    (:func:`td3_jax.runner.programs.compiled`), and its state: ``state`` restored, else initialised;
    KeyboardInterrupt where this process or another of the run was stopped meanwhile
    (:func:`_agree_to_start`).
    The checksum program of its checkpoints is lowered once the programs are traced (it would
    delay the chunk's compile by about a second on a robot: :func:`_prepare_save`), compiles
    beside them and is waited for before anything runs on the devices (no compile runs beside
    a chunk).
    ``say``: print that it compiles first (a log then shows where the time goes), and from
    which stored programs (:func:`td3_jax.runner.programs.find`). XLA's slow-compile alarm,
    MLIR's lines about a damaged stored program and XLA's GSPMD notice are left out of stderr
    meanwhile (the first becomes one line, the second is warned of by the program store, the
    third is td3-jax's choice: :func:`~td3_jax.common.library_noise.filtered_stderr`)."""
    if say:
        # (a stored program ran before: XLA's persistent cache likely holds it compiled)
        cached = " (or loading it from the cache)" if source.stored is not None else ""
        if source.stored is not None:
            print(f"using the traced programs stored in {source.directory / source.key}")
        print(f"compiling the training program{cached}...", flush=True)
    with filtered_stderr():
        check, traced = (partial(step, run, source.mesh) for step in (_check_room, _prepare_save))
        compiled = programs.compiled(source, run.stop, check=check, traced=traced)
    _wait_for_save_warmup(run)  # (before anything runs on the device)
    warp_kernels.wait_ready(run.stop)  # (before the first physics step)
    _agree_to_start(run)  # (a stop while the programs loaded from the cache too)
    return compiled, compiled.init() if state is None else state


def _prepare_save(run: _Run, mesh: Any, state: Any) -> None:
    """Once the programs are traced: the first checkpoint's checksum program, for the state of
    these shapes, lowered here and compiled on a thread beside them
    (:meth:`~td3_jax.runner.checkpoint.Checkpointer.prepare`)."""
    specs = programs.with_sharding(state, state_shardings(state, mesh))
    run.save_warmup = run.checkpointer.prepare(specs)


def _wait_for_save_warmup(run: _Run) -> None:
    """Waits for :func:`_prepare_save`'s compile; one that failed is said in one line (the
    first checkpoint then compiles it itself, and reports what stops it)."""
    if run.save_warmup is None:
        return
    try:
        result(run.save_warmup, run.stop)
    except Exception as err:  # e.g. no memory to compile in: the save itself will say
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        if run.writer:
            print(f"td3-jax: warning: the first checkpoint could not be prepared ahead "
                  f"({first}); it does that work when it is written", file=sys.stderr,
                  flush=True)  # fmt: skip
    finally:
        run.save_warmup = None


def _check_room(run: _Run, mesh: Any, state: Any) -> None:
    """The state (its shapes) and the programs' working memory fit in the memory a device has
    available now (a restored state is there already: only the working memory is checked) and
    its checkpoints on the disk: checked once the shapes are known, before the programs
    compile."""
    working = working_bytes(state, run.cfg, mesh.size)
    check_memory(state, mesh, working, resident=run.start_chunk > 0)
    run.checkpointer.check_space(state)


def _write_config(run: _Run, *, resume: bool, preset: str | None, changes: Any) -> None:
    """config.json for the run (or its resume), by the writing process only."""
    if run.writer:
        changes = _changes_as_trained(run, changes) if resume else changes
        info = run_info(run.out_dir, resume=resume, preset=preset, changes=changes,
                        at_env_steps=run.start_steps)  # fmt: skip
        if not resume:
            info.update(environment_record(run.cfg.env, run.env))
        save_config(run.cfg, run.population, run.out_dir, info)
        if run.tracker is not None:
            run.tracker.set_config(json.loads((run.out_dir / CONFIG_FILE).read_text()))


def _changes_as_trained(run: _Run, changes: dict[str, list]) -> dict[str, list]:
    """A resume's ``changes`` (``{setting: [saved, new]}`` against config.json) with the
    total_steps the restored checkpoint was written under as its saved value: config.json's
    may have been edited by hand since (no entry where the run keeps that value; ``changes``
    as they are for a checkpoint that does not record it)."""
    before = run.trained_total_steps
    if before is None:
        return changes
    rest = {name: change for name, change in changes.items() if name != "total_steps"}
    if before == run.cfg.total_steps:
        return rest
    return {"total_steps": [before, run.cfg.total_steps], **rest}


def _prepare(cfg: TrainConfig, out_dir: Path, resume: bool, sweep: Any, mesh: Any, writer: bool,
             program_dir: Path | None, env: Any = None):  # fmt: skip
    """Checks ``cfg`` and the directory, then finds the run's programs (stored ones, else the
    environment is made): ``(config, members, resume changes, program source)``, the config
    naming the environment ``env`` when one is given
    (:func:`~td3_jax.config.build.bind_environment`). Nothing is written."""
    cfg, env = bind_environment(cfg, env)
    if resume:  # (a run already past --total-steps: said before what cfg alone would say)
        check_total_steps_reach(out_dir, cfg)
    validated(cfg, devices=mesh.size)  # (cfg names env now: object/...)
    if writer:  # (before anything is traced or compiled)
        tracking.check_ready(cfg)
    layout = replay_layout_warning(cfg.replay_shards, mesh.size)
    if layout and writer:
        print(f"td3-jax: warning: {layout}", file=sys.stderr)
    if resume:
        population, changes = check_resume(out_dir, cfg, sweep, writer=writer)
    else:
        population, changes = members(cfg, sweep), {}
        check_fresh(out_dir, writer=writer, run=(cfg, population))
    source = programs.find(cfg, population, mesh, program_dir, with_init=not resume, env=env)
    if resume:  # (the environment just made, before anything is compiled)
        check_environment_unchanged(out_dir, cfg.env, source.env)
    return cfg, population, changes, source


@dataclasses.dataclass
class _Run:
    """The host side of one training call: its outputs and what it has done so far."""

    cfg: TrainConfig
    out_dir: Path
    population: list[Member]
    devices: int
    writer: bool
    stop_after_chunks: int | None
    time_budget_s: float | None
    stop: StopToken = dataclasses.field(default_factory=StopToken)
    env: Any = None  # the environment, when this process made it (a stored program has none)
    checkpointer: Checkpointer | None = None
    logger: MetricsLogger | None = None
    tracker: tracking.Tracker | None = None
    display: _Progress | None = None
    records: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    diverged: set[int] = dataclasses.field(default_factory=set)
    start_chunk: int = 0  # the checkpoint the run resumed from (0: a fresh run)
    start_steps: int = 0  # the env steps it holds (a run's shortened last chunk: not whole)
    trained_total_steps: int | None = None  # the total_steps it was written under, if recorded
    warned_of_growth: bool = False  # (growth_warning: said once per run)
    call: int = dataclasses.field(default_factory=lambda: next(_TRAIN_CALLS))  # (stop keys)
    started_together: bool = False  # (the processes agreed to start: _agree_to_start)
    last_chunk: int | None = None  # the index of the chunk begun last
    clock_start: float = dataclasses.field(default_factory=time.perf_counter)
    wall_offset: float = 0.0
    failed_write: Exception | None = None  # the write the disk refused, which stopped the run
    save_warmup: Future | None = None  # Checkpointer.prepare's compile, until waited for

    def close(self) -> None:
        """Closes the outputs, each on its own: the progress display, a checkpoint still being
        written (finished first), then the logs; redraws the curve (not after a failed write:
        the resumed run draws it) and ends the W&B run with it. A failure here is a warning,
        so it never hides the error that ended the run (none where the disk that stopped the
        run refuses the logs' last flush too: the run's error line says so)."""
        if self.display is not None:
            _warn_on_failure(self.display.close, "closing the progress display")
        if self.checkpointer is not None:
            if self.writer and self.checkpointer.pending is not None:
                print(f"td3-jax: finishing checkpoint {self.checkpointer.pending}...",
                      file=sys.stderr)  # fmt: skip
            _warn_on_failure(self.checkpointer.close, "")
        if self.logger is not None:
            said = self.failed_write is not None
            _warn_on_failure(self.logger.close, "closing the run's logs",
                             unless=lambda err: said and _refused_write(err))  # fmt: skip
        curve = None
        if self.writer and self.logger is not None and self.failed_write is None:
            curve = _warn_on_failure(lambda: plot_curve(self.out_dir), "drawing curve.png",
                                     hint="td3-jax plot redraws the curve")  # fmt: skip
        if self.tracker is not None:
            self.tracker.finish(curve)


def _refused_write(err: Exception) -> bool:
    """Whether ``err`` is a write that the disk refused (full, over quota, read-only)."""
    return isinstance(err, OSError) and err.errno in WRITE_ERRNOS


def _warn_on_failure(action: Any, what: str, hint: str = "",
                     unless: Callable[[Exception], bool] | None = None) -> Any:  # fmt: skip
    """Runs ``action`` and returns what it returns; an error becomes a warning (and ``None``):
    ``what`` failed (the error); ``hint``. An error for which ``unless`` is true is dropped."""
    try:
        return action()
    except Exception as err:  # e.g. a full disk: the records are kept, the curve is not
        if unless is not None and unless(err):
            return None
        text = f"{what} failed ({type(err).__name__}: {err})" if what else str(err)
        print(f"td3-jax: warning: {text}" + (f"; {hint}" if hint else ""), file=sys.stderr)
        return None


def _start(run: _Run, source: Source, resume: bool) -> Any:
    """The restored state on resume (``run.start_chunk`` and ``run.start_steps`` say where its
    checkpoint left the run), ``None`` for a fresh run; the run's checkpointer is opened here.
    The state is checked to fit (with the programs' working memory) before it is restored."""
    run.checkpointer = Checkpointer(run.out_dir / CHECKPOINTS, run.cfg.keep_checkpoints)
    run.clock_start = time.perf_counter()
    if not resume:
        return None
    if run.writer:  # (it holds the run's lock: no other write can be in flight)
        run.checkpointer.remove_unfinished()
    abstract = programs.abstract_state(source)
    check_memory(abstract, source.mesh, working_bytes(abstract, run.cfg, source.mesh.size))
    shardings = state_shardings(abstract, source.mesh)
    state, meta, run.start_chunk = run.checkpointer.restore(abstract, shardings=shardings,
                                                            resize=ring_as_saved)  # fmt: skip
    check_unedited(meta.get("settings"), run.cfg, run.out_dir / CONFIG_FILE)
    run.start_steps = int(meta.get("env_steps", run.start_chunk * run.cfg.steps_per_chunk))
    run.trained_total_steps = meta.get("total_steps")
    _check_resumable(run)
    run.wall_offset = float(meta["wall_time_s"])
    run.diverged = set(meta.get("diverged_members", []))
    return state


def _check_resumable(run: _Run) -> None:
    """A one-line ConfigError for a resume that cannot go on as its run: a ``--total-steps``
    below the steps its checkpoint has taken, or a cosine schedule's length changed (also by
    a config.json whose total_steps was edited by hand since that checkpoint)."""
    cfg, out = run.cfg, run.out_dir
    # A checkpoint of td3-jax 0.1 (no total_steps recorded): its runs ended on whole chunks,
    # past --total-steps, and such a run is done, not cut short.
    done_as_before = (run.trained_total_steps is None
                      and run.start_chunk * cfg.steps_per_chunk >= cfg.total_steps)  # fmt: skip
    if run.start_steps > cfg.run_steps and not done_as_before:
        raise ConfigError(f"--total-steps {cfg.total_steps} is less than the {run.start_steps} "
                          f"env steps the run in {out} has already taken (give more to extend "
                          "it)")  # fmt: skip
    trained = run.trained_total_steps
    if cfg.lr_schedule == "cosine" and trained is not None and trained != cfg.total_steps:
        raise ConfigError(f"--total-steps cannot change on --resume with --lr-schedule cosine "
                          f"(the run in {out} was trained for {trained}, not "
                          f"{cfg.total_steps}): the schedule's length is the run's number of "
                          "updates (start a new run to train longer)")  # fmt: skip


def chunk_calls(cfg: TrainConfig, done: int) -> list[tuple[int, list[int]]]:
    """``(chunk index, [iterations of each call])`` of every chunk a run of ``cfg`` still
    trains after ``done`` iterations: whole chunks of ``iters_per_chunk``, the last one
    shortened to end at :attr:`~td3_jax.config.schema.TrainConfig.run_iterations` (the same
    compiled program: its iteration count is an argument), the first one only the rest of a
    chunk the run stopped inside (a run extended past its shortened last chunk, which then
    ends where a straight run's chunk does); a fresh run's first chunk as two calls, its
    ``early_iterations`` and the rest, with an evaluation after each."""
    per, end = cfg.iters_per_chunk, cfg.run_iterations
    plan = []
    for index in range(done // per, cfg.num_chunks):
        begin, stop = max(index * per, done), min((index + 1) * per, end)
        early = cfg.early_iterations if begin == 0 else 0
        if stop > begin:
            plan.append((index, [early, stop - early] if 0 < early < stop else [stop - begin]))
    return plan


def _loop(run: _Run, compiled: Programs, state: Any) -> None:
    """Chunks, evaluations, records and checkpoints until the run's end or a stop condition.

    The chunks are :func:`chunk_calls`' (one compiled program, whatever their lengths), each
    call followed by an evaluation and a record; a checkpoint follows whole chunks only, and
    the run's last one, written in the background while the next chunk runs (the last one is
    waited for). Stopped by ``run.stop``, it raises KeyboardInterrupt once that chunk is
    checkpointed.
    """
    index = run.start_steps // run.cfg.steps_per_chunk
    try:
        _chunks_until_done(run, compiled, state)
    except BaseException:  # (several processes: the others stop instead of waiting for this one)
        stop_failed(run.last_chunk if run.last_chunk is not None else index, call=run.call)
        raise


def _chunks_until_done(run: _Run, compiled: Programs, state: Any) -> None:
    """:func:`_loop`'s chunks (``run.last_chunk``: the index of the one begun last)."""
    cfg = run.cfg
    chunks, stopped = 0, False
    run.stop.mark_training()  # (a stop from here on waits for the chunk's checkpoint)
    for index, calls in chunk_calls(cfg, run.start_steps // cfg.env_steps_per_iter):
        run.last_chunk = index
        if _stopping(run, chunks, index, end=False):
            stopped = True
            break
        for iterations in calls:
            with awaiting_device():  # (a Ctrl-C leaves the chunk running on the device)
                state, record = _chunk_and_record(run, compiled, state, iterations)
            run.logger.write(record)
            run.records.append(record)
            run.display.update(record)
            _warn_of_critic_growth(run)
            run.checkpointer.check()  # a background write that failed stops the run now
        chunks += 1
        last = index + 1 == cfg.num_chunks or _stopping(run, chunks, index, end=True)
        # The rest of the chunk a restored checkpoint stopped inside would be saved under that
        # checkpoint's own number, deleting it first: kept unless the run ends there.
        rewrites_restored = index + 1 == run.start_chunk and not last
        if (last or (index + 1) % cfg.checkpoint_every == 0) and not rewrites_restored:
            meta = {"wall_time_s": record["wall_time_s"], "env_steps": record["env_steps"],
                    "diverged_members": sorted(run.diverged), "total_steps": cfg.total_steps,
                    "settings": fixed_settings(cfg)}  # fmt: skip
            with run.stop.shielded():  # a Ctrl-C now lets the checkpoint be written
                run.checkpointer.save(index + 1, state, meta, background=not last)
    if stopped:  # (a stop that came with the last chunk: the run is done)
        run.stop.raise_if_set()  # stopped by its token: as interrupted, once checkpointed


def _warn_of_critic_growth(run: _Run) -> None:
    """The warning of :func:`~td3_jax.runner.critic_growth.growth_warning`, once per run, by
    the writing process."""
    if run.warned_of_growth or not run.writer:
        return
    warning = growth_warning(run.records)
    if warning is not None:
        run.warned_of_growth = True
        print(f"td3-jax: warning: {warning}", file=sys.stderr, flush=True)


def _stopping(run: _Run, chunks_done: int, chunk: int, end: bool) -> bool:
    """Whether this call stops at the start (or ``end``) of chunk ``chunk``: its chunk limit,
    wall-clock budget or stop token, agreed with the other processes of a several-process
    run (:func:`~td3_jax.runner.sharding.stop_agreed`; another's stop token sets this one's)."""
    try:
        agreed = stop_agreed(_own_stop_reason(run, chunks_done), chunk, end, call=run.call)
    except ProcessLostError as err:
        raise ProcessLostError(f"{err}; {_kept_checkpoint(run, run.checkpointer.latest_step())}"
                               ) from None
    if agreed == "token":
        run.stop.set()
    return bool(agreed)


def _own_stop_reason(run: _Run, chunks_done: int) -> str:
    """This process's reason to stop before its next chunk: ``"token"`` (its stop token),
    ``"limit"`` (its chunk limit or wall-clock budget) or ``""`` (none)."""
    if run.stop.is_set():
        return "token"
    if run.stop_after_chunks is not None and chunks_done >= run.stop_after_chunks:
        return "limit"
    budget = run.time_budget_s
    over = bool(run.records) and budget is not None and run.records[-1]["wall_time_s"] >= budget
    return "limit" if over else ""


def _chunk_and_record(
    run: _Run, compiled: Programs, state: Any, iterations: int
) -> tuple[Any, dict[str, Any]]:
    """One compiled chunk of ``iterations``, the finiteness check, the evaluation and the
    record of both."""
    chunk_start = time.perf_counter()
    state, metrics = compiled.train_chunk(state, np.int32(iterations))
    metrics = {k: host_value(v) for k, v in metrics.items()}
    chunk_seconds = time.perf_counter() - chunk_start
    env_steps = int(metrics.pop("env_steps")[0])
    updates = int(metrics.pop("agent_steps")[0])
    policy = metrics.pop("eval_policy_env_steps", None)  # (every member's: one env clock)
    metrics = {k: v.astype(np.float64) for k, v in metrics.items()}
    _check_finite(run, metrics, env_steps, state)
    _check_physics(run, metrics, env_steps)
    eval_start = time.perf_counter()
    returns = host_value(compiled.evaluate(state)).astype(np.float64)
    eval_seconds = time.perf_counter() - eval_start
    returns[sorted(run.diverged)] = np.nan
    record = _record(run, updates, metrics, returns, env_steps)
    if policy is not None:  # a whole number of env steps, as env_steps is
        record["eval_policy_env_steps"] = int(policy[0])
    record["wall_time_s"] = run.wall_offset + time.perf_counter() - run.clock_start
    record["chunk_s"], record["eval_s"] = chunk_seconds, eval_seconds
    steps = iterations * run.cfg.env_steps_per_iter
    record["env_steps_per_s"] = len(run.population) * steps / chunk_seconds
    record["devices"] = run.devices
    return state, record


def _record(run: _Run, updates, metrics, returns, env_steps) -> dict[str, Any]:
    cfg, population = run.cfg, run.population
    record: dict[str, Any] = {
        "env": cfg.env,
        "algo": cfg.algo,
        "seed": cfg.seed,
        "members": len(population),
        "env_steps": env_steps,
        "updates": updates,
    }
    alive = [i for i in range(len(population)) if i not in run.diverged]
    scalars = {k: float(np.mean(v[alive])) for k, v in metrics.items() if k != "params_finite"}
    if len(population) == 1:
        return {**record, **return_stats(returns[0]), **scalars}
    record.update(population_stats(returns[alive]))
    record.update(scalars)
    if run.diverged:
        record["diverged_members"] = [population[i].label() for i in sorted(run.diverged)]
    record["per_member"] = [_member_record(run, i, metrics, returns)
                            for i in range(len(population))]  # fmt: skip
    return record


def _member_record(run: _Run, i: int, metrics, returns) -> dict[str, Any]:
    member = run.population[i]
    values = {**return_stats(returns[i]), "critic_loss": float(metrics["critic_loss"][i]),
              "actor_loss": float(metrics["actor_loss"][i])}  # fmt: skip
    values = {k: (v if math.isfinite(v) else None) for k, v in values.items()}
    entry = {"seed": member.seed, "settings": dict(member.overrides), **values}
    return {**entry, "diverged": True} if i in run.diverged else entry


#: How a chunk's non-finite mean reward is named: the environment's, not the learner's fault.
ENV_REWARDS = "rewards from the environment (its step returned NaN or inf)"
#: ... and its observations, found non-finite in the replay ring of a run that diverged.
ENV_OBSERVATIONS = "observations from the environment (its reset or step returned NaN or inf)"
#: ``[members]`` whether each member's replay ring holds only finite observations.
_RINGS_FINITE = jax.jit(jax.vmap(observations_finite))


def _nonfinite(metrics: dict[str, np.ndarray], i: int,
               finite: np.ndarray | None = None) -> list[str]:  # fmt: skip
    """What is non-finite in member ``i``'s chunk metrics: the environment's rewards, or else
    its observations where ``finite`` (``[members]``: its ring's observations are finite)
    says so, first (a cause, where the rest are its consequences), then losses, Q and
    parameters."""
    rewards = metrics.get("reward_mean")
    env = [ENV_REWARDS] if rewards is not None and not math.isfinite(rewards[i]) else []
    if not env and finite is not None and not finite[i]:
        env = [ENV_OBSERVATIONS]
    names = [k for k in ("critic_loss", "actor_loss", "q_mean") if not math.isfinite(metrics[k][i])]
    return env + names + (["parameters"] if metrics["params_finite"][i] < 1.0 else [])


def _diverged(run: _Run, metrics: dict[str, np.ndarray], state: Any) -> dict[int, list[str]]:
    """Member -> what is non-finite, for the members newly diverged in this chunk; where the
    environment's rewards do not explain one, the replay ring's observations are checked
    (:func:`~td3_jax.core.training.observations_finite`, only then: a pass over the ring)."""
    members = [i for i in range(len(run.population)) if i not in run.diverged]
    bad = {i: names for i in members if (names := _nonfinite(metrics, i))}
    if any(ENV_REWARDS not in names for names in bad.values()):
        try:
            finite = host_value(_RINGS_FINITE(state.buffer))
        except Exception:  # (a diagnosis: the run's own error is said without it)
            finite = None
        bad = {i: _nonfinite(metrics, i, finite) for i in bad}
    return bad


def _check_finite(run: _Run, metrics: dict[str, np.ndarray], env_steps: int,
                  state: Any) -> None:  # fmt: skip
    """Marks newly diverged members of a population; stops a single run, or a population
    whose members have all diverged, with :class:`NonFiniteError`."""
    population = run.population
    bad = _diverged(run, metrics, state)
    if len(population) > 1 and len(run.diverged) + len(bad) < len(population):
        for i, names in bad.items():
            print(f"td3-jax: warning: member {population[i].label()} diverged (non-finite "
                  f"{', '.join(names)} at env step {env_steps}); the others go on",
                  file=sys.stderr)  # fmt: skip
        run.diverged.update(bad)
        return
    if not bad:
        return
    try:
        last, failed = run.checkpointer.latest_step(), ""
    except CheckpointWriteError as err:  # the write before this chunk failed as well
        last, failed = run.checkpointer.latest_step(), f"; also, {err}"
    kept = _kept_checkpoint(run, last)
    again = "" if last else f"; {run.out_dir} holds none to resume: {_starting_again(run)}"
    who = lambda i: f" ({population[i].label()})" if len(population) > 1 else ""
    described = "; ".join(", ".join(names) + who(i) for i, names in bad.items())
    raise NonFiniteError(f"non-finite {described} in the chunk ending at env step {env_steps}; "
                         f"stopped, {kept}{failed}{again}")  # fmt: skip


def _starting_again(run: _Run) -> str:
    """How a run stopped before its first checkpoint starts again with other settings: in its
    folder where it wrote no record yet (a fresh run replaces what is there), else after
    moving the folder away."""
    if ended_before_recording(run.out_dir):
        return "with no record written either, a run of other settings may start there"
    return "remove it (or choose another --out) to start again, with other settings"


def _kept_checkpoint(run: _Run, last: int | None) -> str:
    """What a stopped run keeps: its newest checkpoint (after ``last`` chunks), if any."""
    if not last:
        return "no checkpoint had been written yet"
    return f"the last good checkpoint (after {_steps_after(run, last)} env steps) is kept"


def _steps_after(run: _Run, chunks: int) -> int:
    """The env steps of checkpoint ``chunks`` of the run: where the restored one left it, else
    whole chunks up to the run's end (its last chunk may be shortened)."""
    if chunks == run.start_chunk:
        return run.start_steps
    return min(chunks * run.cfg.steps_per_chunk, run.cfg.run_steps)


def _check_physics(run: _Run, metrics: dict[str, np.ndarray], env_steps: int) -> None:
    """Stops the run with :class:`PhysicsOverflowError` when the physics dropped contacts or
    constraints in the chunk (MuJoCo Warp's fixed buffers), naming the flags that size them."""
    overflows = int(np.sum(metrics["physics_overflow"]))
    if not overflows:
        return
    last = run.checkpointer.latest_step()
    kept = _kept_checkpoint(run, last)
    raise PhysicsOverflowError(
        f"MuJoCo Warp's contact or constraint buffer was full in {overflows} environment "
        f"steps of the chunk ending at env step {env_steps} (contacts or constraints were "
        f"dropped: wrong physics); stopped, {kept}; raise --nconmax or --njmax (contacts and "
        "constraints per environment; default: the task's own) in a new run"
    )


class _Progress:
    """One line per evaluation and, on a terminal, below them a rich progress bar (env steps,
    env steps/s, last evaluation return, time left) that fits 80 columns; where the output is
    not a terminal (a log file, a batch job), the lines alone. A part of the run spent in the
    random warm-up says so instead of a rate (it steps without updates, far faster than
    training)."""

    def __init__(self, cfg: TrainConfig, start_steps: int, enabled: bool, console: Any = None):
        from rich.console import Console

        self.enabled, self.warmup = enabled, cfg.warmup_steps
        self.total = cfg.run_steps
        self.done = start_steps  # (env steps before the next record)
        console = console or Console()
        self.lines = enabled and not console.is_terminal
        self.title = f"{cfg.algo} {cfg.env}"
        if enabled and not self.lines:
            console.print(f"{self.title}: {self.total:,} env steps")
            self._progress, self._task = _progress_bar(self.total, self.done, console)

    def update(self, record: dict) -> None:
        start, self.done = self.done, record["env_steps"]
        if not self.enabled:
            return
        # (the run's wall-clock: compile included, counted across resumes)
        line = (f"{self.title}: {record['env_steps']:,}/{self.total:,} env steps, "
                f"{_rate_text(record, start, self.warmup)}, eval {_evaluation_text(record)}"
                f"{_best_setting(record)}, {record['wall_time_s']:.0f} s"
                f"{_slow_evaluation(record)}")  # fmt: skip
        if self.lines:
            print(line, flush=True)
            return
        steps = f"{_count(record['env_steps'])}/{_count(self.total)}"
        self._progress.update(self._task, completed=record["env_steps"], steps=steps,
                              rate=_rate_text(record, start, self.warmup, compact=True),
                              ret=_evaluation_text(record, short=True))  # fmt: skip
        self._progress.console.print(line, markup=False, highlight=False, soft_wrap=True)

    def close(self) -> None:
        if self.enabled and not self.lines:
            self._progress.stop()


def _rate_text(record: dict, start: int, warmup: int, compact: bool = False) -> str:
    """``12,345 env steps/s`` of the record's part of the run (from ``start`` env steps), or
    ``warm-up`` where all of it was the random warm-up (``(with warm-up)`` where part was;
    ``compact``: ``12.35k/s``, for the bar)."""
    if record["env_steps"] <= warmup:
        return "warm-up"
    if compact:
        return f"{_count(record['env_steps_per_s'])}/s"
    rate = f"{record['env_steps_per_s']:,.0f} env steps/s"
    return f"{rate} (with warm-up)" if start < warmup else rate


def _slow_evaluation(record: dict) -> str:
    """``; evaluating took 10.4 s`` where the record's evaluation took a second or more and
    longer than its chunk's training (the rate shown leaves it out), else nothing."""
    seconds = record.get("eval_s", 0.0)
    if seconds < 1.0 or seconds <= record.get("chunk_s", 0.0):
        return ""
    return f"; evaluating took {seconds:.1f} s"


def _count(value: float) -> str:
    """A count in at most 6 characters: ``9,999``, ``20.48k``, ``102.4M``."""
    if value < 10_000:
        return f"{value:,.0f}"
    return f"{value / 1e3:.4g}k" if value < 999_950 else f"{value / 1e6:.4g}M"


def _evaluation_text(record: dict, short: bool = False) -> str:
    """The record's mean evaluation return, with the env steps of the policy it is of where
    that is not the record's own (the evaluation inside the chunk; ``short``: ``@4.096M``)."""
    text = f"{record['eval_return_mean']:.1f}"
    policy = record.get("eval_policy_env_steps")
    if policy is None or policy < 0:
        return text
    return f"{text} @{_count(policy)}" if short else f"{text} (policy of {int(policy):,} steps)"


def _best_setting(record: dict) -> str:
    """For a sweep's record: `` over all 4 members; best actor_lr=0.0003 at -1475.6`` (the
    record's mean is over the members that did not diverge: ``over the 3 of 4 members that
    did not diverge``; the best setting has the highest mean of its members among those), else
    nothing: the record's mean pools different settings."""
    groups = {setting: [r for r in returns if r is not None and math.isfinite(r)]
              for setting, returns in returns_by_setting(record.get("per_member") or []).items()}
    means = {setting: sum(v) / len(v) for setting, v in groups.items() if v and setting}
    if not means:
        return ""
    best = max(means, key=means.__getitem__)
    named = setting_label(best)
    count, alive = len(record["per_member"]), sum(len(v) for v in groups.values())
    over = (f"all {count} members" if alive == count
            else f"the {alive} of {count} members that did not diverge")  # fmt: skip
    return f" over {over}; best {named} at {means[best]:.1f}"


def _progress_bar(total: int, completed: int, console: Any) -> tuple[Any, Any]:
    """A started rich progress bar on ``console`` and its task; the bar takes the width the
    texts leave (80 columns leave it a dozen)."""
    from rich.progress import (
        BarColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    progress = Progress(
        BarColumn(bar_width=None),
        TextColumn("{task.fields[steps]} steps"),
        TextColumn("{task.fields[rate]}"),
        TextColumn("eval {task.fields[ret]}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
        expand=True,
    )
    steps = f"{_count(completed)}/{_count(total)}"
    task = progress.add_task("", total=total, completed=completed, steps=steps, rate="-",
                             ret="-")  # fmt: skip
    progress.start()
    return progress, task
