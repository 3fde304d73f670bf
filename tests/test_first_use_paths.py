"""What a new user meets first: flag errors, help text, the console lines of a run, what
config.json records and where TensorBoard and W&B place evaluation returns."""

from __future__ import annotations

import dataclasses
import json

from support import assert_one_line_error, main
from test_cli import tensorboard_scalars

from td3_jax.config import TrainConfig
from td3_jax.logger import MetricsLogger
from td3_jax.rundir import config_changes, load_config, save_config
from td3_jax.tracking import Tracker

# --------------------------------------------------------------------------------------------
# flags and help
# --------------------------------------------------------------------------------------------


def test_a_flag_of_numbers_given_text_is_one_clear_line(capsys):
    code, _, err = main(["train", "--actor-lr", "abc", "--out", "unused"], capsys)
    assert_one_line_error(code, err, "--actor-lr takes a number, got 'abc'")
    code, _, err = main(["train", "--num-envs=x"], capsys)
    assert_one_line_error(code, err, "--num-envs takes a whole number, got 'x'")
    code, _, err = main(["train", "--hidden-sizes", "64", "x", "--quiet"], capsys)
    assert_one_line_error(code, err, "--hidden-sizes takes whole numbers, got '64' 'x'")


def test_an_unknown_environment_is_the_only_output(capsys, tmp_path):
    code, out, err = main(["train", "--env", "playground/CheetahRunn", "--out",
                           str(tmp_path / "run")], capsys)  # fmt: skip
    assert out == ""  # (no "physics: ..." line before the error)
    assert_one_line_error(code, err, "unknown environment 'playground/CheetahRunn'",
                          "did you mean playground/CheetahRun?")  # fmt: skip
    assert not (tmp_path / "run").exists()


def test_hidden_sizes_help_shows_the_default_a_run_gets(capsys):
    code, out, _ = main(["train", "--help"], capsys)
    assert code == 0
    lines = out.splitlines()
    start = next(i for i, line in enumerate(lines) if "--hidden-sizes" in line)
    end = next(i for i in range(start + 1, len(lines)) if "--" in lines[i])
    entry = " ".join(line.strip("│ ") for line in lines[start:end])
    assert "None" not in entry, entry
    assert "(default: 256 256)" in entry, entry


# --------------------------------------------------------------------------------------------
# config.json
# --------------------------------------------------------------------------------------------


def test_config_json_records_the_values_the_algorithm_chose(tmp_path):
    # TD3Config: actor and critic Adam 1e-3, tau 0.005, 400-300; DDPGConfig: actor 1e-4,
    # critic 1e-3, tau 0.01, 256-256 (the seed notes' defaults)
    left = dict(actor_lr=None, critic_lr=None, tau=None, hidden_sizes=None)
    for algo, expected in (("td3", [1e-3, 1e-3, 0.005, [400, 300]]),
                           ("ddpg", [1e-4, 1e-3, 0.01, [256, 256]])):  # fmt: skip
        cfg = TrainConfig(algo=algo, **left)
        save_config(cfg, [], tmp_path)
        saved = json.loads((tmp_path / "config.json").read_text())
        assert [saved[k] for k in left] == expected, algo
        assert config_changes(load_config(tmp_path), cfg) == {}  # the same run
    given = TrainConfig(actor_lr=3e-4, tau=0.02, hidden_sizes=(64, 64))
    save_config(given, [], tmp_path)
    saved = json.loads((tmp_path / "config.json").read_text())
    assert [saved[k] for k in left] == [3e-4, 1e-3, 0.02, [64, 64]]


def test_an_old_config_json_with_nulls_still_loads_and_resumes_unchanged(tmp_path):
    cfg = TrainConfig(actor_lr=None, critic_lr=None, tau=None, hidden_sizes=None)
    old = {**dataclasses.asdict(cfg), "preset": "pendulum"}  # as written before
    (tmp_path / "config.json").write_text(json.dumps(old))
    loaded = load_config(tmp_path)
    assert loaded.actor_lr is None and loaded.hidden_sizes is None
    resolved = dataclasses.replace(loaded, actor_lr=1e-3, tau=0.005, hidden_sizes=(400, 300))
    assert config_changes(loaded, resolved) == {}


# --------------------------------------------------------------------------------------------
# where evaluation returns are placed
# --------------------------------------------------------------------------------------------

# A record of an in-chunk evaluation: the returns are of the policy at 3200 env steps.
IN_CHUNK_RECORD = {"env_steps": 6400, "eval_policy_env_steps": 3200, "eval_return_mean": -150.0,
                   "eval_return_std": 12.5, "critic_loss": 0.25, "wall_time_s": 9.0}  # fmt: skip


def test_tensorboard_places_in_chunk_returns_at_the_policys_steps(tmp_path):
    logger = MetricsLogger(tmp_path)
    logger.write(IN_CHUNK_RECORD)
    logger.write({"env_steps": 9600, "eval_return_mean": -90.0, "critic_loss": 0.125})
    logger.close()
    scalars = tensorboard_scalars(tmp_path)
    assert scalars["eval_return_mean"] == {3200: -150.0, 9600: -90.0}
    assert scalars["eval_return_std"] == {3200: 12.5}
    assert scalars["critic_loss"] == {6400: 0.25, 9600: 0.125}
    assert scalars["eval_policy_env_steps"] == {6400: 3200.0}


class _Recorder:
    def __init__(self) -> None:
        self.logged: list[dict] = []

    def log(self, values: dict) -> None:
        self.logged.append(dict(values))


def test_wandb_places_in_chunk_returns_at_the_policys_steps():
    run = _Recorder()
    tracker = Tracker(run, image=lambda path: path)
    member = {"seed": 0, "eval_return_mean": -140.0, "critic_loss": 0.5}
    tracker.log({**IN_CHUNK_RECORD, "per_member": [member]})
    rest, returns = run.logged
    assert returns == {"eval_return_mean": -150.0, "eval_return_std": 12.5,
                       "per_member/0/eval_return_mean": -140.0, "env_steps": 3200}  # fmt: skip
    assert rest["env_steps"] == 6400 and rest["critic_loss"] == 0.25
    assert rest["per_member/0/critic_loss"] == 0.5 and rest["eval_policy_env_steps"] == 3200
    assert not any("eval_return" in key for key in rest)
    assert tracker.env_steps == 6400
    run.logged.clear()
    tracker.log({"env_steps": 9600, "eval_return_mean": -90.0})  # evaluated after the chunk
    assert run.logged == [{"env_steps": 9600, "eval_return_mean": -90.0}]
