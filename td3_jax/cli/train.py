"""``td3-jax train`` and ``td3-jax sweep``: the flags over their defaults, the settings
checked and completed, the run under Ctrl-C handling, and the lines that end it."""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from td3_jax.cli import notes, settings
from td3_jax.cli.argv import given_fields, joins_others
from td3_jax.cli.commands import SweepCommand, TrainCommand
from td3_jax.cli.interrupts import leave_processes, process_stop, train_stoppably
from td3_jax.cli.parsing import parse
from td3_jax.cli.run_folder import remove_if_empty, with_run_directory
from td3_jax.cli.tables import print_sweep_ranking
from td3_jax.common import library_noise, runtime
from td3_jax.config.schema import (
    SWITCHED_ON_BY_THEIR_FLAG,
    ConfigError,
    TrainConfig,
    eval_every_within_run,
    flag,
    idle_wandb_flags,
    validate,
)

__all__ = ["parse_train", "sweep_main", "sweep_values", "train_main"]


def train_main(args: list[str], sweeping: bool = False) -> None:
    """``td3-jax train ARGS`` (``sweeping``: ``td3-jax sweep ARGS``): checks the settings,
    trains (or resumes) the run and prints its last line (a sweep's ranking too). Processes of
    one run leave JAX's runtime together when it ends (stopped or failed, the command's exit
    does: :func:`~td3_jax.cli.interrupts.exit_process`)."""
    stop, received = process_stop()
    args, chosen_out = with_run_directory(args)  # (no --out: a new folder under runs/)
    try:
        _train_command(args, sweeping, stop, received, chosen_out)
    except BaseException:
        remove_if_empty(chosen_out)  # (a run refused or stopped before writing anything)
        raise
    leave_processes(None)


def _train_command(args: list[str], sweeping: bool, stop: runtime.StopToken,
                   received: list[int], chosen_out: Path | None = None) -> None:  # fmt: skip
    """:func:`train_main` with the stop token and signals of its process (``chosen_out``: the
    folder made for a run that no ``--out`` named)."""
    command, cfg, preset_name, source = parse_train(args, sweeping)
    if command.out is None:  # (--out None: no folder at all)
        raise ConfigError("--out None names no folder: give the run's, or leave --out out for "
                          "a new one under runs/")  # fmt: skip
    sweep = sweep_values(command, args) if sweeping else None
    from td3_jax import envs  # lazy: imports JAX

    envs.check_name(cfg.env)  # before anything about the environment is said
    if command.local_processes is not None:  # (td3-jax's own command starts them sooner)
        from td3_jax.cli.local_processes import run_local_processes

        status = run_local_processes("sweep" if sweeping else "train", args,
                                     command.local_processes)  # fmt: skip
        raise SystemExit(status)
    program_dir = _start_process(command, args, stop)
    with _others_told_of_a_stop(stop):
        _check_processes_agree(cfg, command, sweep, sweeping)
        cfg, devices, asked_eval_every = _completed(cfg, command, source, args)
        typed = given_fields(args)
        given = typed | set(sweep or {})  # (a swept setting is every member's own)
        with notes.preset_noted(cfg, preset_name, given):
            if command.resume:  # (a run already past --total-steps, before cfg's own checks)
                from td3_jax.runner.rundir import check_total_steps_reach  # lazy: imports JAX

                check_total_steps_reach(command.out, cfg)
            validate(cfg)  # (said once the directory and the environment are good too)
    prepared = functools.partial(notes.when_prepared, cfg, preset_name, source, asked_eval_every,
                                 frozenset(typed), command.resume, chosen_out)  # fmt: skip
    started, started_at = time.perf_counter(), []
    with notes.preset_noted(cfg, preset_name, given):
        records = train_stoppably(cfg, command, stop, received, devices=devices,
                                  sweep=sweep, preset=preset_name, on_prepared=prepared,
                                  program_dir=program_dir,
                                  on_started=started_at.append)  # fmt: skip
    from td3_jax.runner.rundir import is_sweep_dir, nothing_to_do  # lazy: imports JAX

    if not records:
        print(nothing_to_do(command.out, cfg))
        return

    ranked = sweeping or (command.resume and is_sweep_dir(command.out))  # (also train --resume)
    resumed_at = started_at[0] if command.resume and started_at else None
    _print_end(records, cfg, command, time.perf_counter() - started, ranked, resumed_at)


