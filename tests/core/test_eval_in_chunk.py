"""Evaluation inside the training chunk (``--eval-in-chunk``): the training worlds see exactly
what they see without the evaluation worlds, and every finished round's returns are those of a
separate evaluation of the policy the round froze, with the same episodes."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support import TINY_FLAGS, read_records

from td3_jax.config import build
from td3_jax.config.schema import ConfigError, TrainConfig
from td3_jax.core import eval_worlds, training
from td3_jax.envs import FunctionalEnv
from td3_jax.runner import logger, programs
from td3_jax.runner.run import train
from td3_jax.runner.sharding import make_mesh

LIMIT = 12  # the time limit of the drift environment


def _drift_env() -> FunctionalEnv:
    """A point on a line drifting right, pushed by the action; reward for staying near 0.6,
    termination past |x| = 1 (a policy that does not push back ends before the time limit)."""

    def reset(key):
        x = jax.random.uniform(key, (), minval=-0.9, maxval=0.9)
        return x, jnp.stack([x, x * x])

    def step(x, action):
        x = x + 0.4 * action[0] + 0.2
        return x, jnp.stack([x, x * x]), 1.0 - (x - 0.6) ** 2, jnp.abs(x) > 1.0

    return FunctionalEnv(reset, step, observation_size=2, action_size=1, episode_length=LIMIT,
                         name="drift")  # fmt: skip


CFG = TrainConfig(
    num_envs=4,
    eval_envs=4,
    eval_every=4 * LIMIT,  # one episode per chunk
    total_steps=8 * LIMIT * 4,
    warmup_steps=8,
    batch_size=16,
    updates_per_iter=2,
    hidden_sizes=(16, 16),
    buffer_size=512,
    expl_noise=0.5,
)
IN_CHUNK = dataclasses.replace(CFG, eval_in_chunk=True)


def _program(cfg: TrainConfig):
    spec = build.make_spec(cfg, env=_drift_env())
    chunk = jax.jit(lambda hp, s, n: training.chunk(spec, hp, s, n))
    return spec, build.hyperparams(cfg), chunk


@pytest.mark.runs
def test_training_worlds_are_those_of_a_run_without_evaluation_worlds():
    (plain, hp, plain_chunk), (inside, _, inside_chunk) = _program(CFG), _program(IN_CHUNK)
    key = jax.random.PRNGKey(3)
    a, b = training.init(plain, key), training.init(inside, key)
    for _ in range(3):
        a, metrics_a = plain_chunk(hp, a, LIMIT)
        b, metrics_b = inside_chunk(hp, b, LIMIT)
    assert b.env_state.obs.shape[0] == CFG.num_envs + CFG.eval_envs
    # Same parameters, replay ring (no evaluation transitions in it), statistics, counters
    # (up to float rounding: the two programs are fused differently by XLA).
    same = lambda x, y: np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-5,
                                                   atol=1e-6)  # fmt: skip
    jax.tree.map(same, (a.agent, a.buffer, a.obs_stats, a.env_steps, a.key),
                 (b.agent, b.buffer, b.obs_stats, b.env_steps, b.key))  # fmt: skip
    train_obs, _ = eval_worlds.split(inside.layout, b.env_state.obs)
    same(a.env_state.obs, train_obs)
    for name in ("critic_loss", "train_return_mean", "train_episodes", "reward_mean"):
        same(metrics_a[name], metrics_b[name])
    # the round of the third chunk evaluated the policy of its start
    assert int(metrics_b["eval_policy_env_steps"]) == 2 * LIMIT * CFG.num_envs


def test_each_finished_round_is_a_separate_evaluation_of_its_frozen_policy():
    """Called one iteration at a time, each call starts a round where the last one has
    finished, with the policy of its start, and keeps it once finished."""
    spec, hp, chunk = _program(IN_CHUNK)
    state = jax.jit(training.init, static_argnums=0)(spec, jax.random.PRNGKey(1))
    evaluate = jax.jit(training.evaluate, static_argnums=0)  # compiled once, not every round
    policies = {0: state}  # env steps -> the state whose policy a round froze then
    checked, early, seen = 0, 0, 0
    for _ in range(5 * LIMIT):
        state, _ = chunk(hp, state, 1)  # one iteration at a time
        policies[int(state.env_steps)] = state
        evaluator = state.evaluator
        if not eval_worlds.finished(evaluator) or int(evaluator.rounds) == seen:
            continue  # no round finished in this call
        seen = int(evaluator.rounds)
        taken = int(evaluator.last_policy_env_steps)
        key = training.round_key(state.eval_key, seen - 1)
        expected = evaluate(spec, policies[taken], key)
        np.testing.assert_allclose(evaluator.last_returns, expected, rtol=1e-5, atol=1e-5)
        checked += 1
        early += int(state.env_steps - taken) < LIMIT * spec.num_envs
    assert checked >= 4
    assert early >= 1  # some round ended before the time limit: every episode terminated


@pytest.mark.parametrize("seeds", [1, 2])
def test_the_host_loops_two_programs_are_the_librarys_chunk(seeds):
    """The host loop runs a chunk as two programs (the round's start, then the iterations:
    Programs.train_chunk); they give what the library's one chunk gives, bit for bit, whether
    a call starts a round or not (one iteration at a time: most calls start none)."""
    cfg = dataclasses.replace(IN_CHUNK, seeds=seeds)
    env, mesh = _drift_env(), make_mesh(1)
    program = build.make_population(cfg, build.members(cfg), env=env, mesh=mesh)
    split = programs.jitted(program, mesh)
    assert split.start_round is not None
    whole = jax.jit(program.chunk)
    a = split.init()
    b = split.init()
    for iterations in (1, LIMIT, 1, 1, LIMIT - 1, LIMIT, 3):
        a, metrics_a = whole(program.hyperparams, a, np.int32(iterations))
        b, metrics_b = split.train_chunk(b, np.int32(iterations))
        leaves = jax.tree.leaves((a, metrics_a))
        for x, y in zip(leaves, jax.tree.leaves((b, metrics_b)), strict=True):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert int(a.evaluator.rounds[0]) >= 3  # rounds started and finished on the way


@pytest.mark.runs
def test_rounds_of_a_population_member_are_those_of_its_lone_run():
    cfg = dataclasses.replace(IN_CHUNK, total_steps=2 * LIMIT * 4)
    env = _drift_env()
    _, lone = jax.jit(build.make_train(cfg, env=env))(jax.random.PRNGKey(7))
    vmapped = jax.vmap(build.make_train(cfg, env=env, axis_name="seeds"), axis_name="seeds")
    _, both = jax.jit(vmapped)(jnp.stack([jax.random.PRNGKey(7), jax.random.PRNGKey(8)]))
    np.testing.assert_allclose(both["eval_returns"][0], lone["eval_returns"], rtol=1e-4)
    np.testing.assert_array_equal(both["eval_policy_env_steps"][0], lone["eval_policy_env_steps"])
    assert np.all(np.isfinite(lone["eval_returns"]))


def test_layout_splits_and_joins_groups_of_training_then_evaluation_worlds():
    layout = eval_worlds.Layout(train=4, evaluation=2, groups=2)
    batch = np.arange(6 * 3, dtype=np.int32).reshape(6, 3)  # groups [t t e][t t e]
    train_rows, eval_rows = eval_worlds.split(layout, batch)
    np.testing.assert_array_equal(train_rows[:, 0], [0, 3, 9, 12])
    np.testing.assert_array_equal(eval_rows[:, 0], [6, 15])
    np.testing.assert_array_equal(eval_worlds.join(layout, train_rows, eval_rows), batch)
    tree = {"rows": batch, "shared": jnp.zeros((0,))}
    fresh = {"rows": -jnp.ones((2, 3), jnp.int32), "shared": jnp.zeros((0,))}
    kept = eval_worlds.put_evaluation(layout, tree, fresh, jnp.array(False))
    np.testing.assert_array_equal(kept["rows"], batch)
    put = np.asarray(eval_worlds.put_evaluation(layout, tree, fresh, jnp.array(True))["rows"])
    np.testing.assert_array_equal(put[[2, 5]], -1)
    np.testing.assert_array_equal(put[[0, 1, 3, 4]], batch[[0, 1, 3, 4]])


def test_a_chunk_shorter_than_an_episode_is_refused():
    short = dataclasses.replace(IN_CHUNK, eval_every=4 * (LIMIT - 1))
    with pytest.raises(ConfigError, match="--eval-in-chunk needs chunks of at least one episode"):
        build.make_spec(short, env=_drift_env())
    with pytest.raises(ConfigError, match=f"use --eval-every {4 * LIMIT} or more, or --no-eval-in"):
        build.make_spec(short, env=_drift_env())
    split = dataclasses.replace(IN_CHUNK, eval_envs=3, replay_shards=2)
    with pytest.raises(ConfigError, match=r"--eval-envs \(3\) must be divisible by 2"):
        build.make_spec(split, env=_drift_env())


@pytest.mark.runs
def test_records_carry_the_rounds_policy_steps(tmp_path):
    records = train(IN_CHUNK, tmp_path / "run", env=_drift_env(), progress=False)
    steps = [r["eval_policy_env_steps"] for r in records]
    chunk = IN_CHUNK.steps_per_chunk
    # each record holds the round that ran through its chunk: the policy of the chunk's start
    assert steps == [c * chunk for c in range(len(records))]
    assert all(np.isfinite(r["eval_return_mean"]) for r in records)
    saved = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").open()]
    assert [r["eval_policy_env_steps"] for r in saved] == steps
    # env steps are whole numbers, in the records and in metrics.jsonl (3200, not 3200.0)
    assert all(type(r["eval_policy_env_steps"]) is int for r in records + saved)
    # curve.png plots each return at its policy's env steps (the record's own without a round)
    assert [logger.evaluated_steps(r) for r in saved] == steps
    assert logger.evaluated_steps({"env_steps": 96, "eval_policy_env_steps": -1}) == 96
    assert logger.evaluated_steps({"env_steps": 96}) == 96


@pytest.mark.runs
def test_a_resumed_run_evaluates_as_a_straight_one(tmp_path):
    straight = train(IN_CHUNK, tmp_path / "straight", env=_drift_env(), progress=False)
    half = dataclasses.replace(IN_CHUNK, total_steps=IN_CHUNK.total_steps // 2)
    first = train(half, tmp_path / "resumed", env=_drift_env(), progress=False)
    with pytest.raises(ConfigError, match=r"--eval-envs 2 given .* evaluation worlds are in"):
        train(dataclasses.replace(IN_CHUNK, eval_envs=2), tmp_path / "resumed",
              env=_drift_env(), progress=False, resume=True)  # fmt: skip
    rest = train(IN_CHUNK, tmp_path / "resumed", env=_drift_env(), progress=False, resume=True)
    assert len(first) + len(rest) == len(straight)
    for a, b in zip(straight, first + rest, strict=True):
        assert a["eval_policy_env_steps"] == b["eval_policy_env_steps"]
        assert a["eval_return_mean"] == pytest.approx(b["eval_return_mean"], rel=1e-5, abs=1e-5)


@pytest.mark.processes
def test_two_devices_and_a_resume_on_one_evaluate_as_one_device(tmp_path):
    """The evaluation worlds split over 2 devices give the one-device rounds, and a run started
    on 2 devices and resumed on 1 keeps its worlds where they were (the layout follows the
    replay slices, a setting of the run, not the device count)."""
    flags = [*TINY_FLAGS, "--eval-in-chunk", "--quiet"]  # chunks of 16 steps: one episode
    env = {**os.environ, "JAX_PLATFORMS": "cpu",
           "XLA_FLAGS": "--xla_force_host_platform_device_count=2"}  # fmt: skip

    def run(name: str, devices: int, steps: int, *more: str) -> None:
        proc = subprocess.run([sys.executable, "-m", "td3_jax", "train", *flags, "--devices",
                               str(devices), "--total-steps", str(steps), "--out",
                               str(tmp_path / name), *more], env=env, capture_output=True,
                              text=True, timeout=600)  # fmt: skip
        assert proc.returncode == 0, proc.stderr[-3000:]

    run("d1", 1, 192)
    run("d2", 2, 192)
    run("moved", 2, 96)
    run("moved", 1, 192, "--resume")
    one = read_records(tmp_path / "d1")
    for other in (read_records(tmp_path / "d2"), read_records(tmp_path / "moved")):
        assert [r["eval_policy_env_steps"] for r in other] == [r["eval_policy_env_steps"]
                                                                for r in one]  # fmt: skip
        for a, b in zip(one, other, strict=True):
            for name in ("eval_return_mean", "train_return_mean", "critic_loss"):
                assert a[name] == pytest.approx(b[name], rel=1e-3, abs=1e-3), name


def test_eval_and_export_read_an_in_chunk_run_with_any_episode_count(tmp_path):
    """The checkpoint holds the run's own evaluation worlds; `td3-jax eval --episodes N`
    evaluates the final policy on N fresh episodes whatever N."""
    from td3_jax.runner.finished import evaluate_run

    out = tmp_path / "run"
    cfg = dataclasses.replace(IN_CHUNK, env="test_eval_in_chunk:_drift_env")  # a factory
    train(cfg, out, progress=False)
    for episodes in (3, IN_CHUNK.eval_envs):
        _, members, meta, returns = evaluate_run(out, episodes, seed=0)
        assert returns.shape == (1, episodes) and np.all(np.isfinite(returns))
        assert meta["env_steps"] == IN_CHUNK.run_steps and len(members) == 1


def test_the_console_says_which_policy_an_in_chunk_return_is_of():
    from td3_jax.cli.notes import done_line
    from td3_jax.runner.run import _evaluation_text

    record = {"env_steps": 6400, "wall_time_s": 16.4, "eval_return_mean": -1532.54,
              "eval_return_std": 62.5, "eval_policy_env_steps": 3200.0}  # fmt: skip
    assert _evaluation_text(record) == "-1532.5 (policy of 3,200 steps)"
    assert done_line(record, "runs/x") == (
        "done: 6,400 env steps in 16 s; eval return -1532.5 ± 62.5 (policy of 3,200 steps; "
        "td3-jax eval for the final one); outputs in runs/x"
    )
    separate = {k: v for k, v in record.items() if k != "eval_policy_env_steps"}
    assert _evaluation_text(separate) == "-1532.5"
    assert done_line(separate, "runs/x").endswith("-1532.5 ± 62.5; outputs in runs/x")


def test_the_done_line_groups_digits_as_the_progress_lines_do():
    """A resumed 50M-step run: every count with thousands separators (it printed 53248000
    beside progress lines' 53,248,000)."""
    from td3_jax.cli.notes import done_line

    record = {"env_steps": 53_248_000, "wall_time_s": 615.4, "eval_return_mean": 41.76,
              "eval_return_std": 3.29, "eval_policy_env_steps": 49_152_000.0}  # fmt: skip
    line = done_line(record, "runs/t1", process_s=250.2, resumed_at=32_768_000)
    assert line == (
        "done: 53,248,000 env steps (20,480,000 in this process, in 250 s; 615 s over the "
        "whole run); eval return 41.8 ± 3.3 (policy of 49,152,000 steps; td3-jax eval for the "
        "final one); outputs in runs/t1"
    )
