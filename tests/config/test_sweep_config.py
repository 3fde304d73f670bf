"""A sweep's run directory, end to end: what config.json says each member trained with, and the
commands that read it back (``train --resume``, ``eval``, ``export``)."""

from __future__ import annotations

import json

import pytest
from support import TINY_FLAGS, main, read_records

SWEEP_FLAGS = ["--seeds", "2", "--sweep-actor-lr", "3e-4", "1e-3", "--sweep-tau", "0.01"]


@pytest.mark.runs
def test_a_sweeps_config_json_is_each_members_values_through_resume_eval_and_export(
    tmp_path, capsys
):
    """config.json held the base actor_lr 0.001 and tau 0.005 (the pendulum preset's), which no
    member trained with; it now lists the swept values and every member's, as metrics.jsonl
    records them, and a resume, ``eval`` and ``export`` read the directory as before."""
    out = tmp_path / "sweep"
    code, _, err = main(["sweep", *TINY_FLAGS, "--quiet", *SWEEP_FLAGS, "--out", str(out)], capsys)
    assert code == 0, err
    config = json.loads((out / "config.json").read_text())
    assert config["actor_lr"] == [3e-4, 1e-3] and config["tau"] == [0.01]
    expected = [
        {"seed": 7, "actor_lr": 3e-4, "tau": 0.01},
        {"seed": 8, "actor_lr": 3e-4, "tau": 0.01},
        {"seed": 7, "actor_lr": 1e-3, "tau": 0.01},
        {"seed": 8, "actor_lr": 1e-3, "tau": 0.01},
    ]
    assert config["sweep"]["members"] == expected
    per_member = read_records(out)[-1]["per_member"]  # what each member trained with
    assert [{"seed": m["seed"], **m["settings"]} for m in per_member] == expected

    code, stdout, err = main(["train", "--resume", "--total-steps", "192", "--out", str(out),
                              "--quiet"], capsys)  # fmt: skip
    assert code == 0 and "done: 192 env steps" in stdout, err
    # `train --resume` of a sweep ends as `sweep --resume` does: pooled, then the ranking.
    assert "over all 4 members (per setting below)" in stdout, stdout
    ranking = stdout[stdout.index("per setting below") :]
    assert "0.0003" in ranking and "0.001" in ranking, stdout
    resumed = json.loads((out / "config.json").read_text())
    assert resumed["resume_changes"] == [{"at_env_steps": 128, "total_steps": [128, 192]}]
    assert {k: resumed[k] for k in ("actor_lr", "tau", "sweep")} == {
        k: config[k] for k in ("actor_lr", "tau", "sweep")
    }
    assert len(read_records(out)[-1]["per_member"]) == 4

    code, stdout, err = main(["eval", "--run", str(out), "--episodes", "2"], capsys)
    assert code == 0, err
    for label in ("actor_lr=0.0003 tau=0.01 seed=8", "actor_lr=0.001 tau=0.01 seed=7"):
        assert label in stdout, stdout
    policy = tmp_path / "member2.npz"
    code, stdout, err = main(["export", "--run", str(out), "--format", "npz", "--member", "2",
                              "--out", str(policy)], capsys)  # fmt: skip
    assert (
        code == 0
        and policy.is_file()
        and "member 2 (actor_lr=0.001 tau=0.01 seed=7) at 192 env steps" in stdout
    ), err
