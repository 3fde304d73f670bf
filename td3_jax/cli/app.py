"""``td3-jax``: train, evaluate, export, render and plot from the command line.

Subcommands: ``train`` and ``sweep`` (flags from :class:`~td3_jax.config.schema.TrainConfig`),
``eval``, ``export``, ``render``, ``plot``, ``envs``, ``presets``. Bad settings print one line
and exit with code 2.
"""

from __future__ import annotations

import contextlib
import dataclasses
import decimal
import functools
import inspect
import io
import itertools
import os
import re
import shlex
import signal
import sys
import time
import types
import typing
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Annotated, Any, Literal

import tyro

from td3_jax.common import runtime, upstream
from td3_jax.common.errors import WRITE_ERRNOS
from td3_jax.config.presets import PRESETS, device_defaults, env_preset, preset
from td3_jax.config.schema import (
    SWEEPABLE,
    SWITCHED_ON_BY_THEIR_FLAG,
    ConfigError,
    TrainConfig,
    as_flag,
    check_seed,
    eval_every_within_run,
    flag,
    flag_pattern,
    idle_flags,
    idle_wandb_flags,
    rounding_note,
    validate,
    whole_iterations,
)

if typing.TYPE_CHECKING:
    from td3_jax.runner.curves import Curve

__all__ = ["main"]

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

PresetName = Literal[tuple(PRESETS)]  # type: ignore[valid-type]
#: Hidden widths as the command line takes them (no ``None``: the default is shown instead).
Widths = Annotated[tuple[int, ...] | None, tyro.conf.arg(metavar="INT [INT ...]")]


def default_in_help(metavar: str) -> Any:
    """A flag whose help says its default in words: no "(default: None)" from tyro, and
    ``metavar`` instead of ``{None}|PATH``."""
    return tyro.conf.arg(metavar=metavar, help_behavior_hint="")


#: The values a sweep tries for one setting (none: the setting is not swept).
SweptValues = Annotated[tuple[float, ...], tyro.conf.arg(help_behavior_hint="(default: not swept)")]


class Interrupted(Exception):
    """Ctrl-C or SIGTERM during a run; the message says what the run directory holds and
    ``code`` is the exit status (130 for Ctrl-C, 143 for SIGTERM, as shells report them)."""

    def __init__(self, message: str, code: int = 130):
        super().__init__(message)
        self.code = code


@dataclasses.dataclass(frozen=True)
class TrainCommand(TrainConfig):
    """Train TD3 or DDPG. Flags not given take the preset's value, else the default shown."""

    hidden_sizes: Widths = (256, 256)  # (None, for a library caller: the algorithm's own)
    """Hidden widths of actor and critics (the TD3 paper used 400 300)."""
    out: Path = Path("runs/latest")
    """Run directory: config.json, metrics.jsonl, tensorboard/, curve.png, checkpoints/."""
    resume: bool = False
    """Continue the run in --out exactly where its newest good checkpoint left it. Only
    --total-steps (to extend or shorten the run; not with --lr-schedule cosine), --matmuls,
    --keep-checkpoints, --checkpoint-every, --eval-envs, --early-evaluation, --menagerie and
    the --wandb* flags may differ from the run's config.json; other flags must match. The
    command's own flags (--quiet, --time-budget-s, --compile-cache, --devices and the
    several-hosts flags) apply to this process. A run logged to W&B continues its W&B run."""
    preset: PresetName | None = None  # type: ignore[valid-type]
    """Named settings to start from (see `td3-jax presets`); other flags override them.
    Default: the --env's own preset where one exists (said in one line), else settings for the
    device (a GPU gets thousands of environments)."""
    quiet: bool = False
    """No progress display (a live bar on a terminal, else one line per evaluation)."""
    time_budget_s: float | None = None
    """Stop after the first chunk that ends past this wall-clock budget (compile included):
    checkpointed, exit status 0, and a last line naming the --resume that continues it."""
    devices: int | None = None
    """Data-parallel over this many devices (default: all); num_envs and batch stay global."""
    coordinator_address: str | None = None
    """Several hosts: the coordinator's host:port (or env JAX_COORDINATOR_ADDRESS)."""
    num_processes: int | None = None
    """Several hosts: the number of processes (or env JAX_NUM_PROCESSES)."""
    process_id: int | None = None
    """Several hosts: this process's index (or env JAX_PROCESS_ID)."""
    compile_cache: str = "~/.cache/td3-jax/jax"
    """Directory of JAX's persistent compilation cache, so a run with the same shapes starts
    without compiling again (MJX programs take tens of seconds to compile), and of the traced
    programs (its programs/ folder), so a run of the same settings (the seed and the float
    settings that --sweep-* takes may differ) also skips making the environment and tracing;
    'off' disables both."""


@dataclasses.dataclass(frozen=True)
class SweepCommand(TrainCommand):
    """Train every combination of the swept values x --seeds seeds, all in one program.

    Ends with a table of final evaluation returns per setting, ranked, with 95% bootstrap CIs
    over seeds. Settings not swept take their single value (preset, flag or default).
    """

    sweep_actor_lr: SweptValues = ()
    """Actor learning rates to try."""
    sweep_critic_lr: SweptValues = ()
    """Critic learning rates to try."""
    sweep_tau: SweptValues = ()
    """Target Polyak rates to try."""
    sweep_discount: SweptValues = ()
    """Discounts to try."""
    sweep_expl_noise: SweptValues = ()
    """Gaussian exploration scales to try."""
    sweep_policy_noise: SweptValues = ()
    """TD3 target smoothing noise scales to try."""
    sweep_noise_clip: SweptValues = ()
    """TD3 target smoothing clips to try."""
    sweep_ou_sigma: SweptValues = ()
    """OU sigmas to try."""
    sweep_ou_theta: SweptValues = ()
    """OU thetas to try."""
    sweep_expl_noise_min: SweptValues = ()
    """Lower ends of the per-environment exploration stds to try."""
    sweep_expl_noise_max: SweptValues = ()
    """Upper ends of the per-environment exploration stds to try."""
    sweep_weight_decay: SweptValues = ()
    """AdamW weight decays to try."""
    sweep_max_grad_norm: SweptValues = ()
    """Gradient-norm bounds to try (needs --max-grad-norm)."""
    sweep_max_weight_norm: SweptValues = ()
    """Weight-norm bounds to try (needs --max-weight-norm)."""
    sweep_v_min: SweptValues = ()
    """Lowest values of the distributional critic's support to try."""
    sweep_v_max: SweptValues = ()
    """Highest values of the distributional critic's support to try."""
    sweep_lr_final_fraction: SweptValues = ()
    """Ends of the cosine learning-rate schedule to try (needs --lr-schedule cosine)."""
    sweep_return_bound: SweptValues = ()
    """Return bounds of the reward scaling to try (needs --return-bound)."""


@dataclasses.dataclass(frozen=True)
class EvalCommand:
    """Evaluate the newest checkpoint of a run with the deterministic policy."""

    run: Path
    """Run directory written by `td3-jax train`."""
    episodes: int = 32
    """Episodes (one per vectorised environment)."""
    seed: int = 12345
    """Seed of the evaluation environments."""


@dataclasses.dataclass(frozen=True)
class ExportCommand:
    """Write the deterministic policy of a run's newest checkpoint to one file, in float32:
    observation normalisation, actor and the mapping to the environment's action bounds."""

    run: Path
    """Run directory written by `td3-jax train`."""
    format: Annotated[str, tyro.conf.arg(metavar="{onnx,npz}")]
    """onnx (opset 17, needs pip install 'td3-jax[export]') or npz (run it with NumPy alone:
    td3_jax/tools/policy_file.py)."""
    out: Annotated[Path | None, default_in_help("PATH")] = None
    """Output file, ending in .onnx or .npz as --format says (default: RUN/policy.onnx or
    RUN/policy.npz)."""
    member: Annotated[int | None, default_in_help("INT")] = None
    """Member (seed / swept setting) to export, from 0 (default: the best in the checkpoint's
    evaluation in metrics.jsonl; member 0 for a single-seed run)."""


