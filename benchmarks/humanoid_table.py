"""The 50M-step humanoid table of issue #29: each task's final returns over the seeds run, their
IQM, and FlashSAC's and FastTD3's published finals (``../shared/anchors/README.md``).

Reads the ``metrics.jsonl`` files kept in ``benchmarks/results/`` (each named ``*metrics.jsonl``,
with its run's ``config.json`` beside it as ``*config.json`` where kept); a run counts where it
has a record at ``--steps`` env steps. A seed run twice counts once (the file later in path
order). Pushes and domain randomisation come from the config (unknown without one).

    python benchmarks/humanoid_table.py [--steps 53248000] [FILES...]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any, NamedTuple

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from td3_jax.config.presets import preset
from td3_jax.config.schema import TrainConfig
from td3_jax.core.stats import iqm
from td3_jax.runner.program_cache import HOST_ONLY

#: Final returns at 50M env steps (5 seeds), FlashSAC's paper, and FastTD3's (as FlashSAC
#: reports them); ``../shared/anchors/README.md``.
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


def changes_from_preset(config: dict[str, Any]) -> list[str]:
    """``NAME VALUE`` for each setting of a run's config.json that differs from its preset's
    (settings of :data:`NOT_LEARNING` left out; a setting missing from an older config.json
    is the default it ran with); ``["preset unknown"]`` without a preset."""
    name = config.get("preset")
    if name is None:
        return ["preset unknown"]
    base, defaults = preset(name), TrainConfig()
    changes = []
    for field in dataclasses.fields(TrainConfig):
        want = getattr(base, field.name)
        got = config.get(field.name, getattr(defaults, field.name))
        if field.name in NOT_LEARNING or _same(got, want):
            continue
        shown = " ".join(map(str, got)) if isinstance(got, list | tuple) else f"{got}"
        changes.append(f"{field.name} {shown}")
    return changes


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


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("files", nargs="*", type=Path)
    parser.add_argument("--steps", type=int, default=53_248_000)
    args = parser.parse_args(argv)
    files = args.files or sorted(Path(__file__).parent.glob("results/**/*metrics.jsonl"))
    finals = [f for f in (final_of(path, args.steps) for path in files) if f is not None]
    print(table(finals) if finals else f"no run has a record at {args.steps:,} env steps")


if __name__ == "__main__":
    main()
