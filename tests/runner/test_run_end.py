"""Where a run ends: at ``--total-steps`` rounded up to a whole iteration, its last chunk the
same compiled program called with fewer iterations (no second compile); a run stopped inside
it, or extended past it by ``--resume --total-steps``, gives a straight run's numbers; and the
total_steps a resume records as changed is the one its checkpoint was trained for."""

from __future__ import annotations

import dataclasses
import json
import threading

import jax
import numpy as np
import pytest
from configs import tiny_config
from support import TINY_FLAGS, main, read_records

from td3_jax.config.build import make_population, members
from td3_jax.config.schema import TrainConfig
from td3_jax.runner import finished, rundir
from td3_jax.runner import run as run_module
from td3_jax.runner.run import chunk_calls, train

VOLATILE = {"wall_time_s", "env_steps_per_s", "chunk_s", "eval_s"}
#: What a record says of its call's iterations alone (means over them), not of the state.
CHUNK_MEANS = {"actor_loss", "critic_loss", "q_mean", "reward_mean", "target_mean",
               "chunk_updates"}  # fmt: skip


def stripped(records: list[dict], leave_out: set[str] = VOLATILE) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in leave_out} for r in records]


def assert_same_state(a_dir, b_dir) -> None:
    """The newest checkpoints of two runs hold the same train state, bit for bit."""
    cfg = rundir.load_config(b_dir)
    program = make_population(cfg, members(cfg))
    a, meta_a, _ = finished.restore_state(program, a_dir)
    b, meta_b, _ = finished.restore_state(program, b_dir)
    assert meta_a["env_steps"] == meta_b["env_steps"]
    for (path, x), y in zip(jax.tree_util.tree_leaves_with_path(a), jax.tree.leaves(b),
                            strict=True):  # fmt: skip
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), jax.tree_util.keystr(path)


@pytest.mark.parametrize(
    ("overrides", "done", "calls"),
    [
        # 100 steps of 4 envs: 25 iterations, a whole chunk of 16 and a last one of 9
        (dict(total_steps=100), 0, [(0, [16]), (1, [9])]),
        # a fresh run's first chunk of 250 iterations: an early evaluation after 31
        (dict(num_envs=16, eval_every=4000, total_steps=6000), 0, [(0, [31, 219]), (1, [125])]),
        # the same run resumed inside its last chunk, or at its end: the rest, or nothing
        (dict(num_envs=16, eval_every=4000, total_steps=6000), 300, [(1, [75])]),
        (dict(num_envs=16, eval_every=4000, total_steps=6000), 375, []),
        # extended from 6000 to 12000: the rest of the chunk it ended inside, then whole ones
        (dict(num_envs=16, eval_every=4000, total_steps=12000), 375, [(1, [125]), (2, [250])]),
        # a run shorter than its early evaluation's eighth: one call
        (dict(num_envs=16, eval_every=4000, total_steps=320), 0, [(0, [20])]),
        # an in-chunk evaluation keeps whole chunks (a round needs its chunk)
        (dict(total_steps=100, eval_in_chunk=True), 0, [(0, [16]), (1, [16])]),
    ],
)
def test_chunk_calls_end_the_run_at_its_total_steps(overrides, done, calls):
    cfg = TrainConfig(**{**dict(num_envs=4, eval_every=64, episode_length=16), **overrides})
    assert chunk_calls(cfg, done) == calls
    planned = [n for _, parts in chunk_calls(cfg, 0) for n in parts]
    assert sum(planned) == cfg.run_iterations  # every iteration of the run, once
    assert all(n > 0 for n in planned)


@pytest.mark.runs
def test_a_run_ends_at_its_total_steps_with_one_compile(tmp_path, monkeypatch):
    """25 iterations of 4 environments, not 32: records and checkpoints at 64 and 100, and
    nothing compiled while a chunk (the whole one, then the shortened one) and its evaluation
    run: the chunk's iteration count is an argument of the program compiled once."""
    compiles: list[str] = []

    def listener(event, *args, **kwargs):
        # (the main thread's: a checkpoint written in the background may compile its own)
        if threading.current_thread() is threading.main_thread():
            compiles.append(event)

    during: list[int] = []
    real = run_module._chunk_and_record

    def counted(run, compiled, state, iterations):
        before = len(compiles)
        out = real(run, compiled, state, iterations)
        during.append(len(compiles) - before)
        return out

    monkeypatch.setattr(run_module, "_chunk_and_record", counted)
    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        records = train(tiny_config(total_steps=100), tmp_path / "run", progress=False)
        jax.jit(lambda x: x * 3.0625 + 0.5)(np.float32(1.0))  # (the listener hears a compile)
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
    assert [r["env_steps"] for r in records] == [64, 100]
    assert during == [0, 0] and compiles
    assert records[-1]["chunk_updates"] == 9.0  # (every iteration past the warm-up updates once)
    assert [r["env_steps"] for r in read_records(tmp_path / "run")] == [64, 100]
    assert rundir.checkpoint_steps(tmp_path / "run") == [1, 2]


