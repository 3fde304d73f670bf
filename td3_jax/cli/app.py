"""``td3-jax``: train, evaluate, export, render and plot from the command line.

Subcommands: ``train`` and ``sweep`` (flags from :class:`~td3_jax.config.schema.TrainConfig`),
``eval``, ``export``, ``render``, ``plot``, ``envs``, ``presets``. Bad settings print one line
and exit with code 2.

This module is the entry point: the usage, ``--version``, the choice of subcommand and how a
failure ends (one line and an exit code). Each subcommand's module is imported only when it
runs, so ``td3-jax --help`` and ``--version`` answer without importing JAX.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import signal
import sys
import traceback
from collections.abc import Callable

from td3_jax import __version__
from td3_jax.cli.argv import check_no_empty_path, expand_home, repeated_flags_warning
from td3_jax.cli.interrupts import Interrupted, exit_process, process_stop, signals_while_starting
from td3_jax.cli.messages import error, warn
from td3_jax.common import runtime
from td3_jax.common.errors import WRITE_ERRNOS, Td3JaxError, did_you_mean
from td3_jax.common.runtime import joined_others

__all__ = ["COMMANDS", "USAGE", "main", "run_reporting_errors", "subcommand"]

USAGE = """\
usage: td3-jax {train,sweep,eval,export,render,plot,envs,presets} [FLAGS]
       td3-jax --version

Train TD3/DDPG on thousands of vectorised environments inside one compiled JAX program.

subcommands:
  train     train an agent:  td3-jax train --env brax/ant --preset ant --out runs/ant
  sweep     train every combination of float settings x seeds in one program:
              td3-jax sweep --sweep-actor-lr 1e-3 3e-4 --sweep-tau 0.005 0.01 --seeds 4
  eval      evaluate a run's newest checkpoint:  td3-jax eval --run runs/ant
  export    write a run's policy as ONNX or a NumPy-only .npz:
              td3-jax export --run runs/ant --format onnx
  render    write a video of a run's policy:  td3-jax render --run runs/ant [--gif]
  plot      redraw a run's curve.png, or compare runs:
              td3-jax plot --run runs/a runs/b --out compare.png
  envs      list the environment names this installation knows
  presets   list the presets (or those named) and what they set:  td3-jax presets ant

`td3-jax SUBCOMMAND --help` lists a subcommand's flags.
"""

#: Each subcommand's module (under td3_jax.cli) and function, which takes the arguments after
#: the subcommand's name.
COMMANDS = {
    "train": ("train", "train_main"),
    "sweep": ("train", "sweep_main"),
    "eval": ("finished", "eval_main"),
    "export": ("finished", "export_main"),
    "render": ("finished", "render_main"),
    "plot": ("finished", "plot_main"),
    "envs": ("listing", "envs_main"),
    "presets": ("listing", "presets_main"),
}


def main(argv: list[str] | None = None) -> None:
    """Entry point of the ``td3-jax`` console script: runs ``argv`` (default: the process's
    arguments); exits 0, or with the failure's code after one line on stderr."""
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        _dispatch(argv)
        sys.stdout.flush()  # (here, not at exit, where a closed pipe is a traceback and 120)
    except BrokenPipeError:  # the reader of our output went away (`td3-jax ... | head`)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit
        sys.exit(141)  # 128 + SIGPIPE, as other command-line tools end


def _dispatch(argv: list[str]) -> None:
    """The usage (-h, --help), the version, or the subcommand ``argv[0]`` run on the rest; an
    unknown or missing subcommand exits 2 with the closest name (the usage where none is
    given)."""
    if argv[:1] in (["-h"], ["--help"]):
        print(USAGE)
        return
    if not argv:  # (as argparse's required subcommands: the usage, and exit 2)
        print(f"{USAGE}\ntd3-jax: error: a subcommand is required", file=sys.stderr)
        sys.exit(2)
    if argv[0] in ("-V", "--version"):
        if argv[1:]:  # (one line, as for any unknown word)
            print(f"td3-jax: error: {argv[0]} takes nothing after it, got {argv[1]!r}",
                  file=sys.stderr)  # fmt: skip
            sys.exit(2)
        print(f"td3-jax {__version__}")
        return
    if argv[0] not in COMMANDS:
        hint = did_you_mean(argv[0], list(COMMANDS))
        names = ", ".join(COMMANDS)
        print(f"td3-jax: error: unknown subcommand {argv[0]!r}{hint} (subcommands: {names}; "
              "td3-jax --help says what each does)", file=sys.stderr)  # fmt: skip
        sys.exit(2)
    if _launched(argv[0], argv[1:]):
        _launch(argv[0], argv[1:])
        return
    training = argv[0] in ("train", "sweep")
    with signals_while_starting(argv[1:]) if training else contextlib.nullcontext():
        run_reporting_errors(subcommand(argv[0]), argv[1:])  # (imports JAX: seconds)


