"""The subcommands on a run already trained: ``eval`` (its newest checkpoint's returns),
``export`` (its policy as one file), ``render`` (a video) and ``plot`` (its curve, or several
runs compared)."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

from td3_jax.cli.commands import EvalCommand, ExportCommand, PlotCommand, RenderCommand
from td3_jax.cli.messages import warn
from td3_jax.cli.parsing import parse
from td3_jax.cli.tables import (
    print_returns_table,
    print_sweep_ranking,
    ranked_settings,
    sweep_record,
)
from td3_jax.common.library_noise import filtered_stderr
from td3_jax.config.schema import ConfigError, check_seed
from td3_jax.runner.curves import (
    IMAGE_SUFFIXES,
    Curve,
    draw_curve,
    is_td3_jax_figure,
    mixed_envs_warning,
    no_return_warning,
    plot_comparison,
    read_curve,
    run_labels,
)

__all__ = ["check_mujoco_gl", "eval_main", "evaluation_json", "export_main", "plot_main",
           "render_main"]


def eval_main(args: list[str]) -> None:
    """``td3-jax eval ARGS``: the returns of the run's newest checkpoint per member, then the
    statistics over members (per setting for a sweep, never pooled over settings)."""
    from td3_jax.core.stats import population_stats  # lazy: NumPy, only for this subcommand
    from td3_jax.runner.finished import evaluate_run  # lazy: imports JAX

    command = parse(EvalCommand, args, "td3-jax eval")
    if command.episodes <= 0:
        raise ConfigError(f"--episodes must be positive, got {command.episodes}")
    check_seed(command.seed)
    if command.json is not None:
        _check_writable(command.json, command.run)  # (before the evaluation, not after it)
    with filtered_stderr():  # (XLA's slow-compile alarm: a robot's evaluation on a CPU)
        cfg, population, meta, returns = evaluate_run(command.run, command.episodes, command.seed)
    episodes = f"{command.episodes} episode" + ("s" if command.episodes != 1 else "")
    title = (
        f"{cfg.algo} on {cfg.env} after {meta['env_steps']} env steps, {episodes} each, "
        f"evaluation seed {command.seed} (not the episodes of the run's own evaluations)"
    )
    diverged = set(meta.get("diverged_members", []))
    labelled = [(m.label() or f"seed={m.seed}", None if i in diverged else returns[i])
                for i, m in enumerate(population)]  # fmt: skip
    rows = [(label + (" (diverged)" if r is None else ""), r) for label, r in labelled]
    alive = [i for i in range(len(population)) if i not in diverged]
    swept = any(member.overrides for member in population)
    pooled = population_stats(returns[alive]) if len(alive) > 1 and not swept else None
    print_returns_table(title, rows, pooled)
    ranking = sweep_record(population, returns, diverged, meta["env_steps"])
    if swept:  # statistics per setting over its seeds, never pooled over settings
        print_sweep_ranking(ranking)
    if command.json is not None:
        from td3_jax.runner.logger import write_atomically  # lazy: imports JAX

        written = evaluation_json(command, cfg, meta["env_steps"], labelled, pooled,
                                  ranking if swept else None)  # fmt: skip
        write_atomically(command.json, json.dumps(written, indent=2) + "\n")


def _check_writable(path: Path, run: Path) -> None:
    """A ConfigError naming ``--json PATH`` where it lies in the run's own folder (whose files
    it would replace), is not a plain file, or cannot be written (its folder, where the file
    is written first and renamed)."""
    from td3_jax.runner.logger import probe_write  # lazy: imports JAX

    target = path.resolve()
    if target.is_relative_to(run.resolve()):
        raise ConfigError(f"--json {path} is inside the run's folder {run}: write it elsewhere")
    if target.exists() and not target.is_file():
        raise ConfigError(f"--json {path} is not a plain file: give a file's path")
    if target.exists() and not _written_by_eval(target):
        raise ConfigError(f"--json {path} exists and is not an evaluation td3-jax eval wrote: "
                          "remove it or choose another name")  # fmt: skip
    try:
        probe_write(path)
        probe_write(path.with_name(path.name + ".tmp"))
    except OSError as err:
        raise ConfigError(f"--json {path}: cannot write it ({err.strerror or err})") from None


def evaluation_json(command: EvalCommand, cfg: Any, env_steps: int, members: list,
                    pooled: dict | None, ranking: dict | None) -> dict[str, Any]:  # fmt: skip
    """What ``td3-jax eval --json`` writes: the evaluation's settings; each member's returns
    (``members``: ``(label, returns [episodes] or None where it diverged)``) and statistics;
    the ``pooled`` statistics over members (None for one member or a sweep) and, for a sweep,
    the ``ranking`` per setting, best first, its interval named (``interval``: "95% CI", or
    "range" where it is the [min, max] of 3 or fewer, None for one seed); every statistic
    named as in metrics.jsonl (``eval_return_*``), numbers that are not finite as null."""
    from td3_jax.core.stats import interval_name, return_stats  # lazy: NumPy, only for this

    rows = [{"member": i, "label": label, "diverged": returns is None,
             "returns": None if returns is None else [float(r) for r in returns],
             **({} if returns is None else return_stats(returns))}
            for i, (label, returns) in enumerate(members)]  # fmt: skip
    settings = None
    if ranking is not None:
        settings = [{"settings": dict(setting), "seeds": seeds, "diverged": diverged,
                     "interval": interval_name(seeds - diverged) if seeds - diverged > 1
                     else None, **_named_summary(summary, seeds - diverged)}
                    for setting, seeds, diverged, summary in ranked_settings(
                        ranking["per_member"])]  # fmt: skip
    return _finite_or_null({
        "run": str(command.run), "env": cfg.env, "algo": cfg.algo, "env_steps": env_steps,
        "episodes": command.episodes, "seed": command.seed, "members": rows,
        "over_members": pooled, "per_setting": settings})  # fmt: skip


#: The keys of every file :func:`evaluation_json` writes.
_EVALUATION_KEYS = frozenset({"run", "env", "algo", "env_steps", "episodes", "seed", "members",
                              "over_members", "per_setting"})  # fmt: skip


def _written_by_eval(path: Path) -> bool:
    """Whether ``path`` holds what ``td3-jax eval --json`` writes (a JSON object with its
    keys, and any a later version adds), which a later evaluation may replace."""
    try:
        found = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    return isinstance(found, dict) and _EVALUATION_KEYS <= set(found)


def _named_summary(summary: dict | None, finite: int) -> dict[str, Any]:
    """A setting's statistics named ``eval_return_*``; no interval from one finite return."""
    named = {f"eval_return_{k}": v for k, v in (summary or {}).items()}
    if finite <= 1:
        named.update(eval_return_ci95_low=None, eval_return_ci95_high=None)
    return named


