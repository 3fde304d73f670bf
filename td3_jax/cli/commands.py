"""The flags of each subcommand, as the frozen dataclasses that tyro reads: a field per flag,
its docstring the flag's ``--help`` text. ``train`` and ``sweep`` take every
:class:`~td3_jax.config.schema.TrainConfig` setting as a flag, plus their own."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Annotated, Any, Literal

import tyro

from td3_jax.config.presets import NAMES, PRESETS
from td3_jax.config.schema import TrainConfig

__all__ = [
    "EnvsCommand",
    "EvalCommand",
    "ExportCommand",
    "PlotCommand",
    "PresetFlag",
    "PresetName",
    "PresetsCommand",
    "RenderCommand",
    "SweepCommand",
    "SweptValues",
    "TrainCommand",
    "Widths",
    "default_in_help",
]

PresetName = Literal[tuple(PRESETS)]  # type: ignore[valid-type]
#: A preset flag: every name, former ones included (they still run); the help lists current ones.
PresetFlag = Annotated[
    PresetName | None,  # type: ignore[valid-type]
    tyro.conf.arg(metavar="{" + ",".join(NAMES) + "}", help_behavior_hint=""),
]
#: Hidden widths as the command line takes them (no ``None``: the default is shown instead).
Widths = Annotated[tuple[int, ...] | None, tyro.conf.arg(metavar="INT [INT ...]")]


def default_in_help(metavar: str) -> Any:
    """A flag whose help says its default in words: no "(default: None)" from tyro, and
    ``metavar`` instead of ``{None}|PATH``."""
    return tyro.conf.arg(metavar=metavar, help_behavior_hint="")


#: The values a sweep tries for one setting (none: the setting is not swept).
SweptValues = Annotated[
    tuple[float, ...], tyro.conf.arg(metavar="VALUES", help_behavior_hint="(default: not swept)")
]


@dataclasses.dataclass(frozen=True)
class TrainCommand(TrainConfig):
    """Train TD3 or DDPG. Flags not given take the preset's value, else the default shown.

    Most runs need only --preset NAME (or --env SOURCE/NAME) and --out DIR, with --total-steps N
    to change the run's length. --resume continues the run in --out, --seeds K trains K seeds
    in one program, --devices D splits the run over D GPUs. The training settings come first
    below; the command's own flags (--out, --resume, --preset, --quiet, --time-budget-s,
    --devices, ...) come last.
    """

    hidden_sizes: Widths = (256, 256)  # (None, for a library caller: the algorithm's own)
    """Hidden widths of actor and critics (the TD3 paper used 400 300)."""
    out: Annotated[Path | None, default_in_help("PATH")] = None
    """Run directory: config.json, metrics.jsonl, tensorboard/, curve.png, checkpoints/
    (default: a new folder runs/NAME-DATE-TIME, NAME the --preset or --env; --resume needs
    --out)."""
    resume: bool = False
    """Continue the run in --out exactly where its newest good checkpoint left it. Only
    --total-steps (to extend or shorten the run; not with --lr-schedule cosine), --matmuls,
    --keep-checkpoints, --checkpoint-every, --eval-envs, --early-evaluation, --menagerie and
    the --wandb* flags may differ from the run's config.json; other flags must match. The
    command's own flags (--quiet, --time-budget-s, --compile-cache, --devices and the
    several-hosts flags) apply to this process. A run logged to W&B continues its W&B run."""
    preset: PresetFlag = None
    """Named settings to start from (see `td3-jax presets`); flags given override them, --env
    included (a preset such as ant sets its --env: brax/ant). Default: the --env's own preset
    where one exists (said in one line), else settings for the device (a GPU gets thousands of
    environments)."""
    quiet: bool = False
    """No progress display: none of the lines that each evaluation prints (nor, on a terminal,
    the live bar below them); the notes on the settings, the warnings and the last line still
    print."""
    time_budget_s: float | None = None
    """Stop after the first chunk that ends past this wall-clock budget (compile included),
    counted over the whole run: a resume's budget includes the time of the calls before it.
    Checkpointed, exit status 0, and a last line naming the --resume that continues it."""
    devices: int | None = None
    """Data-parallel over this many devices (default: all; one GPU for MuJoCo Warp physics);
    num_envs and batch stay global."""
    local_processes: int | None = None
    """Run as N processes of this host, one per GPU, joined through jax.distributed on a free
    local port (instead of --devices N in one process: faster for MuJoCo Warp, whose host-side
    calls a process's GPUs make in turn); num_envs and batch stay global."""
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
    over seeds (from 3 seeds or fewer, their range). Settings not swept take their single
    value (preset, flag or default).
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
    """Seed of the evaluation environments: new episodes, not those of the run's own
    evaluations, so the mean may differ from its last record."""
    json: Annotated[Path | None, default_in_help("PATH")] = None
    """Also write what the tables show to this JSON file, outside the run's folder: each
    member's episode returns with their mean, std, min and max, the statistics over members
    (none for one; a sweep's per setting, best first), the checkpoint's env steps and the
    evaluation's seed. A file there already is replaced only where td3-jax eval wrote it
    (default: no file)."""


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
