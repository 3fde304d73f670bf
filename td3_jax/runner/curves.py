"""Learning curves drawn from ``metrics.jsonl``: a run's ``curve.png``, and several runs
compared in one figure (``td3-jax plot --run A B --out FILE``)."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

from td3_jax.common.errors import ConfigError
from td3_jax.core import stats
from td3_jax.runner.logger import evaluated_steps, read_metrics, setting_label

__all__ = [
    "IMAGE_SUFFIXES",
    "Curve",
    "draw_curve",
    "is_td3_jax_figure",
    "mixed_envs_warning",
    "no_return_warning",
    "plot_comparison",
    "plot_curve",
    "read_curve",
    "run_labels",
    "setting_curves",
    "setting_means",
]

#: The image formats a figure is written in, by the file's suffix.
IMAGE_SUFFIXES = (".png", ".pdf", ".svg")
#: Written into every figure's metadata (PNG's Software, PDF's and SVG's Creator), so that
#: ``td3-jax plot`` replaces its own figures but no other file (:func:`is_td3_jax_figure`).
FIGURE_MARK = "td3-jax plot"


def is_td3_jax_figure(path: Path) -> bool:
    """Whether the regular file ``path`` is a figure td3-jax drew: its metadata field holds
    :data:`FIGURE_MARK` (PNG's Software text chunk near the start, SVG's title near the start,
    PDF's Creator near the end; only those parts are read). An unreadable file raises its
    OSError."""
    path = Path(path)
    if not path.is_file():
        return False
    fields = (b"tEXtSoftware\x00", b"<dc:title>", b"/Creator (")
    marks = [field + FIGURE_MARK.encode() for field in fields]
    with path.open("rb") as image:
        head = image.read(_MARK_SPAN)
        image.seek(max(image.seek(0, os.SEEK_END) - _MARK_SPAN, 0))
        tail = image.read(_MARK_SPAN)
    return any(mark in head or mark in tail for mark in marks)


#: How much of a figure's start and end :func:`is_td3_jax_figure` reads.
_MARK_SPAN = 64 * 1024


class Curve(NamedTuple):
    """One run's evaluation returns, a point per record of its ``metrics.jsonl``.

    ``steps``: the env steps of each evaluated policy
    (:func:`td3_jax.runner.logger.evaluated_steps`); ``wall``: seconds from launch when the record
    was written; ``mean``: the mean return (over episodes for one run, over members for several);
    ``lower``/``upper``: the band drawn around it (mean ± std over episodes, or the 95% bootstrap CI
    over members); ``members``: each member's mean return per point (empty for a run of one member);
    ``swept``: each member's swept values as ``actor_lr=0.001`` (empty strings for seeds alone).
    """

    env: str
    steps: list[int]
    wall: list[float]
    mean: list[float]
    lower: list[float]
    upper: list[float]
    band: str
    members: list[list[float]]
    policy_steps: bool
    swept: tuple[str, ...] = ()


def _number(value: Any) -> float:
    """A record's value as a float for plotting (null, as JSON writes NaN, becomes NaN)."""
    return math.nan if value is None else float(value)


def _swept_text(member: Any) -> str:
    """A per-member record's swept values as ``actor_lr=0.001 tau=0.01`` (a hand-edited value
    that is not a number shown as it is)."""
    settings = member.get("settings") if isinstance(member, dict) else None
    return setting_label(sorted(settings.items()) if isinstance(settings, dict) else [])


def _check_plottable(records: list, path: Path, band_keys: tuple[str, ...]) -> None:
    """A one-line ConfigError for a record of ``path`` that is not an object holding what the
    curve draws (env steps, time, the mean return and ``band_keys``): a hand-edited file."""
    needed = ("env_steps", "wall_time_s", "eval_return_mean", *band_keys)
    for number, record in enumerate(records, start=1):
        missing = [k for k in needed if k not in record] if isinstance(record, dict) else None
        if missing is None or missing:
            what = "is not a JSON object" if missing is None else f"lacks {', '.join(missing)}"
            raise ConfigError(f"record {number} of {path} {what}: was the file edited? (td3-jax "
                              "writes every record with them)")  # fmt: skip


def read_curve(run_dir: Path) -> Curve | None:
    """The curve of the run in ``run_dir``; None where its ``metrics.jsonl`` holds no record
    yet. A record without what the curve draws raises a one-line ConfigError."""
    path = Path(run_dir) / "metrics.jsonl"
    records = read_metrics(path)
    if not records:
        return None
    several = isinstance(records[-1], dict) and "per_member" in records[-1]
    ci = ("eval_return_ci95_low", "eval_return_ci95_high")
    band_keys = ci if several else ("eval_return_std",)
    _check_plottable(records, path, band_keys)
    mean = [_number(r["eval_return_mean"]) for r in records]
    if several:
        lower = [_number(r["eval_return_ci95_low"]) for r in records]
        upper = [_number(r["eval_return_ci95_high"]) for r in records]
        count = len(records[-1]["per_member"])
        members = [[_number(r["per_member"][i]["eval_return_mean"]) for r in records]
                   for i in range(count)]  # fmt: skip
        band = ("mean over members, 95% bootstrap CI" if _interval_name(members) == "95% CI"
                else "mean over members, their range")  # fmt: skip
        swept = tuple(_swept_text(m) for m in records[-1]["per_member"])
    else:
        std = [_number(r["eval_return_std"]) for r in records]
        lower = [m - d for m, d in zip(mean, std, strict=True)]
        upper = [m + d for m, d in zip(mean, std, strict=True)]
        members, band, swept = [], "mean ± std over episodes", ()
    return Curve(
        env=str(records[-1].get("env", "")), steps=[evaluated_steps(r) for r in records],
        wall=[_number(r["wall_time_s"]) for r in records], mean=mean, lower=lower, upper=upper,
        band=band, members=members, policy_steps="eval_policy_env_steps" in records[-1],
        swept=swept,
    )  # fmt: skip


def _draw_members(ax: Any, x: list, curve: Curve, colors: Sequence[Any]) -> None:
    """A run's members as thin lines; a sweep's coloured and named by their swept values (one
    legend entry a setting, its seeds sharing the colour)."""
    settings = list(dict.fromkeys(curve.swept)) if any(curve.swept) else []
    for i, member in enumerate(curve.members):
        if not settings:
            ax.plot(x, member, lw=0.8, alpha=0.45)
            continue
        k = settings.index(curve.swept[i])
        first = curve.swept.index(curve.swept[i]) == i
        ax.plot(x, member, lw=0.9, alpha=0.6, color=colors[k % len(colors)],
                label=curve.swept[i] if first else None)  # fmt: skip


def setting_means(curve: Curve) -> list[tuple[str, list[float]]]:
    """A sweep's mean return per setting at each point: ``(swept values, means)`` in the order
    the settings first appear, each the mean over that setting's members that did not diverge
    (NaN where all did); ``[]`` for a run that is no sweep."""
    import numpy as np

    means = []
    for setting, members in _setting_rows(curve):
        rows = np.array(members, np.float64)
        finite = np.isfinite(rows)
        count = finite.sum(axis=0)
        total = np.where(finite, rows, 0.0).sum(axis=0)
        means.append((setting, np.where(count > 0, total / np.maximum(count, 1), np.nan).tolist()))
    return means


def _setting_rows(curve: Curve) -> list[tuple[str, list[list[float]]]]:
    """A sweep's members grouped by setting, ``(swept values, members' returns)`` in the order
    the settings first appear; ``[]`` for a run that is no sweep."""
    if not any(curve.swept):
        return []
    return [(setting, [m for m, s in zip(curve.members, curve.swept, strict=True) if s == setting])
            for setting in dict.fromkeys(curve.swept)]  # fmt: skip


def _draw(axes: Sequence[Any], curve: Curve, label: str | None, color: Any,
          colors: Sequence[Any] = ()) -> None:  # fmt: skip
    """``curve`` on both axes (env steps, wall-clock): its members thin, its mean with a
    marker, its band shaded; ``label`` names it in a comparison (else the band does). A sweep
    on its own draws each setting's mean (:func:`setting_means`) instead: one mean over
    different settings would pool them."""
    palette = list(colors) or [color]
    sweep = setting_means(curve) if label is None else []
    for ax, x in zip(axes, (curve.steps, curve.wall), strict=True):
        if label is None:  # (a comparison draws only each run's mean and band)
            _draw_members(ax, x, curve, palette)
        for k, (_, mean) in enumerate(sweep):  # (coloured as its members)
            ax.plot(x, mean, marker="o", ms=3, lw=2.0, color=palette[k % len(palette)])
        if sweep:
            continue
        ax.plot(x, curve.mean, marker="o", ms=3, label=label or curve.band,
                color=color if label or not curve.members else "black")  # fmt: skip
        ax.fill_between(x, curve.lower, curve.upper, alpha=0.2 if label else 0.25,
                        color=color if label or not curve.members else "gray")  # fmt: skip


def _save(labelled: Sequence[tuple[Curve, str | None]], path: Path, title: str) -> Path:
    """Draws the curves into a figure of two panels (return against the evaluated policy's env
    steps and against wall-clock) and writes it to ``path`` (its suffix picks the format)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for index, (curve, label) in enumerate(labelled):
        _draw(axes, curve, label, colors[index % len(colors)], colors)
    in_chunk = any(curve.policy_steps for curve, _ in labelled)
    step_label = "environment steps of the evaluated policy" if in_chunk else "environment steps"
    for ax, x_label in zip(axes, (step_label, "wall-clock (s)"), strict=True):
        ax.set_xlabel(x_label)
        ax.grid(alpha=0.3)
    axes[0].legend(loc="best", fontsize=8)  # (where it covers the fewest points)
    axes[0].set_ylabel("evaluation return")
    fig.suptitle(title)
    fig.tight_layout()
    temporary = path.with_name(f"{path.name}.{os.getpid()}.tmp")  # (a failed write: old image)
    try:
        form = path.suffix[1:].lower() or "png"
        mark = {"Software" if form == "png" else "Creator": FIGURE_MARK}
        fig.savefig(temporary, dpi=110, format=form, metadata=mark)
        temporary.replace(path)
    except OSError as err:  # (named by the image, not the temporary file)
        raise OSError(err.errno, err.strerror, str(path)) from err
    finally:
        plt.close(fig)
        temporary.unlink(missing_ok=True)
    return path


def draw_curve(curve: Curve, path: Path) -> Path:
    """Writes one run's ``curve`` to ``path`` (its suffix picks the format): its members thin,
    their mean (or the run's) with its band; a sweep's, each setting's mean instead."""
    return _save([(curve, None)], Path(path), curve.env)


def plot_curve(run_dir: Path, path: Path | None = None) -> Path | None:
    """Writes the run's curve to ``path`` (default ``run_dir/curve.png``): evaluation return
    against the evaluated policy's env steps and against wall-clock; None (nothing written)
    where its ``metrics.jsonl`` holds no record yet."""
    curve = read_curve(run_dir)
    if curve is None:
        return None
    return draw_curve(curve, Path(path or Path(run_dir) / "curve.png"))


def run_labels(run_dirs: Sequence[Path]) -> list[str]:
    """Short distinct names for runs: each directory's name (``.`` and ``..`` by the folder they
    stand for), or its path as given where two runs share a name (``seed0/run`` and
    ``seed1/run``)."""
    names = [Path(os.path.abspath(run)).name or str(run) for run in run_dirs]  # (no links followed)
    return [name if names.count(name) == 1 else str(run)
            for name, run in zip(names, run_dirs, strict=True)]  # fmt: skip


def plot_comparison(curves: Sequence[Curve], labels: Sequence[str], path: Path) -> Path:
    """Writes one figure of several runs' curves to ``path``, each run's mean return and its
    band in a colour of its own, named by ``labels`` (the bands are those of
    :attr:`Curve.band`: over episodes for a run of one member, over members for several). A
    sweep is a curve per setting (:func:`setting_curves`), never one mean over settings."""
    envs = list(dict.fromkeys(curve.env for curve in curves))
    named = []
    for curve, label in zip(curves, labels, strict=True):
        parts = setting_curves(curve) or [("", curve)]
        named += [(part, " ".join(filter(None, (label, setting))) + f" ({_band_name(part)})")
                  for setting, part in parts]  # fmt: skip
    return _save(named, Path(path), " / ".join(envs))


def setting_curves(curve: Curve) -> list[tuple[str, Curve]]:
    """A sweep as a curve per setting, ``(swept values, curve)`` in the order the settings
    first appear: its members, their mean (:func:`setting_means`) and, at each point, the
    95% bootstrap CI of that mean over the members that did not diverge (their range where
    3 or fewer: :func:`~td3_jax.core.stats.interval_name`); ``[]`` for a run that is no
    sweep."""
    parts = []
    for (setting, mean), (_, rows) in zip(setting_means(curve), _setting_rows(curve), strict=True):
        points = [[v for v in column if math.isfinite(v)] for column in zip(*rows, strict=True)]
        lower, upper = zip(*(_interval(values) for values in points), strict=True)
        parts.append((setting, curve._replace(mean=mean, lower=list(lower), upper=list(upper),
                                              members=rows, swept=(setting,) * len(rows))))
    return parts


def mixed_envs_warning(curves: Sequence[Curve]) -> str | None:
    """A warning when a comparison's runs trained different environments: their returns share
    one axis though their scales need not agree."""
    envs = list(dict.fromkeys(curve.env for curve in curves if curve.env))
    if len(envs) < 2:
        return None
    return (f"these runs trained different environments ({', '.join(envs)}); their returns "
            "share one axis")  # fmt: skip


def no_return_warning(curve: Curve, run_dir: Path) -> str | None:
    """A warning when no record of a run has a finite mean return (each is null: a run that
    diverged, or an environment's NaN rewards): its figure would be empty axes."""
    if any(math.isfinite(value) for value in curve.mean):
        return None
    return (f"{run_dir}: no record has a finite evaluation return (each is null or infinite), "
            "so its curve is empty")  # fmt: skip


def _interval(values: list[float]) -> tuple[float, float]:
    """:func:`~td3_jax.core.stats.bootstrap_ci` of ``values``, which is their [min, max] for
    fewer than :data:`~td3_jax.core.stats.CI_NARROWER_FROM` (taken at once: the bootstrap's
    resamples cost milliseconds a point); NaN for none."""
    if not values:
        return math.nan, math.nan
    if len(values) < stats.CI_NARROWER_FROM:
        return min(values), max(values)
    return stats.bootstrap_ci(values)


def _band_name(curve: Curve) -> str:
    """What a run's band is, briefly, for a comparison's legend."""
    if len(curve.members) == 1:  # (a sweep's setting of one seed: no band)
        return "1 member"
    if curve.members:
        return f"{len(curve.members)} members, {_interval_name(curve.members)}"
    return "± std over episodes"


def _interval_name(members: list[list[float]]) -> str:
    """What the band over ``members`` (each one's returns) is at the end: over those that did
    not diverge (:func:`~td3_jax.core.stats.interval_name`)."""
    return stats.interval_name(sum(math.isfinite(member[-1]) for member in members))
