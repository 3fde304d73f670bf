"""What the command line says around a run, besides its progress: which settings it got and
from where, warnings about settings that work but likely surprise (a GPU-sized run on a CPU,
no learning), notes added to a setting's error, and the lines that end a run."""

from __future__ import annotations

import contextlib
import re
from collections.abc import Iterator
from pathlib import Path

from td3_jax.cli.messages import warn
from td3_jax.cli.run_folder import out_chosen_note
from td3_jax.config.presets import PRESETS, preset
from td3_jax.config.schema import (
    ConfigError,
    TrainConfig,
    as_flag,
    flag_pattern,
    idle_flags,
    rounding_note,
)

__all__ = [
    "CPU_SIZES",
    "chunk_count_warning",
    "cpu_size_warning",
    "cpu_tips",
    "critic_network_note",
    "done_line",
    "eval_size_warning",
    "gpu_sized",
    "large_for_cpu",
    "members_note",
    "no_learning_warning",
    "preset_noted",
    "preset_source_note",
    "unnamed_env_warning",
    "when_prepared",
]


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


def _defaults_note(cfg: TrainConfig, name: str | None, source: str) -> str | None:
    """The line saying which settings a run without --preset got (None when it named one)."""
    if source == "env":
        return f"using preset {name!r} for {cfg.env} (pass --preset or flags to change it)"
    if source != "device":
        return None
    from td3_jax import envs  # lazy: imports JAX

    if cfg.env not in envs.known_names() and not envs.is_custom(cfg.env):
        return None  # (train() reports the unknown name)
    import jax  # lazy: JAX, only for a run

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


#: A run's size on a CPU: evaluations, checkpoints and the whole run in minutes (the
#: ``pendulum`` preset's sizes).
CPU_SIZES = {"num_envs": 16, "total_steps": 20_000, "batch_size": 256, "warmup_steps": 1000,
             "eval_every": 4000, "eval_envs": 16}  # fmt: skip


def gpu_sized(cfg: TrainConfig) -> bool:
    """Whether ``cfg`` is sized for an accelerator: :func:`large_for_cpu`, or evaluation rounds
    inside whole chunks (whose chunk holds an episode of every environment)."""
    return large_for_cpu(cfg) or cfg.eval_in_chunk


def large_for_cpu(cfg: TrainConfig) -> bool:
    """Whether ``cfg`` has thousands of environments, millions of steps or batches of
    thousands."""
    return cfg.num_envs >= 1024 or cfg.run_steps >= 5_000_000 or cfg.batch_size > 4096


