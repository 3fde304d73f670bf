"""The tables the command line prints with rich: a sweep's settings ranked by their final
return (with 95% CIs over seeds), and an evaluation's returns per member."""

from __future__ import annotations

from typing import Any

__all__ = ["output_console", "print_returns_table", "print_sweep_ranking", "ranked_settings",
           "sweep_record"]


def output_console() -> Any:
    """A rich console for stdout: a terminal's width, else (a log file, a pipe) as wide as
    the output needs (rich would cut tables to 80 columns)."""
    from rich.console import Console  # lazy: rich, only for a table

    console = Console()
    return console if console.is_terminal else Console(width=100_000)


def print_sweep_ranking(record: dict) -> None:
    """Final returns per swept setting (mean over its seeds), best first, with 95% CIs (none
    from one finite return).

    ``record`` holds ``env_steps`` and ``per_member``: each member's ``settings`` (its swept
    values) and ``eval_return_mean``. Diverged members (null returns) are left out of their
    setting's statistics and counted in the ``diverged`` column; a setting whose every seed
    diverged ranks last.
    """
    from rich.table import Table  # lazy: rich, only for a table

    from td3_jax.runner.logger import setting_label  # lazy: imports JAX

    rows = ranked_settings(record["per_member"])
    labels = [setting_label(row[0]) for row in rows]
    table = Table()
    for column in ("rank", "setting", "seeds", "diverged", "mean", "95% CI", "IQM"):
        width = max(map(len, labels)) if column == "setting" else None
        table.add_column(column, justify="right", min_width=width, no_wrap=column == "setting")
    for rank, (label, (_, n, diverged, summary)) in enumerate(zip(labels, rows, strict=True), 1):
        cells = ["-", "-", "-"]
        if summary is not None:
            interval = _interval_cell(summary, n - diverged)
            cells = [f"{summary['mean']:.1f}", interval, f"{summary['iqm']:.1f}"]
        table.add_row(str(rank), label, str(n), str(diverged), *cells)
    _print_titled(f"final evaluation return after {record['env_steps']} env steps", table)


def _interval_cell(summary: dict, finite: int) -> str:
    """A setting's 95% CI of its ``finite`` returns' mean; "(range)" after it where, from 3 or
    fewer, it is their [min, max] (:func:`~td3_jax.core.stats.interval_name`); none from one."""
    from td3_jax.core import stats  # lazy: NumPy, only for a table

    if finite <= 1:
        return "- (1 seed)"
    interval = f"[{summary['ci95_low']:.1f}, {summary['ci95_high']:.1f}]"
    return interval if stats.interval_name(finite) == "95% CI" else f"{interval} (range)"


def _print_titled(title: str, table: Any) -> Any:
    """``title`` on a line of its own (so the table is no wider for it), then ``table``, on
    :func:`output_console`; returns that console."""
    console = output_console()
    console.print(title, markup=False, highlight=False, soft_wrap=True)
    console.print(table)
    return console


def ranked_settings(per_member: list[dict]) -> list[tuple[tuple, int, int, dict | None]]:
    """``(setting, seeds, diverged, summary)`` per swept setting of ``per_member``, the best
    mean first: ``setting`` its sorted ``(name, value)`` pairs, ``summary``
    :func:`~td3_jax.core.stats.summary` of its finite returns (None where every seed
    diverged: those rank last)."""
    import numpy as np  # lazy: NumPy, only for a table

    from td3_jax.core import stats  # lazy: NumPy, only for a table
    from td3_jax.runner.logger import returns_by_setting  # lazy: imports JAX

    rows = []
    for setting, returns in returns_by_setting(per_member).items():
        finite = np.asarray([r for r in returns if r is not None], np.float64)
        summary = stats.summary(finite) if finite.size else None
        rows.append((setting, len(returns), len(returns) - finite.size, summary))
    rows.sort(key=lambda row: -np.inf if row[3] is None else row[3]["mean"], reverse=True)
    return rows


def sweep_record(population: list, returns: Any, diverged: set[int], env_steps: int) -> dict:
    """The shape :func:`print_sweep_ranking` reads (``per_member``: each member's settings
    and mean return, ``None`` where it diverged) from ``returns [members, episodes]``."""
    per_member = [{"settings": dict(member.overrides),
                   "eval_return_mean": None if i in diverged else float(returns[i].mean())}
                  for i, member in enumerate(population)]  # fmt: skip
    return {"env_steps": env_steps, "per_member": per_member}


def print_returns_table(title: str, rows: list, aggregate: dict | None) -> None:
    """Per-member mean/std/min/max of episode returns (``rows``: ``(label, returns
    [episodes])``; ``-`` for a member whose returns are ``None``: diverged in training, as the
    sweep table shows it), then the statistics ``aggregate`` over the other members."""
    import numpy as np  # lazy: NumPy, only for a table
    from rich.table import Table  # lazy: rich, only for a table

    from td3_jax.core import stats  # lazy: NumPy, only for a table

    table = Table()
    for column in ("member", "mean", "std", "min", "max"):
        table.add_column(column, justify="right")
    for label, returns in rows:
        r = None if returns is None else np.asarray(returns)
        values = ["-"] * 4 if r is None else [f"{v:.1f}" for v in (r.mean(), r.std(), r.min(),
                                                                    r.max())]  # fmt: skip
        table.add_row(label, *values)
    console = _print_titled(title, table)
    if aggregate:
        alive = sum(returns is not None for _, returns in rows)
        console.print(
            f"over {alive} members: mean {aggregate['eval_return_mean']:.1f} "
            f"[{stats.interval_name(alive)} {aggregate['eval_return_ci95_low']:.1f}, "
            f"{aggregate['eval_return_ci95_high']:.1f}], median "
            f"{aggregate['eval_return_median']:.1f}, IQM {aggregate['eval_return_iqm']:.1f}",
            markup=False,  # (the bracketed interval is text, not rich's markup)
        )
