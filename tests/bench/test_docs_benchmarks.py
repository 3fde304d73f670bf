"""docs/benchmarks.md shows what its data gives: each task's tables are the ones
benchmarks.report draws from docs/benchmarks/TASK.csv, each figure is there, nothing else is in
docs/benchmarks/, and every section the presets cite exists."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from benchmarks import curves, report
from benchmarks.tasks import TASKS

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "benchmarks.md"
DATA = ROOT / "docs" / "benchmarks"
CSVS = sorted(DATA.glob("*.csv"))


def test_every_task_has_its_curves_and_figure_and_nothing_else_is_kept():
    assert {p.stem for p in CSVS} == {"t1", "g1", "t1-rough", "g1-rough", "ant", "humanoid",
                                      "halfcheetah", "cheetah-run"}  # fmt: skip
    expected = {f"{p.stem}{suffix}" for p in CSVS for suffix in (".csv", ".png")}
    assert {p.name for p in DATA.iterdir()} == expected


@pytest.mark.parametrize("csv", CSVS, ids=lambda p: p.stem)
def test_the_page_shows_the_tables_and_figure_its_data_gives(csv):
    task, points = TASKS[csv.stem], curves.read(csv)
    page = PAGE.read_text()
    assert report.task_table(task, points) in page
    td3_runs = {p.run for p in points if p.program == curves.TD3_JAX}
    if len(td3_runs) > 1:
        assert report.settings_table(task, points) in page
    assert f"](benchmarks/{csv.stem}.png)" in page
    assert f"](benchmarks/{csv.stem}.csv)" in page


def _anchors(markdown: str) -> set[str]:
    """The anchors of a page's headings as mkdocs makes them (lowercase, words joined by -)."""
    headings = re.findall(r"^#+ (.+)$", markdown, re.M)
    return {re.sub(r"[\s]+", "-", re.sub(r"[^\w\s-]", "", h).strip().lower()) for h in headings}


def test_every_section_the_presets_cite_exists():
    source = (ROOT / "td3_jax" / "config" / "presets.py").read_text()
    cited = set(re.findall(r"#([a-z0-9-]+)", " ".join(re.findall(r"docs/benchmarks\.md\S*.*",
                                                                   source))))  # fmt: skip
    assert cited >= {"t1-flat", "g1-presets", "cpu-presets", "brax-locomotion-presets"}
    assert cited <= _anchors(PAGE.read_text())