@dataclasses.dataclass(frozen=True)
class RenderCommand:
    """Write a video (MP4 or GIF) of the deterministic policy of a run's newest checkpoint.

    The episodes are those `td3-jax eval` runs with the same --episodes and --seed (the same
    returns); each ends at its termination or time limit, and they play one after another.
    """

    run: Path
    """Run directory written by `td3-jax train`."""
    out: Annotated[Path | None, default_in_help("PATH")] = None
    """Video file to write, .mp4 or .gif. Default: RUN/rollout.mp4 (with --gif,
    RUN/rollout.gif), which a later render replaces; any other existing file is refused."""
    gif: bool = False
    """Write a GIF instead of an MP4."""
    episodes: int = 1
    """Episodes to render, one after another."""
    seed: int = 12345
    """Seed of the evaluation environments (td3-jax eval's default)."""
    member: Annotated[int | None, default_in_help("INT")] = None
    """Member of a multi-seed run or sweep (its index in members.json); default: the highest
    return of the checkpoint's evaluation in metrics.jsonl, as td3-jax export picks."""
    camera: Annotated[str | None, default_in_help("NAME|INDEX")] = None
    """A camera of the model, by name or index (-1: MuJoCo's free camera); default: a free
    camera tracking the root body."""
    width: int = 320
    """Frame width in pixels (at most 8192)."""
    height: int = 240
    """Frame height in pixels (at most 8192)."""
    fps: float = 30.0
    """Frames per second of the video."""


@dataclasses.dataclass(frozen=True)
class PlotCommand:
    """Redraw a run's curve.png from its metrics.jsonl, or compare several runs in one figure
    (each run's mean return and band, against env steps and against wall-clock)."""

    run: Annotated[tuple[Path, ...], tyro.conf.arg(metavar="DIR [DIR ...]")]
    """Run directories written by `td3-jax train` or `td3-jax sweep`: one, or several to
    compare."""
    out: Annotated[Path | None, default_in_help("PATH")] = None
    """Image to write, .png, .pdf or .svg: a new file, or a figure td3-jax plot drew before
    (replaced; any other file is refused); default: RUN/curve.png for one run (replaced);
    several runs need it."""


@dataclasses.dataclass(frozen=True)
class EnvsCommand:
    """List the environments this installation knows, with what each still needs to run."""

    menagerie: Path | None = None
    """Look for the robots' MuJoCo Menagerie folders here too (as `td3-jax train --menagerie`)."""


@dataclasses.dataclass(frozen=True)
class PresetsCommand:
    """List the presets and the flags each sets (flags given to train override them)."""

    names: Annotated[
        tuple[str, ...],
        tyro.conf.Positional,
        tyro.conf.arg(metavar="[NAME ...]", help_behavior_hint="(default: every preset)"),
    ] = ()
    """Presets to show."""


def _parse(command_type: type, args: list[str], prog: str, default=None):
    """``tyro.cli`` whose parse errors become one ``ConfigError`` line (tyro draws a box)."""
    captured = io.StringIO()
    args = whole_numbers_written_out(command_type, args)
    try:
        with contextlib.redirect_stderr(captured), upstream.tyro_help_unwrapped_by(help_paragraphs):
            command = _tyro_cli(command_type, args, default, prog)
    except SystemExit as exit_:
        if exit_.code in (0, None):
            raise
        message = _parse_error(captured.getvalue(), command_type, args, prog)
        raise ConfigError(message) from None
    return command


def _tyro_cli(command_type: type, args: list[str], default: Any, prog: str) -> Any:
    """``tyro.cli``, tried a second time after a ``SystemError`` (CPython 3.11's "AST
    constructor recursion depth mismatch", seen once in CI while tyro parsed this module's
    source for help text; it passed when run again)."""
    try:
        return tyro.cli(command_type, args=args, default=default, prog=prog)
    except SystemError:
        return tyro.cli(command_type, args=args, default=default, prog=prog)


#: A number in scientific notation (``1e6``, ``2.5E+4``), as users write step counts.
_SCIENTIFIC = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)[eE][+-]?\d{1,4}", re.ASCII)


def whole_numbers_written_out(command_type: type, args: list[str]) -> list[str]:
    """``args`` with each value of a whole-number flag of ``command_type`` that is written in
    scientific notation and is a whole number (``--total-steps 1e6``, ``=2.5e4``) written out
    (``1000000``); other values unchanged (``1.5e0`` stays, for the parser to refuse). Only a
    tuple flag's values are all rewritten: a second value after a one-number flag is left as
    typed, for the parser's error to quote."""
    out, kind, several = [], None, False
    for arg in args:
        if arg.startswith("--"):
            name, equals, value = arg.partition("=")
            kind, several = _number_kinds(command_type, name[2:].replace("-", "_")) or (None, False)
            arg = f"{name}={_written_out(value, kind)}" if equals else arg
            kind = None if equals else kind
        else:
            arg = _written_out(arg, kind)
            kind = kind if several else None  # (one value: a second is the parser's to refuse)
        out.append(arg)
    return out


def _written_out(value: str, kind: type | None) -> str:
    """``value`` as a plain integer where ``kind`` is int and it is a whole number written
    in scientific notation, else ``value``."""
    if kind is not int or not _SCIENTIFIC.fullmatch(value):
        return value
    number = decimal.Decimal(value)
    if number.adjusted() > 30:  # (far past any count; the flag's own check refuses it)
        return value
    return str(int(number)) if number == number.to_integral_value() else value


#: A line that starts an item of a list in a docstring (``- x``, ``* x``, ``1. x``, ``2) x``).
_LIST_ITEM = re.compile(r"\s*([-*]|\d+[.)])\s")


def help_paragraphs(docstring: str) -> str:
    """A docstring as ``--help`` text: its lines joined into paragraphs (blank lines between
    paragraphs kept; list items each on a line of their own), so the terminal wraps them."""
    paragraphs = re.split(r"\n\s*\n", inspect.cleandoc(docstring))
    return "\n\n".join(_joined(paragraph.splitlines()) for paragraph in paragraphs).strip()


def _joined(lines: list[str]) -> str:
    """One paragraph's lines as one line, but a new line for each list item."""
    text = lines[0].strip() if lines else ""
    for line in lines[1:]:
        text += ("\n" if _LIST_ITEM.match(line) else " ") + line.strip()
    return text


def _parse_error(text: str, command_type: type, args: list[str], prog: str) -> str:
    """tyro's error box as one line: the options not known (with the closest known one), a
    value that is not a number or not a choice, a flag without its value, the required ones
    missing, else the box's first part (what went wrong, without help text)."""
    title, sections = _tyro_box(text)
    first = " ".join(line.strip() for line in sections[0])
    if title == "Unrecognized options":
        return _unrecognized(command_type, args, prog, sections[0])
    said = None
    if title == "Value error":
        said = _value_error(command_type, args, first)
    elif title == "Invalid choice":
        said = _invalid_choice(first)
    elif title == "Missing argument" and (named := re.search(r"argument '(--[\w-]+)'", first)):
        said = f"{named.group(1)} needs a value (see {prog} --help)"
    elif title == "Required options":  # "Missing from PROG:", each flag 4 deeper, its help 8
        flag = " " * (len(sections[0][0]) - len(sections[0][0].lstrip()) + 4) + "-"
        missing = [line.split()[0] for line in sections[0] if line.startswith(flag)]
        said = missing and f"{prog} needs {', '.join(missing)} (see {prog} --help)"
    return said or first or title or f"could not parse {' '.join(args)} (see {prog} --help)"


def _value_error(command_type: type, args: list[str], text: str) -> str | None:
    """``--actor-lr takes a number, got 'abc'``: tyro's "Error parsing FLAG" for a flag of
    numbers, in one line (None for other flags or errors)."""
    match = re.match(r"Error parsing (--[\w-]+):", text)
    kinds = match and _number_kinds(command_type, match.group(1)[2:].replace("-", "_"))
    if not kinds:
        return None
    flag, (kind, several) = match.group(1), kinds
    given = _first_unparsed(_flag_values(args, flag), kind)
    what = "whole number" if kind is int else "number"
    said = f"{flag} takes {what}s" if several else f"{flag} takes a {what}"
    bad = [value for value in given if not _reads_as(kind, value)]
    if several and 0 < len(bad) < len(given):  # (name the values it could not read)
        return f"{said}, got {' '.join(map(repr, bad))} (of {' '.join(given)})"
    return f"{said}, got {' '.join(map(repr, given)) or 'nothing'}"