def sweep_main(args: list[str]) -> None:
    """``td3-jax sweep ARGS``: :func:`train_main` of a sweep."""
    train_main(args, sweeping=True)


def parse_train(args: list[str], sweeping: bool) -> tuple[Any, TrainConfig, str | None, str]:
    """The train (or sweep) command of ``args`` over its defaults (a preset, the run's own
    config.json on --resume, the device's), its TrainConfig, the preset's name and where the
    defaults came from; the flags that need nothing built are checked here."""
    command_type = SweepCommand if sweeping else TrainCommand
    prog = "td3-jax sweep" if sweeping else "td3-jax train"
    base, preset_name, source = settings.base_config(args)
    default = command_type(
        **dataclasses.asdict(base), preset=preset_name if source == "preset" else None
    )
    command = parse(command_type, args, prog, default=default)
    cfg = TrainConfig(**{f.name: getattr(command, f.name) for f in dataclasses.fields(TrainConfig)})
    idle_wandb_flags(cfg, given_fields(args))
    _check_process_flags(command)
    if sweeping and command.resume:
        _check_sweep_to_resume(command.out)
    return command, cfg, preset_name, source


def sweep_values(command: Any, args: list[str]) -> dict[str, list[float]]:
    """The ``--sweep-*`` lists of a sweep command (``{"actor_lr": [...], ...}``) from its
    ``args``; none is an error unless the sweep is resumed, and so are a list without values, a
    value listed twice and a swept setting also typed as a flag of its own."""
    sweep = {
        f.name.removeprefix("sweep_"): list(getattr(command, f.name))
        for f in dataclasses.fields(SweepCommand)
        if f.name.startswith("sweep_") and getattr(command, f.name)
    }
    typed = [arg.split("=", 1)[0] for arg in args if arg.startswith("--sweep-")]
    empty = [name for name in typed if name.removeprefix("--sweep-").replace("-", "_") not in sweep]
    if empty:
        raise ConfigError(f"{empty[0]} was given no values: list those to try, e.g. "
                          f"{empty[0]} 1e-3 3e-4")  # fmt: skip
    given = given_fields(args)
    if not sweep and not command.resume:
        raise ConfigError("td3-jax sweep needs at least one --sweep-* list of values")
    for name, values in sweep.items():
        twice = sorted({v for v in values if values.count(v) > 1})
        if twice:
            raise ConfigError(f"--sweep-{name.replace('_', '-')} lists {twice[0]:g} more than "
                              "once: each value trains once (--seeds K repeats them)")  # fmt: skip
    both = sorted(set(sweep) & given - set(SWITCHED_ON_BY_THEIR_FLAG))
    if both:
        raise ConfigError(f"{flag(both[0])} and --sweep-{both[0].replace('_', '-')} both given: "
                          "the swept values replace it in every member; give one")  # fmt: skip
    return sweep


def _check_process_flags(command: Any) -> None:
    """The flags of this process that TrainConfig does not hold, checked before anything is
    said (:func:`~td3_jax.runner.run.train` checks them too): a positive ``--devices`` and a
    positive, finite ``--time-budget-s`` (a ConfigError otherwise)."""
    from td3_jax.runner.run import check_time_budget  # lazy: imports JAX
    from td3_jax.runner.sharding import check_devices  # lazy: imports JAX

    check_devices(command.devices)
    check_time_budget(command.time_budget_s)


def _check_sweep_to_resume(out: Path) -> None:
    """``td3-jax sweep --resume`` of a run that ``td3-jax train`` started is one line naming
    the command that resumes it (a sweep's table would rank settings it never swept)."""
    from td3_jax.runner import rundir  # lazy: imports JAX

    if (Path(out) / rundir.CONFIG_FILE).exists() and not rundir.is_sweep_dir(out):
        raise ConfigError(f"{out} holds a run of td3-jax train, not a sweep: resume it with "
                          f"{rundir.resume_command(out)}")  # fmt: skip