@pytest.mark.runs
def test_a_run_extended_past_its_shortened_end_equals_the_straight_run(tmp_path, capsys):
    """100 steps, then --resume --total-steps 256: the resume first runs the 7 iterations
    left of the chunk the run ended inside, then whole chunks; its state and every later
    record are the straight 256-step run's (the record at 128 averages its call's 7
    iterations where the straight run's averages 16: its evaluation is the same)."""
    short, straight = tmp_path / "short", tmp_path / "straight"
    code, out, err = main(["train", *TINY_FLAGS, "--total-steps", "100", "--out", str(short),
                           "--quiet"], capsys)  # fmt: skip
    assert code == 0, err
    assert "--total-steps 100 runs as" not in out  # (25 whole iterations)
    assert "done: 100 env steps" in out
    code, out, err = main(["train", "--resume", "--total-steps", "256", "--out", str(short),
                           "--quiet"], capsys)  # fmt: skip
    assert code == 0, err
    assert f"resuming from checkpoint {short / 'checkpoints' / '2'} (env step 100)" in out
    assert "done: 256 env steps (156 in this process" in out
    code, _, err = main(["train", *TINY_FLAGS, "--total-steps", "256", "--out", str(straight),
                         "--quiet"], capsys)  # fmt: skip
    assert code == 0, err
    extended, whole = read_records(short), read_records(straight)
    assert [r["env_steps"] for r in extended] == [64, 100, 128, 192, 256]
    assert [r["env_steps"] for r in whole] == [64, 128, 192, 256]
    assert stripped(extended[2:], VOLATILE | CHUNK_MEANS) == stripped(whole[1:],
                                                                      VOLATILE | CHUNK_MEANS)
    assert stripped(extended[3:]) == stripped(whole[2:])
    assert_same_state(short, straight)
    changes = json.loads((short / "config.json").read_text())["resume_changes"]
    assert changes == [{"at_env_steps": 100, "total_steps": [100, 256]}]


def test_extending_a_shortened_run_keeps_its_checkpoint_until_a_new_one(tmp_path, capsys,
                                                                        monkeypatch):  # fmt: skip
    """The rest of the chunk the run ended inside is not saved under the restored
    checkpoint's own number (which would delete that checkpoint first, the run's only one with
    --keep-checkpoints 1): the next checkpoint is the next whole chunk's."""
    out = tmp_path / "run"
    code, _, err = main(["train", *TINY_FLAGS, "--total-steps", "100", "--keep-checkpoints",
                         "1", "--out", str(out), "--quiet"], capsys)  # fmt: skip
    assert code == 0, err
    saved = []
    real_save = run_module.Checkpointer.save

    def recording_save(self, step, *args, **kwargs):
        saved.append(step)
        return real_save(self, step, *args, **kwargs)

    monkeypatch.setattr(run_module.Checkpointer, "save", recording_save)
    code, out_text, err = main(["train", "--resume", "--total-steps", "256", "--out", str(out),
                                "--quiet"], capsys)  # fmt: skip
    assert code == 0, err
    assert "(env step 100)" in out_text
    assert saved == [3, 4]  # not 2, the checkpoint it resumed from
    assert [r["env_steps"] for r in read_records(out)] == [64, 100, 128, 192, 256]


@pytest.mark.runs
def test_a_run_stopped_before_its_shortened_chunk_resumes_to_the_straight_run(tmp_path):
    """Stopped after its first chunk, a 100-step run resumes to the numbers of one never
    stopped; a resume asked for fewer steps than it has taken is one line."""
    cut, straight = tmp_path / "cut", tmp_path / "straight"
    cfg = tiny_config(total_steps=100)
    assert [r["env_steps"] for r in train(cfg, cut, progress=False, stop_after_chunks=1)] == [64]
    assert [r["env_steps"] for r in train(cfg, cut, resume=True, progress=False)] == [100]
    train(cfg, straight, progress=False)
    assert stripped(read_records(cut)) == stripped(read_records(straight))
    assert_same_state(cut, straight)
    from td3_jax.common.errors import ConfigError

    for fewer in (90, 60):  # (inside its last chunk, and a whole chunk before it)
        with pytest.raises(ConfigError, match=rf"^--total-steps {fewer} is less than the 100 "):
            train(tiny_config(total_steps=fewer), cut, resume=True, progress=False)