def _reads_as(kind: type, value: str) -> bool:
    """Whether ``kind`` (int or float) reads ``value`` (``None``: tyro's "leave it out")."""
    if value == "None":
        return True
    try:
        kind(value)
    except ValueError:
        return False
    return True


def _flag_values(args: list[str], flag: str) -> list[list[str]]:
    """The values given to ``flag`` each time it appears in ``args`` (``--flag=v`` or
    ``--flag v ...``), in order."""
    found = []
    for i, arg in enumerate(args):
        if arg.startswith(flag + "="):
            found.append([arg.split("=", 1)[1]])
        elif arg == flag:
            found.append(list(itertools.takewhile(lambda a: not a.startswith("--"), args[i + 1 :])))
    return found


def _first_unparsed(occurrences: list[list[str]], kind: type) -> list[str]:
    """The values of the first occurrence that ``kind`` cannot read (the one the parser
    refused: ``--num-envs 4 --num-envs x`` refuses ``x``), else the last one."""
    for values in occurrences:
        if not all(_reads_as(kind, value) for value in values):
            return values
    return occurrences[-1] if occurrences else []


def _invalid_choice(text: str) -> str | None:
    """``--impl 'cuda' is not one of jax, warp``: tyro's "invalid choice" in one line, with the
    closest choice, and without the ``None`` that tyro lists for a flag whose default is to
    leave it out (None for other errors)."""
    import difflib

    pattern = r"invalid choice '(.*)' for argument '(--[\w-]+)'\. Expected one of \((.*)\)\."
    match = re.match(pattern, text)
    if not match:
        return None
    given, flag, listed = match.groups()
    choices = sorted({c.strip(" '") for c in listed.split(",")} - {"None"})  # (tyro's: a set)
    close = difflib.get_close_matches(given.lower(), choices, n=1, cutoff=0.6)
    hint = f"; did you mean {close[0]}?" if close else ""
    return f"{flag} {given!r} is not one of {', '.join(choices)}{hint}"


def _number_kinds(command_type: type, name: str) -> tuple[type, bool] | None:
    """``(int or float, whether several)`` for a field of ``command_type`` holding numbers (a
    number, an optional one or a tuple of them); None for other fields."""
    hint = typing.get_type_hints(command_type, include_extras=False).get(name)
    several = False
    parts = [hint]
    while parts:
        part = parts.pop()
        if part in (int, float):
            return part, several
        origin = typing.get_origin(part)
        if origin is tuple:
            several = True
        if origin in (tuple, typing.Union, types.UnionType):
            parts.extend(
                a for a in typing.get_args(part) if a is not Ellipsis and a is not type(None)
            )
    return None


def _tyro_box(text: str) -> tuple[str, list[list[str]]]:
    """``(title, sections)`` of tyro's error box (drawn with box characters, or in ASCII where
    the output cannot take them): the title line, then the parts between its rules, each part
    its lines with their indentation (an empty list where there is none)."""
    lines = [line.rstrip().removesuffix("│").rstrip() for line in text.splitlines()]
    lines = [line.replace("│ ", "", 1) if line.startswith("│") else line for line in lines]
    lines = [line for line in lines if line.strip() and not line.startswith("usage:")]
    if not lines:
        return "", [[]]
    sections: list[list[str]] = [[]]
    for line in lines[1:]:
        if len(line.strip()) > 2 and set(line.strip()) <= set("─-╰╯"):
            sections.append([])
        else:
            sections[-1].append(line)
    return lines[0].strip("╭─╮ "), [part for part in sections if part] or [[]]


#: Other libraries' names for td3-jax's flags (CleanRL, Stable-Baselines3, FastTD3), offered
#: for an unknown flag of that name: ``--gamma`` (did you mean --discount?).
_OTHER_NAMES = {
    "gamma": ("discount",),
    "env-name": ("env",),
    "actor-learning-rate": ("actor-lr",),
    "critic-learning-rate": ("critic-lr",),
    "num-steps": ("n-step",),
    "use-wandb": ("wandb",),
    "learning-starts": ("warmup-steps",),
    "learning-rate": ("actor-lr", "critic-lr"),
    "total-timesteps": ("total-steps",),
    "n-envs": ("num-envs",),
    "env-id": ("env",),
    "policy-frequency": ("policy-freq",),
    "policy-delay": ("policy-freq",),
    "target-policy-noise": ("policy-noise",),
    "target-noise-clip": ("noise-clip",),
    "exploration-noise": ("expl-noise",),
    "action-noise": ("expl-noise",),
    "gradient-steps": ("updates-per-iter",),
    "num-updates": ("updates-per-iter",),
    "std-min": ("expl-noise-min",),
    "std-max": ("expl-noise-max",),
    "num-eval-envs": ("eval-envs",),
    "eval-freq": ("eval-every",),
    "eval-interval": ("eval-every",),
    "track": ("wandb",),
    "wandb-project-name": ("wandb-project",),
}


def _unrecognized(command_type: type, args: list[str], prog: str, listed: list[str]) -> str:
    """``unrecognized option --totl-steps (did you mean --total-steps?)``, for each option in
    ``args`` that ``command_type`` does not have: the flags that end with it (``--lr``:
    ``--actor-lr or --critic-lr``), else the closest spelling; else tyro's list of leftover
    arguments."""
    import difflib

    known = {"--help", "-h"}
    for field in dataclasses.fields(command_type):
        known.add(f"--{field.name.replace('_', '-')}")
        if field.type in (bool, "bool"):
            known.add(f"--no-{field.name.replace('_', '-')}")
    unknown = [name for name in (arg.split("=", 1)[0] for arg in args)
               if name.startswith("-") and name not in known and not _is_number(name)]  # fmt: skip
    if not unknown:
        leftover = " ".join(listed).split(":", 1)[-1].strip() or " ".join(args)
        return f"unexpected argument {leftover} (see {prog} --help)"
    sweeps = [name for name in unknown if name.startswith("--sweep-")]
    if sweeps and prog == "td3-jax train":  # a sweep's lists are `td3-jax sweep`'s flags
        return (f"{sweeps[0]}: the --sweep-* lists are flags of td3-jax sweep, which trains "
                f"every combination of their values: td3-jax sweep {' '.join(args)}")  # fmt: skip
    settings = {name: "--" + name.removeprefix("--sweep-") for name in sweeps}
    not_swept = [name for name in sweeps if settings[name] in known]  # (a setting, not a typo)
    if not_swept and prog == "td3-jax sweep":
        return (f"{not_swept[0]}: {settings[not_swept[0]]} cannot be swept (it changes the "
                "program, not a value in it); run td3-jax train once per value. A sweep "
                f"varies {', '.join(flag(s)[2:] for s in SWEEPABLE)}")  # fmt: skip
    names = {name.lstrip("-"): name for name in known}
    said = []
    for name in dict.fromkeys(unknown):
        close = _closest_flags(name.lstrip("-"), names) or difflib.get_close_matches(
            name.lstrip("-"), names, n=1, cutoff=0.7
        )
        guesses = " or ".join(names[c] for c in close[:4]) + (" or ..." if len(close) > 4 else "")
        said.append(f"{name} (did you mean {guesses}?)" if close else name)
    hint = "" if len(said) == sum("did you mean" in s for s in said) else f" (see {prog} --help)"
    return f"unrecognized option{'s' if len(said) > 1 else ''} {', '.join(said)}{hint}"


