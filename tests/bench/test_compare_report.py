"""The baseline comparison's report (benchmarks/compare.py): each program's start-up and steady
rate beside its curve, checked on hand-made evaluation records."""

from __future__ import annotations

import pytest

from benchmarks import compare

# A PPO-like program: first evaluation at 71 s, the next at 141 s (compiling its training epoch),
# then 660K env steps/s.
SLOW_START = [
    {"wall_s": 71.0, "env_steps": 0, "eval_return": -50.0},
    {"wall_s": 141.0, "env_steps": 3_300_000, "eval_return": 500.0},
    {"wall_s": 151.0, "env_steps": 9_900_000, "eval_return": 1500.0},
    {"wall_s": 161.0, "env_steps": 16_500_000, "eval_return": 2500.0},
]


def test_the_steady_rate_leaves_out_the_start_up():
    assert compare.steady_rate(SLOW_START) == pytest.approx(13_200_000 / 20.0)  # 660K
    assert compare.steady_rate(SLOW_START[:2]) is None  # two evaluations say nothing steady


def test_returns_are_also_read_from_each_programs_first_evaluation():
    table = compare.table_from_first({"ppo": {"rows": SLOW_START, "status": "ok"}}, 100.0)
    row = table.splitlines()[2].split("|")[1:-1]
    # budget 100: times 25, 50, 75, 100 after the first evaluation (71 s): 96, 121, 146, 171 s
    assert [c.strip() for c in row] == ["ppo", "71.0", "-50.0", "-50.0", "500.0", "2500.0",
                                        "660,000"]  # fmt: skip