def _launched(name: str, args: list[str]) -> bool:
    """Whether ``td3-jax NAME ARGS`` is a train or sweep of ``--local-processes`` (not its
    ``--help``)."""
    from td3_jax.cli.argv import flag_name
    from td3_jax.cli.local_processes import FLAG  # (no JAX: quick)

    return name in ("train", "sweep") and not {"-h", "--help"} & set(args) and any(
        flag_name(arg) == FLAG for arg in args)  # fmt: skip


def _launch(name: str, args: list[str]) -> None:
    """Starts the processes of ``--local-processes`` before anything heavy is imported here
    (JAX, the environments: seconds each process would wait); they check and say the rest
    (warnings included) themselves. Its own refusal is one line and exit status 2."""
    from td3_jax.cli import local_processes

    try:
        local_processes.main(name, args)
    except Td3JaxError as err:
        error(str(err))
        sys.exit(err.exit_code)


def subcommand(name: str) -> Callable[[list[str]], None]:
    """The function of subcommand ``name`` (a key of :data:`COMMANDS`), its module imported
    now: the subcommands' modules import the presets, and those JAX (seconds), which the
    usage, the version and an unknown name do without."""
    module, function = COMMANDS[name]
    return getattr(importlib.import_module(f"td3_jax.cli.{module}"), function)


def run_reporting_errors(command: Callable[[list[str]], None], args: list[str]) -> None:
    """Runs a subcommand; a known failure becomes one message and its exit code
    (:mod:`td3_jax.common.errors`: 2 bad input, 3 a run stopped by what it computed; 130
    interrupted). A process of several ends any failure with the others
    (:func:`~td3_jax.cli.interrupts.exit_process`), an unforeseen one after its traceback."""
    runtime.quiet_library_logs()  # orbax's and asyncio's log lines, Brax's notice
    try:
        check_no_empty_path(args)
        if (warning := repeated_flags_warning(args)) is not None:
            warn(warning)
        command(expand_home(args))
    except Td3JaxError as err:
        _fail(str(err), err.exit_code)
    except Interrupted as err:
        exit_process(f"td3-jax: {err}", err.code)
    except KeyboardInterrupt:  # (before a run started: a SIGTERM of a process of several too)
        if signal.SIGTERM in process_stop()[1]:
            exit_process("td3-jax: terminated (SIGTERM)", 128 + signal.SIGTERM)
        exit_process("td3-jax: interrupted", 130)
    except Exception as err:
        _exit_failed(err)


def _exit_failed(err: Exception) -> None:
    """The failures of :func:`run_reporting_errors` that are not td3-jax's own: mujoco's
    refusal of an unknown ``MUJOCO_GL``, an operating system's refusal to write (a full disk, a
    quota, a read-only file system, no permission) as one line and exit status 2; anything
    else as its traceback (exit status 1), raised again unless the process joined others."""
    if isinstance(err, RuntimeError) and "MUJOCO_GL" in str(err):
        _fail(f"{err} (unset it or use egl, osmesa or glfw)", 2)
    if isinstance(err, OSError) and err.errno in WRITE_ERRNOS:
        _fail(f"{err.filename}: {err.strerror}" if err.filename else f"{err.strerror}", 2)
    if not joined_others():  # (a BrokenPipeError: main says the reader went away)
        raise err
    if isinstance(err, BrokenPipeError):  # (as main: 141, nothing more to the closed pipe)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        exit_process(None, 141, abandon_work=False)
    traceback.print_exc()
    exit_process(None, 1, abandon_work=False)


def _fail(message: str, code: int) -> None:
    """``td3-jax: error: MESSAGE`` and exit status ``code``, the other processes of a run left
    first (:func:`~td3_jax.cli.interrupts.exit_process`)."""
    error(message)
    exit_process(None, code, abandon_work=False)