def _closest_flags(bare: str, names: Iterable[str]) -> list[str]:
    """The flags (bare: ``actor-lr``) that ``bare`` most likely means, by another library's
    name (``gamma``: ``discount``) or as the end of ours (``lr``: ``actor-lr``, ``critic-lr``),
    each also under ``sweep-`` (``sweep-gamma``: ``sweep-discount``); ``[]``: none."""
    stem = bare.removeprefix("sweep-")
    prefix = bare[: len(bare) - len(stem)]
    other = [prefix + n for n in _OTHER_NAMES.get(stem.replace("_", "-"), ())]
    ours = [n for n in other if n in names]
    ends = sorted(n for n in names if n.startswith(prefix) and n.endswith("-" + stem)
                  and not n.startswith("no-") and n != bare)  # fmt: skip
    return ours or ends


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _flag_value(args: list[str], flag: str) -> str | None:
    for i, arg in enumerate(args):
        if arg == flag and i + 1 < len(args):
            return args[i + 1]
        if arg.startswith(flag + "="):
            return arg.split("=", 1)[1]
    return None


def _resumed_settings(cfg: TrainConfig, out: Path) -> TrainConfig:
    """``cfg`` for a --resume of ``out``: an --eval-every given as the run was started (3000,
    which the fresh run took as the whole iterations of 3008) is the saved one; and, where the
    run is not in use and has a checkpoint, a flag that the resume may not change is refused
    before the settings' own checks, whose advice (``try --batch-size 256``) would name a
    change that the resume then refuses (:func:`td3_jax.runner.rundir.config_changes`)."""
    from td3_jax.runner import rundir

    if not (out / rundir.CONFIG_FILE).exists():
        return cfg  # (the run says there is nothing to resume)
    saved = rundir.load_config(out)
    if cfg.env_steps_per_iter > 0 and saved.steps_per_chunk in whole_iterations(
        cfg.eval_every, cfg.env_steps_per_iter
    ):
        cfg = dataclasses.replace(cfg, eval_every=saved.eval_every)
    import jax

    if jax.process_index() == 0:  # (as the resume itself checks first, in its writer only)
        rundir.check_not_in_use(out)
    if rundir.checkpoint_steps(out):
        rundir.config_changes(saved, cfg, rundir.load_members(out, cfg))
    return cfg


def _base_config(args: list[str]) -> tuple[TrainConfig, str | None, str]:
    """``(defaults, preset, source)`` for the train flags, ``source`` saying where they come
    from: ``resume`` (the run's saved config.json), ``preset`` (--preset), ``env`` (the preset
    made for --env) or ``device`` (an environment without a preset: :func:`device_defaults`,
    the CPU ones here; train_main swaps in the accelerator's once JAX is up)."""
    from td3_jax.runner.rundir import CONFIG_FILE, load_config

    out = _flag_value(args, "--out") or str(TrainCommand.out)
    name = _flag_value(args, "--preset")
    if "--resume" in args:
        if name:
            _check_resumed_preset(name, Path(out))
        if (Path(out) / CONFIG_FILE).exists():
            return load_config(Path(out)), None, "resume"
        return TrainConfig(), None, "resume"  # (train() says there is nothing to resume)
    if name:
        return preset(name), name, "preset"  # ConfigError naming the closest for an unknown one
    env = _flag_value(args, "--env") or TrainConfig.env
    name = env_preset(env)
    if name:
        return dataclasses.replace(preset(name), env=env), name, "env"
    return device_defaults(env, accelerator=False), None, "device"


def _check_resumed_preset(name: str, out: Path) -> None:
    """A resume keeps its run's config: ``--preset`` may only name the preset the run was
    started from (so the command that started it, plus ``--resume``, resumes it)."""
    from td3_jax.runner.rundir import load_run_info

    try:
        started = load_run_info(out).get("preset")
    except Exception:  # (no or an unreadable config.json: train() says what is wrong)
        return
    if started != name:
        was = f"--preset {started}" if started else "no preset"
        raise ConfigError(f"--preset {name} given but the run was started with {was}; a resume "
                          "keeps its run's config (leave --preset out)")  # fmt: skip


def _given_fields(args: list[str]) -> set[str]:
    """The TrainConfig fields that a flag in ``args`` names (``--num-envs``, ``--no-x``, ...)."""
    names = {f.name for f in dataclasses.fields(TrainConfig)}
    given = set()
    for arg in args:
        if not arg.startswith("--"):
            continue
        name = arg[2:].split("=", 1)[0].replace("-", "_")
        if name not in names and name.startswith("no_"):
            name = name[3:]
        if name in names:
            given.add(name)
    return given


def preset_source_note(message: str, cfg: TrainConfig, preset_name: str | None,
                       given: set[str]) -> str:  # fmt: skip
    """`` (--critic-hidden-sizes 1024 512 256 from preset 't1')``: the settings that an error
    ``message`` names by their flag and that came from the preset, not from a flag given (so
    the user sees where a value they never typed comes from); empty where there is none."""
    if preset_name is None:
        return ""

    found = {name: re.search(flag_pattern(name), message)
             for name in PRESETS[preset_name] if name not in given}  # fmt: skip
    named = sorted((match.start(), name) for name, match in found.items() if match)
    if not named:
        return ""
    values = ", ".join(as_flag(name, getattr(cfg, name)) for _, name in named)
    return f" ({values} from preset {preset_name!r})"


@contextlib.contextmanager
def preset_noted(cfg: TrainConfig, preset_name: str | None, given: set[str]) -> Iterator[None]:
    """Re-raises a :class:`ConfigError` of its block with :func:`preset_source_note` added."""
    try:
        yield
    except ConfigError as err:
        note = preset_source_note(str(err), cfg, preset_name, given)
        if not note:
            raise
        raise type(err)(f"{err}{note}") from err


def _scale_to_device(cfg: TrainConfig, args: list[str]) -> TrainConfig:
    """An environment without a preset on an accelerator: its defaults, then the given flags."""
    import jax

    if jax.default_backend() == "cpu":
        return cfg
    base = device_defaults(cfg.env, accelerator=True)
    return dataclasses.replace(base, **{n: getattr(cfg, n) for n in _given_fields(args)})


def _defaults_note(cfg: TrainConfig, name: str | None, source: str) -> str | None:
    """The line saying which settings a run without --preset got (None when it named one)."""
    if source == "env":
        return f"using preset {name!r} for {cfg.env} (pass --preset or flags to change it)"
    if source != "device":
        return None
    from td3_jax import envs

    if cfg.env not in envs.known_names() and not envs.is_custom(cfg.env):
        return None  # (train() reports the unknown name)
    import jax

    device = "CPU" if jax.default_backend() == "cpu" else "accelerator"
    return (
        f"no preset for {cfg.env}: the {device} defaults apply where no flag is given (this "
        f"run: {cfg.num_envs} environments, {cfg.total_steps} steps; --preset NAME picks one)"
    )


def unnamed_env_warning(cfg: TrainConfig, preset_name: str | None, source: str,
                        given: frozenset[str] | set[str]) -> str | None:  # fmt: skip
    """A warning when a named preset that sets no environment (``td3-classic``: a recipe for
    any) runs without ``--env``: the default environment trains, which nothing else says."""
    if source != "preset" or preset_name is None or "env" in given:
        return None
    if "env" in PRESETS[preset_name]:
        return None
    return (f"preset {preset_name!r} sets no environment and no --env was given: training "
            f"{cfg.env}, the default (--env picks one)")  # fmt: skip


def cpu_size_warning(cfg: TrainConfig, backend: str, source: str = "preset") -> str | None:
    """A warning when a run sized for an accelerator is about to start on a CPU, with the flags
    that size it for one (together they make a valid run: a batch and a warm-up within the
    steps). ``source`` is where the settings came from (:func:`_base_config`): only a
    ``--preset`` given can be left out."""
    steps = cfg.run_steps  # (what runs: whole chunks)
    if backend != "cpu" or (cfg.num_envs < 1024 and steps < 5_000_000):
        return None
    sizes = (("--num-envs 16", cfg.num_envs >= 1024),
             ("--total-steps 20000", steps >= 5_000_000),
             ("--batch-size 256", cfg.batch_size > 4096),
             ("--warmup-steps 1000", cfg.warmup_steps > 10_000),
             ("--no-eval-in-chunk", steps >= 5_000_000 and cfg.eval_in_chunk),
             # (evaluations, and checkpoints, in the 20000 steps: else one chunk, all or nothing)
             ("--eval-every 4000", steps >= 5_000_000 and cfg.eval_every > 20_000))  # fmt: skip
    if source == "resume":  # (its sizes cannot change)
        return (f"this run is sized for a GPU ({cfg.num_envs} environments, {steps} steps, "
                f"batch {cfg.batch_size}) and JAX found only a CPU: it will train for hours; "
                "a resume keeps its sizes, so resume it where a GPU is")  # fmt: skip
    tips = [tip for tip, large in sizes if large]  # (only what is sized for a GPU)
    alternative = " (or no --preset)" if source == "preset" else ""
    return (
        f"this run is sized for a GPU ({cfg.num_envs} environments, {steps} steps, "
        f"batch {cfg.batch_size}) and JAX found only a CPU: it will compile for minutes and "
        f"train for hours. For a CPU try {' '.join(tips)}{alternative}"
    )


