"""The warning of a critic loss that grows without bound: at least doubled at each of 3
evaluations in a row and past 1e3, said once per run, naming what to look at."""

from __future__ import annotations

import math

import pytest
from configs import tiny_config

from td3_jax.runner import run as run_module
from td3_jax.runner.critic_growth import growing_without_bound, growth_warning


@pytest.mark.parametrize(
    ("losses", "growing"),
    [
        ([200, 400, 800, 1600], True),
        ([5, 200, 400, 800, 1600], True),  # (the last four count)
        ([125, 250, 500, 1001], True),
        ([125, 250, 500, 1000], False),  # not past 1e3
        ([10, 20, 40, 80], False),  # doubling, but small: an early, settling loss
        ([200, 400, 790, 1600], False),  # one step short of doubling
        ([400, 800, 1600], False),  # two doublings: too few evaluations
        ([1000, 2000, 4000, 8000, 9000], False),  # it has stopped doubling
        ([200, 400, math.nan, 1600, 3200], False),  # (a diverged chunk's loss never counts)
        ([200, 400, 800, math.inf], False),
        ([-200, 400, 800, 1600], False),
        ([], False),
    ],
)
def test_growth_is_at_least_doubling_three_evaluations_in_a_row_past_1e3(losses, growing):
    assert growing_without_bound(losses) is growing


def test_the_warning_names_the_loss_and_what_to_look_at():
    records = [{"critic_loss": loss, "env_steps": 4000 * (i + 1)}
               for i, loss in enumerate([300.0, 700.0, 1500.0, 3100.0])]  # fmt: skip
    warning = growth_warning(records)
    assert warning.startswith("the critic loss at least doubled at each of the last 3 "
                              "evaluations, to 3,100 at env step 16,000: ")  # fmt: skip
    for needle in ("reward scale", "--return-bound", "--total-steps", "--expl-noise"):
        assert needle in warning
    assert growth_warning(records[:3]) is None


@pytest.mark.runs
def test_a_run_says_it_once(tmp_path, monkeypatch, capsys):
    """Six chunks whose critic loss triples from 100: the warning comes after the fourth
    (2,700) and is not repeated at the fifth and sixth."""
    real = run_module._chunk_and_record

    def tripling(run, compiled, state, iterations):
        state, record = real(run, compiled, state, iterations)
        record["critic_loss"] = 100.0 * 3 ** len(run.records)
        return state, record

    monkeypatch.setattr(run_module, "_chunk_and_record", tripling)
    records = run_module.train(tiny_config(total_steps=384), tmp_path / "run", progress=False)
    assert [r["critic_loss"] for r in records] == [100.0 * 3**i for i in range(6)]
    err = capsys.readouterr().err
    assert err.count("td3-jax: warning: the critic loss at least doubled") == 1, err
    assert "to 2,700 at env step 256:" in err