def _finite_or_null(value: Any) -> Any:
    """``value`` with every float that is not finite, however deep, as None (JSON's null)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite_or_null(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite_or_null(v) for v in value]
    return value


def export_main(args: list[str]) -> None:
    """``td3-jax export ARGS``: writes the policy file and prints its path and a summary."""
    from td3_jax.tools.export import export_run, summary  # lazy: imports JAX

    command = parse(ExportCommand, args, "td3-jax export")
    path, policy = export_run(command.run, command.format, command.out, command.member)
    print(path)
    print(summary(policy, _member_label(command.run, policy.member)))


def _member_label(run_dir: Path, member: int) -> str:
    """Member ``member``'s seed and swept values (``actor_lr=0.001 seed=1``) in a run of
    several members; empty for a run of one."""
    from td3_jax.runner import rundir  # lazy: imports JAX

    population = rundir.load_members(run_dir, rundir.load_config(run_dir))
    return population[member].label() if len(population) > 1 else ""


def render_main(args: list[str]) -> None:
    """``td3-jax render ARGS``: writes the video and prints its path and each episode's
    frames and return."""
    from td3_jax.tools import render  # lazy: imports JAX

    command = parse(RenderCommand, args, "td3-jax render")
    check_seed(command.seed)
    check_mujoco_gl(os.environ.get("MUJOCO_GL", ""), render.KNOWN_GL)
    out = render.video_path(command.run, command.out, command.gif)
    with filtered_stderr():  # (XLA's slow-compile alarm: a robot's rollout on a CPU)
        rendered = render.render_run(
            command.run, out, episodes=command.episodes, seed=command.seed,
            member=command.member, camera=command.camera, width=command.width,
            height=command.height, fps=command.fps,
        )  # fmt: skip
    print(rendered.path)
    for e, (frames, ret) in enumerate(zip(rendered.lengths, rendered.returns, strict=True)):
        print(f"member {rendered.member} episode {e + 1}: {frames} frames, return {ret:.2f}")
    if rendered.env_steps is not None:
        print(f"(the policy of the checkpoint at {rendered.env_steps} env steps)")


def check_mujoco_gl(value: str, choices: tuple[str, ...]) -> None:
    """A one-line ConfigError for a ``MUJOCO_GL`` (``value``) that names none of the OpenGL
    backends render draws with (``choices``), before anything imports MuJoCo, whose import
    refuses an unknown one in words of its own; empty: render picks one that works here."""
    given = value.strip()
    if given and given.lower() not in choices:
        raise ConfigError(f"MUJOCO_GL={given} is not one of {', '.join(choices)}, the OpenGL "
                          "backends td3-jax render draws with: set one of them, or unset "
                          "MUJOCO_GL and render picks one that works here")  # fmt: skip


def plot_main(args: list[str]) -> None:
    """``td3-jax plot ARGS``: draws one run's curve, or several runs in one figure, and prints
    where (warnings first: runs of different environments, a run without returns)."""
    command = parse(PlotCommand, args, "td3-jax plot")
    out = _plot_path(command.run, command.out)
    curves = [_curve_to_plot(run) for run in command.run]
    warnings = [mixed_envs_warning(curves)]
    warnings += [
        no_return_warning(curve, run) for curve, run in zip(curves, command.run, strict=True)
    ]
    for warning in filter(None, warnings):
        warn(warning)
    try:
        if len(curves) == 1:
            print(draw_curve(curves[0], out))
        else:
            print(plot_comparison(curves, run_labels(command.run), out))
    except OSError as err:  # (named by the figure: not a temporary file written beside it)
        raise ConfigError(f"cannot write {out}: {err.strerror or err}; --out FILE draws the "
                          "figure elsewhere") from err  # fmt: skip


def _plot_path(runs: tuple[Path, ...], out: Path | None) -> Path:
    """Where ``td3-jax plot`` writes its image: ``out``, checked (a known suffix, an existing
    folder, no run given twice; an existing file only where td3-jax drew it, or a run's own
    curve.png), else the one run's curve.png."""
    if not runs:
        raise ConfigError("td3-jax plot: give a run directory: --run DIR [DIR ...]")
    _check_runs_differ(runs)
    if out is None:
        if len(runs) > 1:
            raise ConfigError(f"comparing {len(runs)} runs needs --out FILE (.png, .pdf or .svg)")
        return Path(runs[0]) / "curve.png"
    _check_figure_path(out)
    return out


def _check_runs_differ(runs: tuple[Path, ...]) -> None:
    """A ConfigError for a run given twice to ``td3-jax plot`` (the same path, or two paths of
    one folder)."""
    resolved = [Path(run).resolve() for run in runs]
    again = next((j for j, path in enumerate(resolved) if path in resolved[:j]), None)
    if again is None:
        return
    first = runs[resolved.index(resolved[again])]
    if str(first) == str(runs[again]):
        raise ConfigError(f"--run {first} is given twice")
    raise ConfigError(f"--run {first} and {runs[again]} are the same run")


def _check_figure_path(out: Path) -> None:
    """A ConfigError where ``td3-jax plot`` may not write ``out``: an unknown image suffix, a
    folder or a file in no folder, an existing file that is neither a figure td3-jax drew nor
    a run's own curve.png."""
    from td3_jax.runner.rundir import CONFIG_FILE  # lazy: imports JAX

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


def _curve_to_plot(run: Path) -> Curve:
    """The curve of ``run``, or a one-line reason why it has none: not a run directory, a run
    stopped before its first evaluation, or one training before it."""
    from td3_jax.runner.rundir import (  # lazy: imports JAX
        holder_for_reader,
        load_config,
        require_run_dir,
    )

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