def critic_network_note(cfg: TrainConfig, preset_name: str | None, given: set[str]) -> str | None:
    """A note when ``--critic-network`` is given and differs from the preset's, while the
    critics' sizes are still the preset's (made for the other network): ``--preset g1
    --critic-network mlp`` gets plain critics of 256 256, not the 1024 512 256 of the others."""
    if preset_name is None or "critic_network" not in given or "critic_hidden_sizes" in given:
        return None
    base = preset(preset_name)
    if base.critic_network == cfg.critic_network or base.critic_hidden_sizes is None:
        return None
    sizes = as_flag("critic_hidden_sizes", base.critic_hidden_sizes)
    return (f"--critic-network {cfg.critic_network} keeps the {sizes} of preset "
            f"{preset_name!r} (set for its {base.critic_network} critics); give "
            "--critic-hidden-sizes to choose others")  # fmt: skip


def eval_size_warning(cfg: TrainConfig) -> str | None:
    """A warning when ``--eval-envs`` dwarfs the training (more than 1024 environments and 8
    times ``--num-envs``): every evaluation steps them all through a whole episode."""
    if cfg.eval_envs <= max(1024, 8 * cfg.num_envs):
        return None
    return (
        f"--eval-envs {cfg.eval_envs} is {cfg.eval_envs / cfg.num_envs:.0f}x --num-envs "
        f"{cfg.num_envs}: every evaluation steps {cfg.eval_envs} environments through a whole "
        "episode (the env steps/s shown leave it out; metrics.jsonl's eval_s has its seconds)"
    )


def _announce(cfg: TrainConfig, preset_name: str | None, source: str,
              asked_eval_every: int | None = None, rounding: bool = True) -> None:  # fmt: skip
    """Prints which settings the run got, before it starts (``rounding``: also how
    ``--total-steps`` and ``--eval-every`` round to whole chunks and iterations)."""
    rounded = rounding_note(cfg, asked_eval_every) if rounding else None
    for line in (_defaults_note(cfg, preset_name, source), rounded):
        if line:
            print(line, flush=True)


def _choose_physics(cfg: TrainConfig, devices: int | None) -> tuple[TrainConfig, int | None]:
    """A Playground task's physics (``--impl``; default: MuJoCo Warp where it can run) and the
    device count, said in one line; ``--impl warp`` where Warp cannot run is a ConfigError
    naming what is missing. Warp runs on one device: by default a run then takes one GPU."""
    if not cfg.env.startswith("playground/"):
        return cfg, devices
    import jax

    from td3_jax.envs import physics

    asked = cfg.impl or ("warp" if cfg.env_backend == "warp" else None)
    try:
        impl = physics.resolve(asked)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    note = ""
    if impl == "warp" and devices is None and jax.device_count() > 1:
        devices, note = 1, f" on one GPU (--impl jax spreads a run over all {jax.device_count()})"
    elif impl == "jax" and asked is None:
        note = f": {physics.warp_missing()}"  # (why not Warp, the default where it runs)
    if jax.process_index() == 0:
        name = "MuJoCo Warp" if impl == "warp" else "MJX's JAX implementation"
        print(f"physics: {name} (--impl {impl}){note}", flush=True)
    return dataclasses.replace(cfg, impl=impl), devices


def no_learning_warning(cfg: TrainConfig) -> str | None:
    """A warning for ``--updates-per-iter 0``: the run collects and evaluates but never
    learns (a collection-only run, as a throughput benchmark wants, is the one use)."""
    if cfg.updates_per_iter:
        return None
    return ("--updates-per-iter 0: no gradient updates, so the policy never learns (it "
            "evaluates its initial networks throughout)")  # fmt: skip


def _when_prepared(cfg: TrainConfig, preset_name: str | None, source: str,
                   asked_eval_every: int | None = None, given: frozenset[str] = frozenset(),
                   resumed: bool = False) -> None:  # fmt: skip
    """Once the run's settings, directory and environment are good (a run they stop says
    nothing else): which settings it got, and warnings (a GPU-sized run on a CPU, an
    evaluation that dwarfs the training, no updates). A resume says how its steps round only
    where ``--total-steps`` was typed (its fresh start said so already)."""
    import jax

    if jax.process_index() != 0:
        return
    rounding = not resumed or "total_steps" in given
    _announce(cfg, preset_name, source, asked_eval_every, rounding)
    warnings = (unnamed_env_warning(cfg, preset_name, source, given),
                cpu_size_warning(cfg, jax.default_backend(), source),
                critic_network_note(cfg, preset_name, set(given)), eval_size_warning(cfg),
                no_learning_warning(cfg), *idle_flags(cfg, set(given)))  # fmt: skip
    for warning in warnings:
        if warning:
            print(f"td3-jax: warning: {warning}", file=sys.stderr, flush=True)


def _sweep_values(command: Any, args: list[str]) -> dict[str, list[float]]:
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
    given = _given_fields(args)
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
    from td3_jax.runner.run import check_time_budget
    from td3_jax.runner.sharding import check_devices

    check_devices(command.devices)
    check_time_budget(command.time_budget_s)


def _parse_train(args: list[str], sweeping: bool) -> tuple[Any, TrainConfig, str | None, str]:
    """The train (or sweep) command of ``args`` over its defaults (a preset, the run's own
    config.json on --resume, the device's), its TrainConfig, the preset's name and where the
    defaults came from; the flags that need nothing built are checked here."""
    command_type = SweepCommand if sweeping else TrainCommand
    prog = "td3-jax sweep" if sweeping else "td3-jax train"
    base, preset_name, source = _base_config(args)
    default = command_type(
        **dataclasses.asdict(base), preset=preset_name if source == "preset" else None
    )
    command = _parse(command_type, args, prog, default=default)
    cfg = TrainConfig(**{f.name: getattr(command, f.name) for f in dataclasses.fields(TrainConfig)})
    idle_wandb_flags(cfg, _given_fields(args))
    _check_process_flags(command)
    if sweeping and command.resume:
        _check_sweep_to_resume(command.out)
    return command, cfg, preset_name, source


def train_main(args: list[str], sweeping: bool = False) -> None:
    from td3_jax.runner.rundir import is_sweep_dir

    command, cfg, preset_name, source = _parse_train(args, sweeping)
    sweep = _sweep_values(command, args) if sweeping else None
    from td3_jax import envs

    envs.check_name(cfg.env)  # before anything about the environment is said
    given_cache = any(arg.split("=", 1)[0] == "--compile-cache" for arg in args)
    program_dir = runtime.enable_compile_cache(command.compile_cache, given=given_cache)
    from td3_jax.runner.sharding import initialize_distributed

    initialize_distributed(command.coordinator_address, command.num_processes, command.process_id)
    if source == "device":
        cfg = _scale_to_device(cfg, args)
    cfg, devices = _choose_physics(cfg, command.devices)
    asked_eval_every = cfg.eval_every
    if not command.resume:  # (a resume keeps the chunk its checkpoints were written with)
        cfg = eval_every_within_run(cfg)
    typed = _given_fields(args)
    given = typed | set(sweep or {})  # (a swept setting is every member's own)
    if command.resume:
        cfg = _resumed_settings(cfg, command.out)
    with preset_noted(cfg, preset_name, given):
        validate(cfg)  # (said once the directory and the environment are good too)
    prepared = functools.partial(_when_prepared, cfg, preset_name, source, asked_eval_every,
                                 frozenset(typed), command.resume)  # fmt: skip
    started = time.perf_counter()
    with preset_noted(cfg, preset_name, given):
        records = _train_stoppably(cfg, command, devices=devices, sweep=sweep, preset=preset_name,
                                   on_prepared=prepared, program_dir=program_dir)  # fmt: skip
    if not records:
        print(nothing_to_do(command.out, cfg))
        return
    ranked = sweeping or (command.resume and is_sweep_dir(command.out))  # (also train --resume)
    _print_end(records, cfg, command, time.perf_counter() - started, ranked)


