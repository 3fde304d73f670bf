"""The compiled training chunk and the host loop, end to end on tiny gymnax/Pendulum-v1 runs.

Compilation dominates on a CPU, so each configuration is compiled once per module: the fixture
``learn`` runs three chunks of one small TD3 configuration and keeps host copies of everything
the tests look at; ``explore`` does the same for an OU-exploration configuration without
gradient updates (its actor never changes, so every stored action can be recomputed exactly).

Layout of the tiny runs: ``NUM_ENVS`` environments, one vectorised step per iteration, so the
replay buffer's row ``r`` holds the transition of environment ``r % NUM_ENVS`` at global step
``r // NUM_ENVS`` (for rows written before the ring wraps around).
"""

from __future__ import annotations

import dataclasses
import json
import math
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from td3_jax.common.errors import NonFiniteError
from td3_jax.config.build import make_population, make_trainer, members
from td3_jax.config.schema import TrainConfig, validate
from td3_jax.core.normalization import RunningStats
from td3_jax.runner import programs
from td3_jax.runner.checkpoint import Checkpointer
from td3_jax.runner.finished import restore_state
from td3_jax.runner.logger import read_metrics
from td3_jax.runner.run import train

NUM_ENVS = 4
EPISODE = 16  # time limit of the tiny runs (Pendulum's own is 200)
PENDULUM_DT = 0.05  # gymnax Pendulum-v1 integration step
PENDULUM_MAX_TORQUE = 2.0

TINY = dict(
    env="gymnax/Pendulum-v1",
    hidden_sizes=(16, 16),
    num_envs=NUM_ENVS,
    steps_per_iter=1,
    eval_envs=2,
    episode_length=EPISODE,
    actor_lr=1e-3,
    critic_lr=1e-3,
)

# 24 iterations (96 env steps) per chunk; warm-up ends inside the second chunk; the ring buffer
# (160 slots) fills up during the second chunk.
LEARN = TrainConfig(
    **TINY,
    eval_every=96,
    total_steps=3 * 96,
    updates_per_iter=2,
    batch_size=16,
    buffer_size=160,
    warmup_steps=150,
)

# No updates and no observation normalisation: the policy is a fixed function of the stored obs.
# The first chunk is exactly the warm-up.
EXPLORE = TrainConfig(
    **TINY,
    eval_every=96,
    total_steps=3 * 96,
    updates_per_iter=0,
    batch_size=16,
    warmup_steps=96,
    normalize_obs=False,
    exploration="ou",
    ou_sigma=0.3,
    ou_min_sigma=0.3,
)


def restore(cfg: TrainConfig, out_dir):
    """The newest checkpoint of a single-seed run directory (state with a member axis of 1)."""
    return restore_state(make_population(cfg, members(cfg)), out_dir)


def host(tree):
    """A host copy (numpy, owning its memory) of a pytree, safe to keep after buffer donation."""
    return jax.tree.map(lambda x: np.array(x, copy=True), tree)


def expected_updates(cfg: TrainConfig, start_env_steps: int, start_buffer: int, iters: int) -> int:
    """Hand count: updates_per_iter for each iteration ending with env_steps >= warmup and a
    buffer holding at least one batch."""
    total = 0
    for i in range(1, iters + 1):
        env_steps = start_env_steps + i * cfg.env_steps_per_iter
        buffer = min(start_buffer + i * cfg.env_steps_per_iter, cfg.replay_capacity)
        if env_steps >= cfg.warmup_steps and buffer >= cfg.batch_size:
            total += cfg.updates_per_iter
    return total


class CountedRun(types.SimpleNamespace):
    """Host copies of a few chunks of one configuration, plus the jitted functions used."""