def _start_process(command: Any, args: list[str], stop: runtime.StopToken) -> Path | None:
    """This process's side of a run: JAX's compilation cache (``--compile-cache``) and, on
    several hosts, the distributed runtime, with the line with which JAX's coordination service
    ends a process (another did not join, or stopped answering) and its stack trace said as
    one line of td3-jax's (:data:`~td3_jax.common.library_noise.PROCESS_LOST`). Returns the
    folder of the traced programs (None: off)."""
    given_cache = any(arg.split("=", 1)[0] == "--compile-cache" for arg in args)
    program_dir = runtime.enable_compile_cache(command.compile_cache, given=given_cache)
    stop.raise_if_set()  # (stopped while it started: joining could block for minutes)
    if joins_others(args):  # (JAX's coordination service may end it with a C++ stack trace)
        library_noise.filtered_stderr_until_exit(
            (), fatal=(library_noise.COORDINATION_FATAL, library_noise.PROCESS_LOST))
    from td3_jax.runner.sharding import initialize_distributed  # lazy: imports JAX

    initialize_distributed(command.coordinator_address, command.num_processes, command.process_id)
    return program_dir


@contextlib.contextmanager
def _others_told_of_a_stop(stop: runtime.StopToken) -> Iterator[None]:
    """Between joining the other processes and training: where this process stops (a check of
    its own host's run directory, a signal), the others are told, so none waits for it
    (:func:`~td3_jax.runner.run.stop_before_next_training`)."""
    try:
        yield
    except BaseException:
        if runtime.joined_others():
            from td3_jax.runner.run import stop_before_next_training  # lazy: imports JAX

            stop_before_next_training("token" if stop.is_set() else "error")
        raise


def _check_processes_agree(
    cfg: TrainConfig, command: Any, sweep: dict[str, list[float]] | None, sweeping: bool
) -> None:
    """Several processes: each was given the run's flags as the others were (else one line in
    every process, naming one that differs), so none waits for the others at a step they
    will not take. Compared as parsed, before anything is worked out on each host; a host's
    own ``--menagerie`` (the folder of its robots' files) may differ."""
    from td3_jax.runner.sharding import check_same_settings  # lazy: imports JAX

    settings = {k: v for k, v in dataclasses.asdict(cfg).items() if k != "menagerie"}
    process = {"command": "sweep" if sweeping else "train", "resume": command.resume,
               "devices": command.devices, "out": str(command.out),
               "time_budget_s": command.time_budget_s}  # fmt: skip
    swept = {f"sweep_{name}": values for name, values in (sweep or {}).items()}
    check_same_settings({**settings, **process, **swept})


def _completed(cfg: TrainConfig, command: Any, source: str,
               args: list[str]) -> tuple[TrainConfig, int | None, int]:  # fmt: skip
    """``cfg`` as the device and the run directory complete it (an accelerator's defaults for
    an environment without a preset, a Playground task's physics, whole chunks, a resume's own
    chunk), the device count, and the ``--eval-every`` as asked (before it rounds)."""
    if source == "device":
        cfg = settings.scale_to_device(cfg, args)
    cfg, devices = settings.choose_physics(cfg, command.devices)
    asked_eval_every = cfg.eval_every
    if not command.resume:  # (a resume keeps the chunk its checkpoints were written with)
        cfg = eval_every_within_run(cfg)
    if command.resume:
        cfg = settings.resumed_settings(cfg, command.out)
    return cfg, devices, asked_eval_every


def _print_end(records: list[dict], cfg: TrainConfig, command: Any, process_s: float,
               sweeping: bool, resumed_at: int | None = None) -> None:  # fmt: skip
    """The lines that end a run this process trained (resumed at ``resumed_at`` env steps, if
    it was): :func:`~td3_jax.cli.notes.done_line` with what its ± is over
    (:func:`~td3_jax.cli.notes.members_note`), a note when ``--time-budget-s`` stopped it
    before its last step (and how to go on), a sweep's ranking."""
    pooled = notes.members_note(records[-1], sweeping)
    taken = records[-1]["env_steps"]
    early = command.time_budget_s is not None and taken < cfg.run_steps
    print(notes.done_line(records[-1], command.out, process_s, resumed_at, pooled,
                          word="stopped" if early else "done"))  # fmt: skip
    if early:
        from td3_jax.runner.rundir import resume_command  # lazy: imports JAX

        print(f"stopped by --time-budget-s {command.time_budget_s:g} at {taken:,} of "
              f"{cfg.run_steps:,} env steps; {resume_command(command.out)} "
              "continues it")  # fmt: skip
    if sweeping and "per_member" in records[-1]:
        print_sweep_ranking(records[-1])