def _train_stoppably(cfg: TrainConfig, command: Any, **train_options: Any) -> list[dict[str, Any]]:
    """``run.train`` under handlers that turn SIGINT and SIGTERM into a stop at the next chunk
    (a second signal stops at once); a stop leaves the last checkpoint and says, in one line,
    what it left (``Interrupted``, exit 130, or 143 for SIGTERM)."""
    import jax

    from td3_jax.runner.run import train
    from td3_jax.runner.rundir import interrupted_message

    received: list[int] = []
    stop = runtime.StopToken()  # set by the signal handlers: this run's only way to be stopped
    ended = functools.partial(interrupted_message, command.out)  # what a stop leaves, one line
    try:
        signals = runtime.stop_signals(stop, received, say=jax.process_index() == 0,
                                       aftermath=ended)  # fmt: skip
        with signals:
            return train(cfg, command.out, resume=command.resume, stop=stop,
                         progress=not command.quiet, time_budget_s=command.time_budget_s,
                         **train_options)  # fmt: skip
    except KeyboardInterrupt:
        if signal.SIGTERM in received:
            raise Interrupted(ended("terminated (SIGTERM)"), 128 + signal.SIGTERM) from None
        raise Interrupted(ended()) from None


def _check_sweep_to_resume(out: Path) -> None:
    """``td3-jax sweep --resume`` of a run that ``td3-jax train`` started is one line naming
    the command that resumes it (a sweep's table would rank settings it never swept)."""
    from td3_jax.runner import rundir

    if (Path(out) / rundir.CONFIG_FILE).exists() and not rundir.is_sweep_dir(out):
        raise ConfigError(f"{out} holds a run of td3-jax train, not a sweep: resume it with "
                          f"{rundir.resume_command(out)}")  # fmt: skip


def nothing_to_do(out: Path, cfg: TrainConfig) -> str:
    """The line of a ``--resume`` that finds its run complete: how far the run went and how to
    train it further (a larger ``--total-steps``; a new run where a cosine schedule fixed its
    length)."""
    done = f"{cfg.run_steps:,}"
    from td3_jax.runner.rundir import load_config

    planned = load_config(out).run_steps  # (a complete run's resume rewrote nothing)
    if planned > cfg.run_steps:  # a stopped run resumed with a shorter --total-steps
        go_on = f"td3-jax train --out {shlex.quote(str(out))} --resume"
        return (f"nothing to do: the run in {out} has taken {done} env steps, what --total-steps "
                f"{cfg.total_steps:,} asks; it was set for {planned:,}: {go_on} goes on to "
                "them")  # fmt: skip
    if cfg.lr_schedule == "cosine":
        further = ("its cosine learning-rate schedule fixed its length: start a new run with a "
                   "larger --total-steps to train longer")  # fmt: skip
    else:
        more = 2 * cfg.run_steps
        go_on = f"td3-jax train --out {shlex.quote(str(out))} --resume --total-steps {more}"
        further = f"{go_on} goes on to {more:,}"
    return f"nothing to do: the run in {out} is complete ({done} env steps); {further}"


def _print_end(records: list[dict], cfg: TrainConfig, command: Any, process_s: float,
               sweeping: bool) -> None:  # fmt: skip
    """The lines that end a run this process trained: :func:`done_line`, a note when
    ``--time-budget-s`` stopped it before its last step (and how to go on), a sweep's ranking."""
    resumed_at = records[0]["env_steps"] - cfg.steps_per_chunk if command.resume else None
    count = records[-1]["members"]
    pooled = f" over all {count} members" if count > 1 else " over its 1 member"
    pooled = f"{pooled} (per setting below)" if sweeping else ""
    taken = records[-1]["env_steps"]
    early = command.time_budget_s is not None and taken < cfg.run_steps
    print(done_line(records[-1], command.out, process_s, resumed_at, pooled,
                    word="stopped" if early else "done"))  # fmt: skip
    if early:
        from td3_jax.runner.rundir import resume_command

        print(f"stopped by --time-budget-s {command.time_budget_s:g} at {taken:,} of "
              f"{cfg.run_steps:,} env steps; {resume_command(command.out)} "
              "continues it")  # fmt: skip
    if sweeping and "per_member" in records[-1]:
        print_sweep_ranking(records[-1])


def done_line(last: dict, out: Path, process_s: float | None = None,
              resumed_at: int | None = None, pooled: str = "",
              word: str = "done") -> str:  # fmt: skip
    """The line that ends a run (``word``: done, or stopped for one a time budget ended early):
    its steps, time and last evaluation (with the env steps of the policy it is of, where
    evaluated inside the chunk; ``pooled`` says over what, for a sweep's members of different
    settings). A run resumed at ``resumed_at`` env steps says what this process did in
    ``process_s`` seconds, then the whole run's time."""
    policy = last.get("eval_policy_env_steps", -1)
    of = (
        f" (policy of {int(policy):,} steps; td3-jax eval for the final one)" if policy >= 0 else ""
    )
    took = f"in {last['wall_time_s']:.0f} s"
    if resumed_at is not None:
        seconds = last["wall_time_s"] if process_s is None else process_s
        took = (f"({last['env_steps'] - resumed_at:,} in this process, in {seconds:.0f} s; "
                f"{last['wall_time_s']:.0f} s over the whole run)")  # fmt: skip
    return (f"{word}: {last['env_steps']:,} env steps {took}; eval return "
            f"{last['eval_return_mean']:.1f} ± {last['eval_return_std']:.1f}{pooled}{of}; "
            f"outputs in {out}")  # fmt: skip


def sweep_main(args: list[str]) -> None:
    train_main(args, sweeping=True)


def output_console() -> Any:
    """A rich console for stdout: a terminal's width, else (a log file, a pipe) as wide as
    the output needs (rich would cut tables to 80 columns)."""
    from rich.console import Console

    console = Console()
    return console if console.is_terminal else Console(width=100_000)


def print_sweep_ranking(record: dict) -> None:
    """Final returns per swept setting (mean over its seeds), best first, with 95% CIs.

    Diverged members (null returns) are left out of their setting's statistics and counted in
    the ``diverged`` column; a setting whose every seed diverged ranks last.
    """
    import numpy as np
    from rich.table import Table

    from td3_jax.core import stats

    groups: dict[tuple, list[float | None]] = {}
    for member in record["per_member"]:
        setting = tuple(sorted(member.get("settings", {}).items()))
        groups.setdefault(setting, []).append(member["eval_return_mean"])
    rows = []
    for setting, returns in groups.items():
        finite = np.asarray([r for r in returns if r is not None], np.float64)
        summary = stats.summary(finite) if finite.size else None
        rows.append((setting, len(returns), len(returns) - finite.size, summary))
    rows.sort(key=lambda row: -np.inf if row[3] is None else row[3]["mean"], reverse=True)
    labels = [" ".join(f"{k}={v:g}" for k, v in row[0]) for row in rows]
    title = f"final evaluation return after {record['env_steps']} env steps"
    table = Table(title=title, min_width=len(title))
    for column in ("rank", "setting", "seeds", "diverged", "mean", "95% CI", "IQM"):
        width = max(map(len, labels)) if column == "setting" else None
        table.add_column(column, justify="right", min_width=width, no_wrap=column == "setting")
    for rank, (label, (_, n, diverged, summary)) in enumerate(zip(labels, rows, strict=True), 1):
        cells = ["-", "-", "-"]
        if summary is not None:
            interval = f"[{summary['ci95_low']:.1f}, {summary['ci95_high']:.1f}]"
            cells = [f"{summary['mean']:.1f}", interval, f"{summary['iqm']:.1f}"]
        table.add_row(str(rank), label, str(n), str(diverged), *cells)
    output_console().print(table)