@pytest.mark.runs
def test_the_library_resumes_with_the_config_the_run_was_started_with(tmp_path):
    """``train(cfg, out, resume=True)`` with the very ``cfg`` of the fresh run: an
    ``eval_every`` the fresh run made whole iterations (66 of 4 environments: 68) is the run's
    chunk, not a change; another value is refused, and so is one the fresh run lowered to a
    shorter run (1000 in 64 steps: 64), twice alike, as the command line refuses them."""
    from td3_jax.common.errors import ConfigError

    rounded, lowered = tmp_path / "rounded", tmp_path / "lowered"
    cfg = tiny_config(total_steps=130, eval_every=66)
    assert [r["env_steps"] for r in train(cfg, rounded, progress=False,
                                          stop_after_chunks=1)] == [68]  # fmt: skip
    assert rundir.load_config(rounded).eval_every == 68
    assert [r["env_steps"] for r in train(cfg, rounded, resume=True, progress=False)] == [132]
    longer = dataclasses.replace(cfg, total_steps=200)
    for other in (64, 72):  # (other chunks, though 66 lies between them)
        with pytest.raises(ConfigError, match=rf"^--eval-every {other} given but the run was "
                                              r"started with --eval-every 68: "):  # fmt: skip
            train(dataclasses.replace(longer, eval_every=other), rounded, resume=True,
                  progress=False)  # fmt: skip
    short = tiny_config(total_steps=64, eval_every=1000)
    assert [r["env_steps"] for r in train(short, lowered, progress=False)] == [64]
    assert rundir.load_config(lowered).eval_every == 64
    for total in (128, 192):
        with pytest.raises(ConfigError, match=r"^--eval-every 1000 given but the run was "
                                              r"started with --eval-every 64: "):  # fmt: skip
            train(dataclasses.replace(short, total_steps=total), lowered, resume=True,
                  progress=False)  # fmt: skip
    extended = dataclasses.replace(short, total_steps=128, eval_every=64)
    assert [r["env_steps"] for r in train(extended, lowered, resume=True, progress=False)] == [128]


def test_the_library_warns_that_a_resumed_run_is_complete_and_writes_nothing(tmp_path):
    """A resume of a complete run trains nothing and returns no record, as the command line
    does, and says so with a warning in Python's words at the caller's line."""
    from td3_jax.runner.run import RunCompleteWarning

    cfg, out = tiny_config(total_steps=64, eval_every=64), tmp_path / "done"
    assert [r["env_steps"] for r in train(cfg, out, progress=False)] == [64]
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file() and p.name != ".lock"}
    with pytest.warns(RunCompleteWarning) as said:
        assert train(cfg, out, resume=True, progress=False) == []
    assert [str(w.message) for w in said] == [
        f"nothing to do: the run in {out} is complete (64 env steps); resume=True with "
        "total_steps=128 goes on to 128"]  # fmt: skip
    assert said[0].filename == __file__  # (where the caller called train)
    after = {p: p.read_bytes() for p in out.rglob("*") if p.is_file() and p.name != ".lock"}
    assert after == before


@pytest.mark.parametrize("python", [False, True])
def test_nothing_to_do_says_how_to_go_on_in_the_callers_words(tmp_path, python):
    """Complete: resume to twice the steps; complete with a cosine schedule: a new run; set for
    more than a shorter resume asked (stopped at 128 of 256): resume to the steps it was set
    for. The command line's words, or a Python caller's."""
    out, cfg = tmp_path / "run", tiny_config(total_steps=128)
    out.mkdir()
    rundir.save_config(cfg, members(cfg), out)
    resume = "resume=True with total_steps=256" if python else (
        f"td3-jax train --out {out} --resume --total-steps 256")  # fmt: skip
    assert rundir.nothing_to_do(out, cfg, python=python) == (
        f"nothing to do: the run in {out} is complete (128 env steps); {resume} goes on to 256")
    cosine = dataclasses.replace(cfg, lr_schedule="cosine")
    steps = "total_steps" if python else "--total-steps"
    assert rundir.nothing_to_do(out, cosine, python=python).endswith(
        f"complete (128 env steps); its cosine learning-rate schedule fixed its length: start a "
        f"new run with a larger {steps} to train longer")  # fmt: skip
    rundir.save_config(dataclasses.replace(cfg, total_steps=256), members(cfg), out)
    asked = "total_steps=128" if python else "--total-steps 128"
    resume = "resume=True with total_steps=256" if python else f"td3-jax train --out {out} --resume"
    assert rundir.nothing_to_do(out, cfg, python=python) == (
        f"nothing to do: the run in {out} has taken 128 env steps, what {asked} asks; it was "
        f"set for 256: {resume} goes on to them")  # fmt: skip


@pytest.mark.runs
def test_resume_changes_record_the_total_steps_the_run_was_trained_for(tmp_path, capsys):
    """A config.json whose total_steps was edited by hand (128 to 192) is not the run's: the
    resume records the 128 its checkpoint was written under as the value it changed."""
    out = tmp_path / "run"
    code, _, err = main(["train", *TINY_FLAGS, "--out", str(out), "--quiet"], capsys)
    assert code == 0, err
    config = json.loads((out / "config.json").read_text())
    (out / "config.json").write_text(json.dumps({**config, "total_steps": 192}, indent=2))
    code, _, err = main(["train", "--resume", "--total-steps", "256", "--out", str(out),
                         "--quiet"], capsys)  # fmt: skip
    assert code == 0, err
    changes = json.loads((out / "config.json").read_text())["resume_changes"]
    assert changes == [{"at_env_steps": 128, "total_steps": [128, 256]}]