def run_chunks(cfg: TrainConfig, n_chunks: int) -> CountedRun:
    validate(cfg)
    trainer = make_trainer(cfg)
    traces = {"chunk": 0, "evaluate": 0}

    def counted_chunk(state):
        traces["chunk"] += 1
        return trainer.chunk(state)

    def counted_evaluate(state, key):
        traces["evaluate"] += 1
        return trainer.evaluate(state, key)

    chunk = jax.jit(counted_chunk, donate_argnums=0)
    evaluate = jax.jit(counted_evaluate)
    state = jax.jit(trainer.init)(jax.random.PRNGKey(cfg.seed))
    states, metrics, returns = [host(state)], [], []
    for i in range(n_chunks):
        state, m = chunk(state)
        metrics.append({k: float(v) for k, v in m.items()})
        states.append(host(state))
        returns.append(np.asarray(evaluate(state, jax.random.PRNGKey(100 + i))))
    return CountedRun(
        cfg=cfg,
        trainer=trainer,
        chunk=chunk,
        evaluate=evaluate,
        traces=dict(traces),
        chunk_cache_size=chunk._cache_size(),
        evaluate_cache_size=evaluate._cache_size(),
        states=states,  # states[0]: initial, states[i]: after chunk i
        metrics=metrics,  # metrics[i]: of chunk i + 1
        returns=returns,
        last_state=state,  # live device state after the last chunk (not donated yet)
    )


@pytest.fixture(scope="module")
def learn() -> CountedRun:
    return run_chunks(LEARN, 3)


@pytest.fixture(scope="module")
def explore() -> CountedRun:
    return run_chunks(EXPLORE, 3)


def ring(buffer):
    """The one replay slice of a ``replay_shards=1`` buffer (leaves ``[1, capacity, ...]``)."""
    return jax.tree.map(lambda x: x[0], buffer)


def rows(buffer_data, chunk_rows: slice | None = None):
    """Buffer rows reshaped to [steps, num_envs, ...] (rows must be in write order)."""
    sel = chunk_rows or slice(None)
    return jax.tree.map(lambda x: x[sel].reshape(-1, NUM_ENVS, *x.shape[1:]), buffer_data)


# --------------------------------------------------------------------------------------------
# compile once
# --------------------------------------------------------------------------------------------


def test_chunk_compiles_once(learn):
    assert LEARN.iters_per_chunk == 24
    assert learn.traces["chunk"] == 1, "the chunk was traced again for a later chunk"
    assert learn.chunk_cache_size == 1
    # The state coming out of a chunk has exactly the structure, shapes and dtypes going in.
    before = jax.tree.map(lambda x: (x.shape, x.dtype), learn.states[0])
    after = jax.tree.map(lambda x: (x.shape, x.dtype), learn.states[-1])
    assert before == after


def test_evaluate_compiles_once(learn):
    assert learn.traces["evaluate"] == 1
    assert learn.evaluate_cache_size == 1
    for returns in learn.returns:
        assert returns.shape == (LEARN.eval_envs,)
        assert np.all(np.isfinite(returns))
        # Pendulum rewards lie in [-16.3, 0]; EPISODE steps each.
        assert np.all(returns <= 0.0) and np.all(returns >= -16.3 * EPISODE)


# --------------------------------------------------------------------------------------------
# warm-up and update counts
# --------------------------------------------------------------------------------------------


def test_no_update_before_warmup(learn):
    steps_per_chunk = LEARN.iters_per_chunk * LEARN.env_steps_per_iter
    assert steps_per_chunk < LEARN.warmup_steps < 2 * steps_per_chunk
    s0, s1 = learn.states[0], learn.states[1]
    assert int(s1.env_steps) == steps_per_chunk
    assert int(s1.iteration) == LEARN.iters_per_chunk
    assert int(s1.agent.step) == 0
    assert learn.metrics[0]["chunk_updates"] == 0
    # Nothing the agent learns has moved.
    for a, b in zip(jax.tree.leaves(s0.agent), jax.tree.leaves(s1.agent), strict=True):
        assert np.array_equal(a, b)


def test_update_count_after_warmup(learn):
    per_chunk = LEARN.iters_per_chunk * LEARN.env_steps_per_iter
    expected = [
        expected_updates(LEARN, i * per_chunk, min(i * per_chunk, LEARN.replay_capacity), 24)
        for i in range(3)
    ]
    # Hand count for these numbers: env steps 4 i >= 150 <=> i >= 38; 2 updates per iteration.
    assert expected == [0, 2 * (48 - 38 + 1), 2 * 24]
    for i in range(3):
        assert learn.metrics[i]["chunk_updates"] == expected[i]
        assert int(learn.states[i + 1].agent.step) == sum(expected[: i + 1])