def eval_main(args: list[str]) -> None:
    from td3_jax.core.stats import population_stats
    from td3_jax.runner.finished import evaluate_run

    command = _parse(EvalCommand, args, "td3-jax eval")
    if command.episodes <= 0:
        raise ConfigError(f"--episodes must be positive, got {command.episodes}")
    check_seed(command.seed)
    cfg, population, meta, returns = evaluate_run(command.run, command.episodes, command.seed)
    title = (
        f"{cfg.algo} on {cfg.env} after {meta['env_steps']} env steps, "
        f"{command.episodes} episodes each"
    )
    diverged = set(meta.get("diverged_members", []))
    rows = [((m.label() or f"seed={m.seed}") + (" (diverged)" if i in diverged else ""),
             None if i in diverged else returns[i])
            for i, m in enumerate(population)]  # fmt: skip
    alive = [i for i in range(len(population)) if i not in diverged]
    swept = any(member.overrides for member in population)
    pooled = population_stats(returns[alive]) if len(alive) > 1 and not swept else None
    print_returns_table(title, rows, pooled)
    if swept:  # statistics per setting over its seeds, never pooled over settings
        print_sweep_ranking(sweep_record(population, returns, diverged, meta["env_steps"]))


def sweep_record(population: list, returns: Any, diverged: set[int], env_steps: int) -> dict:
    """The shape :func:`print_sweep_ranking` reads (``per_member``: each member's settings
    and mean return, ``None`` where it diverged) from ``returns [members, episodes]``."""
    per_member = [{"settings": dict(member.overrides),
                   "eval_return_mean": None if i in diverged else float(returns[i].mean())}
                  for i, member in enumerate(population)]  # fmt: skip
    return {"env_steps": env_steps, "per_member": per_member}


def print_returns_table(title: str, rows: list, aggregate: dict | None) -> None:
    """Per-member mean/std/min/max of episode returns (``-`` for a member whose returns are
    ``None``: diverged in training, as the sweep table shows it), then the statistics over the
    other members."""
    import numpy as np
    from rich.table import Table

    table = Table(title=title, min_width=len(title))  # the title on one line
    for column in ("member", "mean", "std", "min", "max"):
        table.add_column(column, justify="right")
    for label, returns in rows:
        r = None if returns is None else np.asarray(returns)
        values = ["-"] * 4 if r is None else [f"{v:.1f}" for v in (r.mean(), r.std(), r.min(),
                                                                    r.max())]  # fmt: skip
        table.add_row(label, *values)
    console = output_console()
    console.print(table)
    if aggregate:
        alive = sum(returns is not None for _, returns in rows)
        console.print(
            f"over {alive} members: mean {aggregate['eval_return_mean']:.1f} "
            f"[95% CI {aggregate['eval_return_ci95_low']:.1f}, "
            f"{aggregate['eval_return_ci95_high']:.1f}], median "
            f"{aggregate['eval_return_median']:.1f}, IQM {aggregate['eval_return_iqm']:.1f}"
        )


def export_main(args: list[str]) -> None:
    from td3_jax.tools.export import export_run, summary

    command = _parse(ExportCommand, args, "td3-jax export")
    path, policy = export_run(command.run, command.format, command.out, command.member)
    print(path)
    print(summary(policy, _member_label(command.run, policy.member)))


def _member_label(run_dir: Path, member: int) -> str:
    """Member ``member``'s seed and swept values (``actor_lr=0.001 seed=1``) in a run of
    several members; empty for a run of one."""
    from td3_jax.runner import rundir

    population = rundir.load_members(run_dir, rundir.load_config(run_dir))
    return population[member].label() if len(population) > 1 else ""


def render_main(args: list[str]) -> None:
    from td3_jax.tools import render

    command = _parse(RenderCommand, args, "td3-jax render")
    check_seed(command.seed)
    out = render.video_path(command.run, command.out, command.gif)
    rendered = render.render_run(
        command.run, out, episodes=command.episodes, seed=command.seed, member=command.member,
        camera=command.camera, width=command.width, height=command.height, fps=command.fps,
    )  # fmt: skip
    print(rendered.path)
    for e, (frames, ret) in enumerate(zip(rendered.lengths, rendered.returns, strict=True)):
        print(f"member {rendered.member} episode {e + 1}: {frames} frames, return {ret:.2f}")
    if rendered.env_steps is not None:
        print(f"(the policy of the checkpoint at {rendered.env_steps} env steps)")


def plot_main(args: list[str]) -> None:
    from td3_jax.runner.curves import (
        draw_curve,
        mixed_envs_warning,
        no_return_warning,
        plot_comparison,
        run_labels,
    )

    command = _parse(PlotCommand, args, "td3-jax plot")
    out = _plot_path(command.run, command.out)
    curves = [_curve_to_plot(run) for run in command.run]
    warnings = [mixed_envs_warning(curves)]
    warnings += [
        no_return_warning(curve, run) for curve, run in zip(curves, command.run, strict=True)
    ]
    for warning in filter(None, warnings):
        print(f"td3-jax: warning: {warning}", file=sys.stderr, flush=True)
    if len(curves) == 1:
        print(draw_curve(curves[0], out))
    else:
        print(plot_comparison(curves, run_labels(command.run), out))


def _plot_path(runs: tuple[Path, ...], out: Path | None) -> Path:
    """Where ``td3-jax plot`` writes its image: ``out``, checked (a known suffix, an existing
    folder, no run given twice; an existing file only where td3-jax drew it, or a run's own
    curve.png), else the one run's curve.png."""
    from td3_jax.runner.curves import IMAGE_SUFFIXES, is_td3_jax_figure
    from td3_jax.runner.rundir import CONFIG_FILE

    if not runs:
        raise ConfigError("td3-jax plot: give a run directory: --run DIR [DIR ...]")
    resolved = [Path(run).resolve() for run in runs]
    again = next((j for j, path in enumerate(resolved) if path in resolved[:j]), None)
    if again is not None:
        first = runs[resolved.index(resolved[again])]
        if str(first) == str(runs[again]):
            raise ConfigError(f"--run {first} is given twice")
        raise ConfigError(f"--run {first} and {runs[again]} are the same run")
    if out is None:
        if len(runs) > 1:
            raise ConfigError(f"comparing {len(runs)} runs needs --out FILE (.png, .pdf or .svg)")
        return Path(runs[0]) / "curve.png"
    if out.suffix.lower() not in IMAGE_SUFFIXES:
        raise ConfigError(f"--out {out}: the image's format comes from its suffix, one of "
                          f"{', '.join(IMAGE_SUFFIXES)}, not {out.suffix or 'none'}")  # fmt: skip
    if out.is_dir() or not out.parent.is_dir():
        what = "is a directory" if out.is_dir() else f"is in {out.parent}, which is no directory"
        raise ConfigError(f"--out {out} {what}; give an image file in an existing folder")
    own = out.name == "curve.png" and (out.parent / CONFIG_FILE).is_file()  # (a run's own)
    if out.exists() and not own and not is_td3_jax_figure(out):
        raise ConfigError(f"--out {out} exists and is not a figure td3-jax plot drew (or one "
                          "from an older td3-jax, which did not mark its figures): remove it or "
                          "choose another name")  # fmt: skip
    return out


def _curve_to_plot(run: Path) -> Curve:
    """The curve of ``run``, or a one-line reason why it has none: not a run directory, a run
    stopped before its first evaluation, or one training before it."""
    from td3_jax.runner.curves import read_curve
    from td3_jax.runner.rundir import holder_for_reader, load_config, require_run_dir

    require_run_dir(run)
    curve = read_curve(run)
    if curve is not None:
        return curve
    load_config(run)  # (not a run directory, or one still starting: it says)
    holder = holder_for_reader(run)
    if holder is None:
        raise ConfigError(f"{run} has no evaluation to plot (none in its metrics.jsonl): its "
                          "run stopped before its first evaluation, or the file was "
                          "removed")  # fmt: skip
    raise ConfigError(f"{run} has no evaluation yet: a td3-jax run ({holder}) is training it; "
                      "plot again after its first evaluation")  # fmt: skip