def cpu_tips(cfg: TrainConfig) -> list[str]:
    """Every flag that sizes ``cfg`` for a CPU (:data:`CPU_SIZES`), each only where ``cfg``'s
    own value is larger: the environments, the run's steps, the batch, the warm-up, the
    in-chunk evaluation, the evaluation period and its episodes; and float32 matmuls for
    bfloat16 ones, which a CPU computes at about half their speed (measured: a 1024-512-256
    critic's gradient, batch 256). Together they make a valid run of the steps it keeps (a
    batch and a warm-up within them) that ends at --total-steps."""
    long = cfg.run_steps >= 5_000_000
    steps = CPU_SIZES["total_steps"] if long else cfg.total_steps  # (the run's, after the tips)
    batch = min(CPU_SIZES["batch_size"], steps)
    warmup = min(CPU_SIZES["warmup_steps"], steps // 2)
    tips = (
        (f"--num-envs {CPU_SIZES['num_envs']}", cfg.num_envs > 64),
        (f"--total-steps {steps}", steps != cfg.total_steps),
        (f"--batch-size {batch}", cfg.batch_size > 4096 or cfg.batch_size > steps),
        (f"--warmup-steps {warmup}", cfg.warmup_steps > 10_000 or cfg.warmup_steps >= steps),
        ("--no-eval-in-chunk", cfg.eval_in_chunk),
        (f"--eval-every {CPU_SIZES['eval_every']}", cfg.eval_every > 20_000),
        (f"--eval-envs {CPU_SIZES['eval_envs']}", cfg.eval_envs > 64),
        ("--precision float32", cfg.precision == "bfloat16"),
    )
    return [tip for tip, larger in tips if larger]


def cpu_size_warning(cfg: TrainConfig, backend: str, source: str = "preset") -> str | None:
    """A warning when a run sized for an accelerator (:func:`gpu_sized`) is about to start on
    a CPU, with every flag that sizes it for one (:func:`cpu_tips`). ``source`` is where the
    settings came from (:func:`~td3_jax.cli.settings.base_config`): only a ``--preset`` given
    can be left out."""
    if backend != "cpu" or not gpu_sized(cfg):
        return None
    steps, large = cfg.run_steps, large_for_cpu(cfg)  # (steps: whole chunks of an in-chunk eval)
    if source == "resume":  # (its sizes cannot change: a small one just runs)
        return None if not large else (
            f"this run is sized for a GPU ({cfg.num_envs} environments, {steps} steps, batch "
            f"{cfg.batch_size}) and JAX found only a CPU: it will train for hours; a resume "
            "keeps its sizes, so resume it where a GPU is")  # fmt: skip
    tips = cpu_tips(cfg)
    alternative = " (or no --preset)" if source == "preset" else ""
    if not large:  # (a small run with a GPU preset's in-chunk evaluation)
        return (f"this run evaluates inside each chunk, as the humanoid presets do: its "
                f"{cfg.eval_envs} evaluation environments step beside its {cfg.num_envs} "
                f"training ones at every iteration, and JAX found only a CPU. For a CPU try "
                f"{' '.join(tips)}{alternative}")  # fmt: skip
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


#: More chunks than this in one run draws :func:`chunk_count_warning`.
MANY_CHUNKS = 1000


def chunk_count_warning(cfg: TrainConfig) -> str | None:
    """A warning when ``--eval-every`` cuts the run into more than :data:`MANY_CHUNKS` chunks:
    each ends in an evaluation and, every ``--checkpoint-every`` chunks, a checkpoint of the
    whole train state, which then take most of the run's time."""
    if cfg.num_chunks <= MANY_CHUNKS:
        return None
    hundredth = -(-cfg.total_steps // 100)
    return (
        f"--eval-every {cfg.steps_per_chunk} cuts the run into {cfg.num_chunks} chunks, each "
        f"ending in an evaluation (and a checkpoint every --checkpoint-every "
        f"{cfg.checkpoint_every}), which take most of its time; --eval-every {hundredth} "
        "gives about 100"
    )


def _announce(cfg: TrainConfig, preset_name: str | None, source: str,
              asked_eval_every: int | None = None, rounding: bool = True) -> None:  # fmt: skip
    """Prints which settings the run got, before it starts (``rounding``: also how
    ``--total-steps`` and ``--eval-every`` round to whole chunks and iterations)."""
    rounded = rounding_note(cfg, asked_eval_every) if rounding else None
    for line in (_defaults_note(cfg, preset_name, source), rounded):
        if line:
            print(line, flush=True)


def no_learning_warning(cfg: TrainConfig) -> str | None:
    """A warning for ``--updates-per-iter 0``: the run collects and evaluates but never
    learns (a collection-only run, as a throughput benchmark wants, is the one use)."""
    if cfg.updates_per_iter:
        return None
    return ("--updates-per-iter 0: no gradient updates, so the policy never learns (it "
            "evaluates its initial networks throughout)")  # fmt: skip


def when_prepared(cfg: TrainConfig, preset_name: str | None, source: str,
                  asked_eval_every: int | None = None, given: frozenset[str] = frozenset(),
                  resumed: bool = False, chosen_out: Path | None = None) -> None:  # fmt: skip
    """Once the run's settings, directory and environment are good (a run they stop says
    nothing else): where the run goes when no ``--out`` named it (``chosen_out``), which
    settings it got, and warnings (a GPU-sized run on a CPU, an evaluation that dwarfs the
    training, no updates). A resume says how its steps round only where ``--total-steps`` was
    typed (its fresh start said so already)."""
    import jax  # lazy: JAX, only for a run

    if jax.process_index() != 0:
        return
    if chosen_out is not None:
        print(out_chosen_note(chosen_out), flush=True)
    rounding = not resumed or "total_steps" in given
    _announce(cfg, preset_name, source, asked_eval_every, rounding)
    warnings = (unnamed_env_warning(cfg, preset_name, source, given),
                cpu_size_warning(cfg, jax.default_backend(), source),
                critic_network_note(cfg, preset_name, set(given)), eval_size_warning(cfg),
                chunk_count_warning(cfg), no_learning_warning(cfg),
                *idle_flags(cfg, set(given)))  # fmt: skip
    for warning in warnings:
        if warning:
            warn(warning)


def members_note(last: dict, sweeping: bool = False) -> str:
    """What the ± of the done line of a run of several members is over (the spread of their
    mean returns): `` over 4 seeds``, a sweep's `` over all 4 members (per setting below)``,
    and, where some diverged, that only the others count and how many did not (``last``: the
    run's last record, its ``members`` and ``diverged_members``); for a run of one member
    (a sweep of one setting too, which has no table per setting), `` over its evaluation
    episodes``."""
    count = last["members"]
    if count == 1:
        return " over its evaluation episodes"
    unit = "member" if sweeping else "seed"
    diverged = len(last.get("diverged_members") or [])
    below = "per setting below" if sweeping else ""
    if not diverged:
        over = f" over all {count} {unit}s" if count > 1 else f" over its 1 {unit}"
        return f"{over} ({below})" if below else over
    alive = count - diverged
    them = f"{alive} {unit}s that" if alive > 1 else f"1 {unit} that"
    counted = f"{diverged} of {count} diverged" + (f"; {below}" if below else "")
    return f" over the {them} did not diverge ({counted})"


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