def test_updates_wait_for_a_full_batch(learn):
    """After warm-up, a buffer with fewer than batch_size transitions still gets no updates."""
    state = host(learn.states[1])
    state = state.replace(
        env_steps=np.asarray(10_000, np.int32),
        buffer=state.buffer.replace(
            position=np.zeros((1,), np.int32), size=np.zeros((1,), np.int32)
        ),
    )
    step_before = int(state.agent.step)
    out, metrics = learn.chunk(jax.device_put(state))
    expected = expected_updates(LEARN, 10_000, 0, LEARN.iters_per_chunk)
    assert expected == 2 * (24 - 4 + 1)  # the buffer reaches 16 transitions at iteration 4
    assert float(metrics["chunk_updates"]) == expected
    assert int(out.agent.step) == step_before + expected


# --------------------------------------------------------------------------------------------
# replay contents
# --------------------------------------------------------------------------------------------


def test_buffer_holds_min_of_steps_and_capacity(learn):
    assert LEARN.replay_capacity == 160
    for i in (1, 2, 3):
        buf = ring(learn.states[i].buffer)
        steps = int(learn.states[i].env_steps)
        assert steps == 96 * i
        assert int(buf.size) == min(steps, LEARN.replay_capacity)
        assert int(buf.position) == steps % LEARN.replay_capacity
    # Before wrap-around, the unwritten slots are still zero and the written ones are not.
    buf1 = ring(learn.states[1].buffer)
    assert np.all(buf1.data[0].obs[96:] == 0)
    assert np.all(np.any(buf1.data[0].obs[:96] != 0, axis=-1))


def _angle(obs):
    return np.arctan2(obs[..., 1], obs[..., 0])


def _wrap(x):
    return (x + np.pi) % (2 * np.pi) - np.pi


def test_stored_transitions_pendulum(learn):
    """done is 0 (time limits only), next_obs is the true successor, even at episode ends."""
    data = rows(ring(learn.states[1].buffer.data[0]), slice(0, 96))  # [24 steps, 4 envs, ...]
    obs, action, reward, next_obs, done = (
        data.obs,
        data.action,
        data.reward,
        data.next_obs,
        data.done,
    )
    assert obs.shape == (24, NUM_ENVS, 3)
    assert np.all(done == 0.0)
    # Beside each transition the ring keeps whether its episode ended there (here: time limits).
    ended = rows(ring(learn.states[1].buffer.data[1]), slice(0, 96))
    expected_ended = (np.arange(1, 25) % EPISODE == 0)[:, None].repeat(NUM_ENVS, axis=1)
    np.testing.assert_array_equal(ended, expected_ended)
    assert np.all(np.abs(action) <= 1.0)

    # Pendulum physics: theta' = theta + dt * thetadot', for every stored transition. A next_obs
    # replaced by the reset observation at an episode end would break this.
    dtheta = _wrap(_angle(next_obs) - _angle(obs))
    np.testing.assert_allclose(dtheta, PENDULUM_DT * next_obs[..., 2], atol=2e-4)

    # Reward of the stored (obs, action): -(theta^2 + 0.1 thetadot^2 + 0.001 u^2), u = 2 a.
    u = PENDULUM_MAX_TORQUE * action[..., 0]
    expected_reward = -(_angle(obs) ** 2 + 0.1 * obs[..., 2] ** 2 + 0.001 * u**2)
    np.testing.assert_allclose(reward, expected_reward, rtol=1e-4, atol=1e-4)

    # Within an episode next_obs is the following obs; at the time limit the environment was
    # reset, so the following obs is a fresh start, not the stored next_obs.
    for t in range(23):
        end = (t + 1) % EPISODE == 0
        for e in range(NUM_ENVS):
            if end:
                assert not np.allclose(next_obs[t, e], obs[t + 1, e], atol=1e-3), (t, e)
            else:
                assert np.array_equal(next_obs[t, e], obs[t + 1, e]), (t, e)

    # The episode statistics of the chunk: each env finished exactly one 16-step episode.
    m = learn.metrics[0]
    assert m["train_episodes"] == NUM_ENVS
    assert m["train_length_mean"] == EPISODE
    first_episode_return = reward[:EPISODE].sum(axis=0).mean()
    assert math.isclose(m["train_return_mean"], first_episode_return, rel_tol=1e-4)