def envs_main(args: list[str]) -> None:
    """One line per environment: its name, the td3-jax extra it needs, whether it runs here
    (else what it still needs); then which physics Playground's tasks get here, and how to
    train an environment of your own."""
    from td3_jax import envs
    from td3_jax.envs import physics
    from td3_jax.envs.custom import KINDS

    command = _parse(EnvsCommand, args, "td3-jax envs")
    if command.menagerie is not None and not command.menagerie.expanduser().is_dir():
        raise ConfigError(f"--menagerie {command.menagerie} is not a directory")
    for line in envs_table(envs.catalog(command.menagerie)):
        print(line)
    missing = physics.warp_missing()
    engine = f"MJX's JAX implementation; {missing}" if missing else "MuJoCo Warp"
    print(f"\nPlayground physics here by default: {engine}. --impl jax|warp chooses.")
    print(f"Your own environment: --env module.path:function, a function returning "
          f"{KINDS} (README: Your own environment).")  # fmt: skip


def envs_table(rows: list[tuple[str, str, str]]) -> list[str]:
    """The lines of ``td3-jax envs``' table of ``(name, extra, what it still needs)`` rows:
    a header, then each environment, its extra (``-``: none) and ``yes`` where it runs here,
    else ``no:`` and what it needs."""
    cells = [("environment", "extra", "runs here")]
    cells += [(name, extra or "-", f"no: {need}" if need else "yes") for name, extra, need in rows]
    name_width = max(len(c[0]) for c in cells)
    extra_width = max(len(c[1]) for c in cells)
    return [f"{n:<{name_width}}  {e:<{extra_width}}  {h}" for n, e, h in cells]


def presets_main(args: list[str]) -> None:
    """One line per preset (the named ones, else all): its name and the flags it sets; an
    unknown name is :func:`~td3_jax.config.presets.preset`'s ConfigError (the closest names)."""
    names = _parse(PresetsCommand, args, "td3-jax presets").names or tuple(PRESETS)
    for name in names:
        preset(name)  # (refuses an unknown name before anything is printed)
    for name in names:
        settings = " ".join(as_flag(k, v) for k, v in PRESETS[name].items())
        print(f"{name}: {settings}")


COMMANDS = {
    "train": train_main,
    "sweep": sweep_main,
    "eval": eval_main,
    "export": export_main,
    "render": render_main,
    "plot": plot_main,
    "envs": envs_main,
    "presets": presets_main,
}


def main(argv: list[str] | None = None) -> None:
    """Entry point of the ``td3-jax`` console script."""
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
        from td3_jax import __version__

        print(f"td3-jax {__version__}")
        return
    command = COMMANDS.get(argv[0])
    if command is None:
        from td3_jax.common.errors import did_you_mean

        hint = did_you_mean(argv[0], list(COMMANDS))
        names = ", ".join(COMMANDS)
        print(f"td3-jax: error: unknown subcommand {argv[0]!r}{hint}\n(subcommands: {names}; "
              "td3-jax --help says what each does)", file=sys.stderr)  # fmt: skip
        sys.exit(2)
    _run_reporting_errors(command, argv[1:])


#: The flags whose value is a run's folder or an output file: given empty, each would mean
#: the working directory. (An empty --compile-cache means off and an empty --menagerie not
#: given, as before.)
_PATH_FLAGS = ("--out", "--run")


def check_no_empty_path(args: list[str]) -> None:
    """``ConfigError`` for ``--out`` or ``--run`` given an empty or blank value (``--out ''``,
    ``--out=``: often ``--out "$DIR"`` with DIR unset), which would otherwise mean the working
    directory (or a path named by spaces)."""
    for token, after in itertools.pairwise([*args, None]):
        flag, equals, value = token.partition("=")
        given = value if equals else after
        if flag in _PATH_FLAGS and given is not None and not given.strip():
            raise ConfigError(f"{flag} is {'blank' if given else 'empty'} (an unset shell "
                              "variable?); give the path, or ./ for the working "
                              "directory")  # fmt: skip


def expand_home(args: list[str]) -> list[str]:
    """``args`` with a leading ``~`` of an ``--out`` or ``--run`` value (each of ``--run``'s
    values) expanded to the home folder, as the shell does for ``--out ~/x`` but not for
    ``--out=~/x``, a quoted ``'~/x'`` or a Python caller's list (which made a folder named
    ``~`` in the working directory, and said ``~/x``)."""
    expanded, flag = [], None  # (the path flag whose values follow)
    for token in args:
        name, equals, value = token.partition("=")
        if token.startswith("-"):
            flag = name if name in _PATH_FLAGS and not equals else None
            if equals and name in _PATH_FLAGS and value.startswith("~"):
                token = f"{name}={os.path.expanduser(value)}"
        elif flag is not None and token.startswith("~"):
            token = os.path.expanduser(token)
        expanded.append(token)
    return expanded


#: The flags that take a list of values (besides ``--sweep-*``), whose repetition might be
#: read as adding to the list.
_LIST_FLAGS = ("--hidden-sizes", "--actor-hidden-sizes", "--critic-hidden-sizes", "--run")


def repeated_flags_warning(args: list[str]) -> str | None:
    """A warning naming the list flags (``--sweep-*``, :data:`_LIST_FLAGS`) given more than
    once in ``args``: only the last list counts, so ``--sweep-actor-lr 1e-4 --sweep-actor-lr
    1e-3 3e-4`` drops 1e-4. ``None``: none. (A repeated one-value flag is an override, as
    a script's defaults followed by ``--seed 3`` give, and is not warned about.)"""
    flags = [arg.split("=", 1)[0] for arg in args if arg.startswith("--")]
    lists = [f for f in flags if f.startswith("--sweep-") or f in _LIST_FLAGS]
    repeated = [flag for flag in dict.fromkeys(lists) if lists.count(flag) > 1]
    if not repeated:
        return None
    return (f"{', '.join(repeated)} given more than once: only the last list of each counts "
            "(the lists are not added together)")  # fmt: skip


def _exit_interrupted(message: str, code: int = 130) -> None:
    """Prints ``message`` and exits with ``code`` at once: an XLA compile still running on a
    background thread, or a chunk or evaluation a Ctrl-C left running on the device (neither can
    be interrupted), is abandoned rather than waited for (the run's outputs are closed by then).
    Waiting took the rest of the chunk, and tearing down XLA under it could end in SIGSEGV."""
    print(message, file=sys.stderr)
    if runtime.background_work_running():
        sys.stdout.flush()
        sys.stderr.flush()
        runtime.forget_abandoned_work()  # (for a caller whose os._exit returns: tests)
        os._exit(code)
    sys.exit(code)


def _run_reporting_errors(command, args: list[str]) -> None:
    """Runs a subcommand; a known failure becomes one message and its exit code
    (:mod:`td3_jax.common.errors`: 2 bad input, 3 a run stopped by what it computed; 130
    interrupted)."""
    from td3_jax.common.errors import Td3JaxError

    runtime.quiet_library_logs()  # orbax's and asyncio's log lines, Brax's notice
    try:
        check_no_empty_path(args)
        if (warning := repeated_flags_warning(args)) is not None:
            print(f"td3-jax: warning: {warning}", file=sys.stderr, flush=True)
        command(expand_home(args))
    except Td3JaxError as err:
        print(f"td3-jax: error: {err}", file=sys.stderr)
        sys.exit(err.exit_code)
    except RuntimeError as err:
        if "MUJOCO_GL" not in str(err):  # mujoco's import refuses an unknown MUJOCO_GL value
            raise
        print(f"td3-jax: error: {err} (unset it or use egl, osmesa or glfw)", file=sys.stderr)
        sys.exit(2)
    except Interrupted as err:
        _exit_interrupted(f"td3-jax: {err}", err.code)
    except OSError as err:  # a full disk, a quota, a read-only file system, no permission
        if err.errno not in WRITE_ERRNOS:
            raise
        where = f"{err.filename}: " if err.filename else ""
        print(f"td3-jax: error: {where}{err.strerror}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        _exit_interrupted("td3-jax: interrupted")
