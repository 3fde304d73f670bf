"""``td3-jax eval --json``: the file holds what the tables show, recomputable from its own
episode returns, with a diverged member as nulls; an unwritable path is refused first."""

from __future__ import annotations

import json

import numpy as np
import pytest
from support import TINY_FLAGS, assert_one_line_error, main, read_records


@pytest.mark.runs
def test_a_sweeps_evaluation_file_holds_each_member_and_each_setting_best_first(
    tmp_path, capsys
):
    out = tmp_path / "sweep"
    code, _, err = main(["sweep", *TINY_FLAGS, "--sweep-critic-lr", "1e-3", "1e30",
                         "--out", str(out), "--quiet"], capsys)  # fmt: skip
    assert code == 0, err
    path = tmp_path / "eval.json"
    code, _, err = main(["eval", "--run", str(out), "--episodes", "3", "--json", str(path)],
                        capsys)  # fmt: skip
    assert code == 0, err
    written = json.loads(path.read_text())
    assert (written["run"], written["episodes"], written["seed"]) == (str(out), 3, 12345)
    assert written["env_steps"] == read_records(out)[-1]["env_steps"]
    assert written["over_members"] is None  # (a sweep: never pooled over settings)
    alive, gone = written["members"]
    assert (alive["diverged"], gone["diverged"], gone["returns"]) == (False, True, None)
    returns = np.asarray(alive["returns"])
    assert returns.shape == (3,)
    assert alive["eval_return_mean"] == pytest.approx(returns.mean())
    assert alive["eval_return_std"] == pytest.approx(returns.std())
    assert (alive["eval_return_min"], alive["eval_return_max"]) == (returns.min(), returns.max())
    assert (alive["label"], gone["label"]) == ("critic_lr=0.001 seed=7", "critic_lr=1e+30 seed=7")
    best, last = written["per_setting"]
    assert best["settings"] == {"critic_lr": 1e-3} and last["settings"] == {"critic_lr": 1e30}
    assert (best["seeds"], best["diverged"], last["diverged"]) == (1, 0, 1)
    assert best["eval_return_mean"] == pytest.approx(alive["eval_return_mean"])
    assert best["interval"] is None and best["eval_return_ci95_low"] is None  # (one seed)
    assert "eval_return_mean" not in last
    code, _, err = main(["eval", "--run", str(out), "--json", str(out / "config.json")], capsys)
    assert_one_line_error(code, err, "is inside the run's folder")
    code, _, err = main(["eval", "--run", str(out), "--episodes", "2", "--json", str(path)],
                        capsys)  # fmt: skip
    assert code == 0, err  # (an evaluation's file is replaced by the next)
    assert json.loads(path.read_text())["episodes"] == 2


@pytest.mark.parametrize(("where", "message"), [
    ("no such folder/eval.json", "cannot write it"), ("a folder", "is not a plain file")])
def test_an_unwritable_json_path_is_refused_before_the_evaluation(where, message, tmp_path,
                                                                  capsys):  # fmt: skip
    (tmp_path / "a folder").mkdir()
    path = tmp_path / where
    code, _, err = main(["eval", "--run", str(tmp_path / "missing"), "--json", str(path)],
                        capsys)  # fmt: skip
    assert_one_line_error(code, err, f"--json {path}", message)


@pytest.mark.parametrize("held", ["my notes\n", "{}\n", '{"members": []}\n'])
def test_a_file_eval_did_not_write_is_refused_and_kept(held, tmp_path, capsys):
    path = tmp_path / "notes.json"
    path.write_text(held)
    code, _, err = main(["eval", "--run", str(tmp_path / "missing"), "--json", str(path)],
                        capsys)  # fmt: skip
    assert_one_line_error(code, err, f"--json {path} exists and is not an evaluation")
    assert path.read_text() == held