# --------------------------------------------------------------------------------------------
# non-finite guards
# --------------------------------------------------------------------------------------------


def test_params_finite_flag(learn):
    assert [m["params_finite"] for m in learn.metrics] == [1.0, 1.0, 1.0]
    state = learn.last_state
    nan_actor = jax.tree.map(lambda p: jnp.full_like(p, jnp.nan), state.agent.actor_params)
    state = state.replace(agent=state.agent.replace(actor_params=nan_actor))
    _, metrics = learn.chunk(state)
    assert float(metrics["params_finite"]) == 0.0


@pytest.mark.parametrize("second_write_fails", [False, True])
def test_nonfinite_run_stops_and_keeps_checkpoint(tmp_path, monkeypatch, second_write_fails):
    """Also when checkpoint 2, written in the background during the bad chunk, fails: the
    message is still the divergence, naming checkpoint 1 as the one kept and the failure."""
    cfg = TrainConfig(
        **{**TINY, "episode_length": 8},
        eval_every=32,
        total_steps=4 * 32,
        updates_per_iter=1,
        batch_size=8,
        warmup_steps=16,
    )
    per_chunk = 32
    real_make_population = programs.make_population

    def poisoned_make_population(cfg, population, **kwargs):
        program = real_make_population(cfg, population, **kwargs)

        def chunk(hp, state, iterations):  # (the host loop's chunk: its iterations)
            state, metrics = program.iterate(hp, state, iterations)
            poisoned = state.env_steps[0] > 2 * per_chunk  # from the third chunk on
            actor = jax.tree.map(
                lambda p: jnp.where(poisoned, jnp.nan, p), state.agent.actor_params
            )
            state = state.replace(agent=state.agent.replace(actor_params=actor))
            finite = jnp.stack(
                [
                    jnp.all(jnp.isfinite(x), axis=tuple(range(1, x.ndim)))
                    for x in jax.tree.leaves(state.agent)
                    if jnp.issubdtype(x.dtype, jnp.floating)
                ]
            ).all(axis=0)  # per member
            return state, {**metrics, "params_finite": finite.astype(jnp.float32)}

        return program._replace(iterate=chunk)

    monkeypatch.setattr(programs, "make_population", poisoned_make_population)
    out = tmp_path / "run"
    if second_write_fails:
        fail_writes_under(monkeypatch, out / "checkpoints" / "2")
    with pytest.raises(NonFiniteError, match=rf"env step {3 * per_chunk}\b") as info:
        train(cfg, out, progress=False)
    monkeypatch.undo()
    kept = 1 if second_write_fails else 2
    assert "parameters" in str(info.value)
    assert f"after {kept * per_chunk} env steps" in str(info.value)
    failed = f"; also, could not write checkpoint {out / 'checkpoints' / '2'}: OSError"
    assert (failed in str(info.value)) == second_write_fails

    # The two good chunks are logged and the checkpoints written are kept; the bad one is not.
    assert [r["env_steps"] for r in read_metrics(out / "metrics.jsonl")] == [32, 64]
    checkpointer = Checkpointer(out / "checkpoints", cfg.keep_checkpoints)
    try:
        assert checkpointer.latest_step() == kept
    finally:
        checkpointer.close()
    state, meta, step = restore(cfg, out)
    assert step == kept and int(state.env_steps[0]) == meta["env_steps"] == kept * per_chunk
    assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(state.agent))


