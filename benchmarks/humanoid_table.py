"""The 50M-step humanoid table: each task's final returns over the seeds run, their IQM, and
FlashSAC's and FastTD3's published finals (:data:`PUBLISHED`); and :func:`run_label`, a run
named by its preset and the flags that differ from it.

Reads runs' ``metrics.jsonl`` files (run directories, or files named ``*metrics.jsonl`` with
their run's config.json beside them as ``*config.json`` where kept); a run counts where it has
a record at ``--steps`` env steps. A seed run twice counts once (the file later in path order).
Pushes and domain randomisation come from the config (unknown without one).

    python -m benchmarks.humanoid_table [--steps 53248000] RUN_DIR_OR_METRICS_FILE...
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path
from typing import Any, NamedTuple

from td3_jax.config.presets import preset
from td3_jax.config.schema import TrainConfig, as_flag
from td3_jax.core.stats import iqm
from td3_jax.runner.program_cache import HOST_ONLY

#: Final returns at 50M env steps (5 seeds): FlashSAC's paper (arXiv 2604.04539), and
#: FastTD3's as FlashSAC reports them.
PUBLISHED = {
    "T1JoystickFlatTerrain": (38.5, 35.0),
    "T1JoystickRoughTerrain": (34.6, 30.6),
    "G1JoystickFlatTerrain": (39.9, 31.5),
    "G1JoystickRoughTerrain": (34.1, 27.9),
}


class Final(NamedTuple):
    """One run's return at the table's env steps."""

    task: str
    seed: int
    settings: str
    value: float
    source: Path


#: Settings that do not change what a run learns: the seed and length, where it runs and
#: how fast (physics implementation, matmul kernels), how it is evaluated and recorded.
#: (The host-only settings, then the rest; pushes and domain randomisation are shown apart.)
NOT_LEARNING = (*HOST_ONLY, "total_steps", "impl", "matmuls", "eval_every", "eval_envs",
                "eval_in_chunk", "pushes", "domain_randomization")  # fmt: skip


#: Settings whose None means "the algorithm's own value", which config.json records instead.
ALGORITHM_DEFAULTS = ("hidden_sizes", "actor_lr", "critic_lr", "tau")


def differences(config: dict[str, Any]) -> list[tuple[str, Any]]:
    """``(setting, value)`` for each setting of a run's config.json that differs from its
    preset's, in TrainConfig's order (settings of :data:`NOT_LEARNING` left out, and those of
    :data:`ALGORITHM_DEFAULTS` that the preset leaves to the algorithm; a setting missing from
    an older config.json is the default it ran with)."""
    base, defaults = preset(config["preset"]), TrainConfig()
    found = []
    for field in dataclasses.fields(TrainConfig):
        want = getattr(base, field.name)
        got = config.get(field.name, getattr(defaults, field.name))
        if want is None and field.name in ALGORITHM_DEFAULTS:
            continue
        if field.name not in NOT_LEARNING and not _same(got, want):
            found.append((field.name, tuple(got) if isinstance(got, list) else got))
    return found


def changes_from_preset(config: dict[str, Any]) -> list[str]:
    """``NAME VALUE`` for each of :func:`differences`; ``["preset unknown"]`` without a
    preset."""
    if config.get("preset") is None:
        return ["preset unknown"]
    return [f"{name} {' '.join(map(str, value)) if isinstance(value, tuple) else value}"
            for name, value in differences(config)]  # fmt: skip


def run_label(config: dict[str, Any]) -> str:
    """A run as ``PRESET FLAGS``: its preset's name and the flags of the settings that differ
    from it (:func:`differences`, then pushes and domain randomisation where they differ), so
    that ``td3-jax train --preset PRESET FLAGS`` trains it again; a ValueError without a
    preset."""
    name = config.get("preset")
    if name is None:
        raise ValueError("the run's config.json names no preset")
    base = preset(name)
    shown = [*differences(config),
             *[(setting, config[setting]) for setting in ("pushes", "domain_randomization")
               if setting in config and config[setting] != getattr(base, setting)]]  # fmt: skip
    return " ".join([name, *(as_flag(setting, value) for setting, value in shown)])


def _same(got: Any, want: Any) -> bool:
    if isinstance(want, tuple) and isinstance(got, list):
        got = tuple(got)
    return got == want


def settings_of(config: dict[str, Any] | None) -> str:
    """``pushes P, DR on|off`` from a run's config.json (``unknown`` without one), then what
    else differs from its preset (:func:`changes_from_preset`)."""
    if config is None:
        return "unknown"
    randomised = "on" if config.get("domain_randomization") else "off"
    return ", ".join([f"pushes {config.get('pushes', '?')}, DR {randomised}",
                      *changes_from_preset(config)])  # fmt: skip


def final_of(metrics: Path, steps: int) -> Final | None:
    """The run's evaluation return at ``steps`` env steps, or ``None`` if it has no record there."""
    records = [json.loads(line) for line in metrics.read_text().splitlines() if line.strip()]
    at = [
        r for r in records if r.get("env_steps") == steps and r.get("eval_return_mean") is not None
    ]
    if not at:
        return None
    config_path = metrics.with_name(metrics.name.replace("metrics.jsonl", "config.json"))
    config = json.loads(config_path.read_text()) if config_path.is_file() else None
    record = at[-1]
    task = str(record["env"]).rpartition("/")[2]
    return Final(task, int(record["seed"]), settings_of(config), float(record["eval_return_mean"]),
                 metrics)  # fmt: skip


def table(finals: list[Final]) -> str:
    """A Markdown table: a row per task and settings, its seeds' finals, their IQM, published."""
    kept: dict[tuple[str, str, int], Final] = {}
    for final in sorted(finals, key=lambda f: str(f.source)):
        kept[(final.task, final.settings, final.seed)] = final  # a later file wins
    rows = ["| task | settings | seeds: final | IQM | FlashSAC | FastTD3 |",
            "| --- | --- | --- | ---: | ---: | ---: |"]  # fmt: skip
    for task, settings in sorted({(t, s) for t, s, _ in kept}):
        runs = sorted((f for f in kept.values() if (f.task, f.settings) == (task, settings)),
                      key=lambda f: f.seed)  # fmt: skip
        seeds = ", ".join(f"{f.seed}: {f.value:.1f}" for f in runs)
        flash, fast = PUBLISHED.get(task, (float("nan"), float("nan")))
        score = iqm([f.value for f in runs])
        count = f"{len(runs)} seed{'s' if len(runs) > 1 else ''}"
        rows.append(f"| {task} | {settings} | {seeds} | {score:.1f} ({count}) "
                    f"| {flash} | {fast} |")  # fmt: skip
    return "\n".join(rows)


def metrics_files(paths: list[Path]) -> list[Path]:
    """The ``metrics.jsonl`` of each run directory in ``paths`` and each file given as is."""
    return [path / "metrics.jsonl" if path.is_dir() else path for path in paths]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path,
                        help="run directories or *metrics.jsonl files")  # fmt: skip
    parser.add_argument("--steps", type=int, default=53_248_000)
    args = parser.parse_args(argv)
    missing = [str(path) for path in metrics_files(args.runs) if not path.is_file()]
    if missing:
        parser.error(f"no metrics.jsonl at {', '.join(missing)}")
    finals = [f for f in (final_of(path, args.steps) for path in metrics_files(args.runs)) if f]
    print(table(finals) if finals else f"no run has a record at {args.steps:,} env steps")


if __name__ == "__main__":
    main()