def fail_writes_under(monkeypatch, prefix) -> None:
    """Every Python-level open for writing of a path starting with ``prefix`` raises EIO."""
    import builtins
    import errno
    import os

    real_open = builtins.open

    def open_(file, mode="r", *args, **kwargs):
        if str(file).startswith(str(prefix)) and any(flag in mode for flag in "wax+"):
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        return real_open(file, mode, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", open_)


# --------------------------------------------------------------------------------------------
# exploration
# --------------------------------------------------------------------------------------------


def _policy(run: CountedRun, obs: np.ndarray) -> np.ndarray:
    params = run.states[0].agent.actor_params  # no updates in EXPLORE: the actor never changes
    return np.asarray(run.trainer.agent.act(params, jnp.asarray(obs)))


def test_warmup_actions_are_uniform(explore):
    assert int(explore.states[-1].agent.step) == 0
    data = rows(ring(explore.states[1].buffer.data[0]), slice(0, 96))  # all of chunk 1: warm-up
    actions = data.action[..., 0]  # [24, 4]
    flat = np.sort(actions.ravel())
    assert flat.min() >= -1.0 and flat.max() <= 1.0
    # Kolmogorov-Smirnov distance to U(-1, 1) (1.63 / sqrt(n) is the 1% critical value).
    cdf = (flat + 1.0) / 2.0
    n = flat.size
    ks = max(np.max(np.arange(1, n + 1) / n - cdf), np.max(cdf - np.arange(n) / n))
    assert ks < 1.63 / math.sqrt(n), ks
    # Independent draws, unlike the strongly autocorrelated OU-noisy policy actions.
    lag1 = np.corrcoef(actions[:-1].ravel(), actions[1:].ravel())[0, 1]
    assert abs(lag1) < 0.3, lag1
    # Not the policy's actions plus OU noise.
    residual = actions - _policy(explore, data.obs)[..., 0]
    assert np.mean(np.abs(residual)) > 0.3


def test_ou_exploration_after_warmup_and_reset_at_episode_end(explore):
    # After chunk 2 (48 steps = 3 whole episodes) every episode has just ended: OU state reset.
    s2 = explore.states[2]
    assert int(s2.env_steps) == 2 * 96
    assert np.all(s2.env_state.steps == 0)
    assert np.all(s2.ou_state.x == 0.0)

    # After chunk 3 (72 steps) every env is 8 steps into its episode: OU state not reset.
    s3 = explore.states[3]
    assert np.all(s3.env_state.steps == 72 % EPISODE)
    assert np.all(s3.ou_state.x != 0.0)

    # Post-warm-up actions are clip(policy(obs) + OU state): the last action of chunk 3 used the
    # OU value still held in the state.
    data3 = rows(ring(s3.buffer.data[0]), slice(192, 288))  # chunk 3's transitions
    last_obs, last_action = data3.obs[-1], data3.action[-1]
    expected = np.clip(_policy(explore, last_obs) + s3.ou_state.x, -1.0, 1.0)
    np.testing.assert_allclose(last_action, expected, atol=1e-5)

    # OU noise is temporally correlated and centred on the policy.
    data2 = rows(ring(s2.buffer.data[0]), slice(96, 192))
    residual = data2.action[..., 0] - _policy(explore, data2.obs)[..., 0]
    unclipped = np.abs(data2.action[..., 0]) < 1.0
    assert unclipped.mean() > 0.5
    # The first step of each episode starts from x = 0: x_1 = sigma * eps, smaller on average
    # than the later, accumulated values.
    starts = residual[0::EPISODE][unclipped[0::EPISODE]]
    later = residual[EPISODE - 1 :: EPISODE][unclipped[EPISODE - 1 :: EPISODE]]
    assert np.mean(np.abs(starts)) < np.mean(np.abs(later))
    lag1 = np.corrcoef(residual[:-1].ravel(), residual[1:].ravel())[0, 1]
    assert lag1 > 0.5, lag1


# --------------------------------------------------------------------------------------------
# exact resume
# --------------------------------------------------------------------------------------------

RESUME = TrainConfig(
    **TINY,
    eval_every=64,
    total_steps=4 * 64,
    updates_per_iter=2,
    batch_size=16,
    warmup_steps=64,
    seed=3,
)
VOLATILE = {"wall_time_s", "env_steps_per_s", "chunk_s", "eval_s"}


def _comparable(records):
    return [json.dumps({k: v for k, v in r.items() if k not in VOLATILE}) for r in records]


@pytest.mark.runs
def test_stop_and_resume_reproduces_the_uninterrupted_run(tmp_path):
    dir_a, dir_b = tmp_path / "a", tmp_path / "b"
    full = train(RESUME, dir_a, progress=False)
    assert [r["env_steps"] for r in full] == [64, 128, 192, 256]

    first = train(RESUME, dir_b, progress=False, stop_after_chunks=2)
    assert [r["env_steps"] for r in first] == [64, 128]
    # Simulate a crash after the third evaluation was logged but before its checkpoint was
    # written: the resumed run must not keep that record twice.
    with (dir_b / "metrics.jsonl").open("a") as f:
        f.write(json.dumps({**first[-1], "env_steps": 192, "eval_return_mean": 1.0}) + "\n")
    second = train(RESUME, dir_b, resume=True, progress=False)
    assert [r["env_steps"] for r in second] == [192, 256]

    state_a, meta_a, step_a = restore(RESUME, dir_a)
    state_b, meta_b, step_b = restore(RESUME, dir_b)
    assert step_a == step_b == 4
    assert meta_a["env_steps"] == meta_b["env_steps"] == 256
    paths_a = jax.tree_util.tree_leaves_with_path(state_a)
    paths_b = jax.tree_util.tree_leaves_with_path(state_b)
    assert len(paths_a) == len(paths_b)
    for (path, a), (_, b) in zip(paths_a, paths_b, strict=True):
        a, b = np.asarray(a), np.asarray(b)
        assert a.dtype == b.dtype and a.shape == b.shape, jax.tree_util.keystr(path)
        assert np.array_equal(a, b, equal_nan=True), jax.tree_util.keystr(path)
    assert int(state_b.agent.step[0]) > 0  # the compared runs did learn something

    records_a = read_metrics(dir_a / "metrics.jsonl")
    records_b = read_metrics(dir_b / "metrics.jsonl")
    assert [r["env_steps"] for r in records_b] == [64, 128, 192, 256]
    assert _comparable(records_b) == _comparable(records_a)
    assert _comparable(first + second) == _comparable(full)
    for records in (records_a, records_b):
        assert set(records[0]) >= VOLATILE | {"eval_return_mean", "critic_loss", "updates"}
        walls = [r["wall_time_s"] for r in records]
        assert walls == sorted(walls)
    # (tau left to the algorithm is recorded as the value TD3 uses: the paper's 0.005)
    assert json.loads((dir_b / "config.json").read_text()) == dataclasses.asdict(RESUME) | {
        "hidden_sizes": list(RESUME.hidden_sizes),
        "tau": 0.005,
    }


def test_obs_stats_are_part_of_the_state(learn):
    """Normalisation statistics travel in the state (so a resume restores them)."""
    stats = learn.states[1].obs_stats
    assert isinstance(stats, RunningStats)
    assert float(stats.count) == 96.0
    data = ring(learn.states[1].buffer.data[0]).obs[:96]
    np.testing.assert_allclose(stats.mean, data.mean(axis=0), rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(stats.var, data.var(axis=0), rtol=1e-3, atol=1e-5)


def test_n_step_batches_fold_the_following_steps_of_the_same_environment(learn):
    """A 3-step trainer's batch, checked row by row against the ring it was drawn from."""
    cfg = dataclasses.replace(LEARN, n_step=3, discount=0.9)
    trainer = make_trainer(cfg)
    buffer = learn.states[2].buffer  # 192 steps written into 160 slots: wrapped once
    batch = host(jax.jit(trainer.sample)(buffer, jax.random.PRNGKey(4)))
    store, ended = host(ring(buffer.data))
    position = int(ring(buffer).position)
    # Rows in write order, oldest first: [40 steps, 4 envs].
    order = (position + np.arange(160)) % 160
    seq = jax.tree.map(lambda x: x[order].reshape(40, NUM_ENVS, *x.shape[1:]), store)
    seq_ended = ended[order].reshape(40, NUM_ENVS)
    starts = set()
    for b in range(cfg.batch_size):
        t, e = np.argwhere(np.all(seq.obs == batch.obs[b], axis=-1))[0]
        assert t <= 40 - 3, "a run must not reach past the newest step"
        starts.add((t, e))
        reward, k, bootstrap = 0.0, 0, 1.0
        for j in range(3):
            reward += 0.9**j * seq.reward[t + j, e]
            k = j
            if seq_ended[t + j, e]:
                break
        np.testing.assert_allclose(batch.reward[b], reward, rtol=1e-5)
        np.testing.assert_array_equal(batch.next_obs[b], seq.next_obs[t + k, e])
        np.testing.assert_array_equal(batch.action[b], seq.action[t, e])
        bootstrap = 0.9**k * (1.0 - seq.done[t + k, e])
        np.testing.assert_allclose(batch.done[b], 1.0 - bootstrap, rtol=1e-5)
    assert len(starts) > 8
