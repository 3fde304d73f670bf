"""``td3-jax render``: rollout videos of a run's policy (td3_jax.tools.render).

The MuJoCo run is made by hand (config.json, members.json and a checkpoint of a fresh train
state, as a run writes after its first chunk) so that no training chunk compiles: MJX programs
take tens of seconds to compile on a CPU. Compiles: the init, ``evaluate_run``'s evaluation and
the render's recorded evaluation, on brax/inverted_pendulum (plus cheap gymnax ones).
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import os
import re
import tracemalloc
from pathlib import Path

import imageio.v2 as imageio
import jax
import numpy as np
import pytest
from support import assert_one_line_error, main

from td3_jax.cli import app as cli
from td3_jax.common import errors, upstream
from td3_jax.config.build import make_population, members
from td3_jax.config.schema import TrainConfig
from td3_jax.runner import finished, rundir
from td3_jax.runner.checkpoint import Checkpointer
from td3_jax.tools import export, render

EPISODE = 30  # time limit of the tiny runs
WIDTH, HEIGHT = 64, 48
SEED = 4321

TINY = dict(num_envs=2, total_steps=64, eval_every=64, warmup_steps=32, batch_size=8,
            updates_per_iter=1, hidden_sizes=(8, 8), eval_envs=2, episode_length=EPISODE,
            buffer_size=128, seed=3)  # fmt: skip


def make_run(out: Path, env: str, **overrides) -> Path:
    """A run directory holding one checkpoint of a freshly initialised train state."""
    cfg = TrainConfig(env=env, **{**TINY, **overrides})
    population = members(cfg)
    out.mkdir(parents=True)
    rundir.save_config(cfg, population, out)
    state = jax.jit(make_population(cfg, population).init)()
    checkpointer = Checkpointer(out / rundir.CHECKPOINTS, cfg.keep_checkpoints)
    checkpointer.save(1, state, {"env_steps": 0})
    checkpointer.close()
    return out


@pytest.fixture(scope="module")
def mujoco_run(tmp_path_factory):
    require_gl()
    return make_run(tmp_path_factory.mktemp("render") / "run", "brax/inverted_pendulum")


def require_gl() -> None:
    """Skips the MuJoCo rendering tests on a machine without headless OpenGL, unless
    ``TD3_JAX_REQUIRE_GL=1`` (CI sets it once it has the libraries: there they must run)."""
    try:
        render.default_gl_backend()
    except render.GLUnavailableError as err:
        if os.environ.get("TD3_JAX_REQUIRE_GL") == "1":
            raise
        pytest.skip(f"no headless OpenGL here: {err}")


@pytest.fixture(scope="module")
def rendered(mujoco_run):
    """``td3-jax render`` of two episodes into an MP4, with its printed lines."""
    out = mujoco_run / "two.mp4"
    args = ["render", "--run", str(mujoco_run), "--out", str(out), "--episodes", "2",
            "--seed", str(SEED), "--width", str(WIDTH), "--height", str(HEIGHT)]  # fmt: skip
    with contextlib.redirect_stdout(io.StringIO()) as stdout:
        cli.main(args)
    return out, stdout.getvalue().splitlines()


@pytest.mark.mjx
def test_rendered_video_matches_the_evaluation(mujoco_run, rendered):
    out, lines = rendered
    assert lines[0] == str(out)
    assert lines[-1] == "(the policy of the checkpoint at 0 env steps)"  # make_run's meta
    frames = np.asarray(imageio.mimread(out, memtest=False))
    assert frames.shape[1:] == (HEIGHT, WIDTH, 3)
    # inverted_pendulum pays 1 per step until the pole passes 0.2 rad (termination) or the
    # time limit: the evaluation's returns are the episodes' lengths, hence the frame counts.
    _, _, _, returns = finished.evaluate_run(mujoco_run, 2, SEED)
    lengths = [int(r) for r in returns[0]]
    np.testing.assert_array_equal(returns[0], lengths)
    assert all(1 <= n <= EPISODE for n in lengths)
    assert len(frames) == sum(lengths)
    for e, n in enumerate(lengths):
        assert lines[1 + e] == f"member 0 episode {e + 1}: {n} frames, return {returns[0][e]:.2f}"
    # The pole moves: consecutive frames of an episode differ, and the scene is not blank.
    first = frames[: lengths[0]].astype(np.int16)
    assert lengths[0] >= 2 and np.abs(np.diff(first, axis=0)).max() > 30
    assert frames.std() > 5


@pytest.mark.mjx
def test_bad_camera_exits_2_before_compiling(mujoco_run, capsys):
    code, _, err = main(["render", "--run", str(mujoco_run), "--camera", "nope"], capsys)
    assert_one_line_error(code, err, "--camera nope", "-1: the free camera")


@pytest.mark.mjx
def test_no_opengl_exits_2_with_what_to_install(mujoco_run, capsys, monkeypatch):
    def unavailable():
        return render.gl_backend({}, probe=lambda backend: "no display")

    monkeypatch.setattr(render, "default_gl_backend", unavailable)
    code, _, err = main(["render", "--run", str(mujoco_run)], capsys)
    assert_one_line_error(code, err, "egl: no display", "osmesa: no display", "libosmesa6")
    assert not (mujoco_run / "rollout.mp4").exists()


def test_gl_backend_choice():
    tried = []

    def probe(backend):
        tried.append(backend)
        return None if backend == "osmesa" else "EGL not found"

    assert render.gl_backend({}, probe=probe) == "osmesa" and tried == ["egl", "osmesa"]
    tried.clear()  # a forced backend is probed too, and its failure is one error
    assert render.gl_backend({"MUJOCO_GL": "OSMesa"}, probe=probe) == "osmesa"
    with pytest.raises(render.GLUnavailableError, match="MUJOCO_GL=egl cannot render here"):
        render.gl_backend({"MUJOCO_GL": "EGL"}, probe=probe)
    assert tried == ["osmesa", "egl"]
    tried.clear()  # PyOpenGL loads only PYOPENGL_PLATFORM's library: only that one is tried
    assert render.gl_backend({"PYOPENGL_PLATFORM": "osmesa"}, probe=probe) == "osmesa"
    assert tried == ["osmesa"]
    with pytest.raises(render.GLUnavailableError) as err:
        render.gl_backend({}, probe=lambda backend: f"{backend} missing")
    message = str(err.value)
    assert "\n" not in message
    for needle in ("egl: egl missing", "osmesa: osmesa missing", "libegl1", "libosmesa6",
                   "PyOpenGL", "MUJOCO_GL"):  # fmt: skip
        assert needle in message, needle
    with pytest.raises(render.GLUnavailableError, match="MUJOCO_GL=wgl is not one of"):
        render.gl_backend({"MUJOCO_GL": "wgl"})


def test_default_member_is_the_best_at_the_checkpoints_evaluation(tmp_path):
    record = lambda steps, *r: {"env_steps": steps,
                                "per_member": [{"eval_return_mean": x} for x in r]}  # fmt: skip
    lines = [record(100, 1.0, 9.0, 3.0), record(200, 5.0, 2.0, None)]
    (tmp_path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lines))
    assert render.choose_member(tmp_path, 3, None, 100) == 1  # the checkpoint's evaluation
    assert render.choose_member(tmp_path, 3, None, 200) == 0
    assert render.choose_member(tmp_path, 3, None, 999) == 0  # none at those steps: the last
    assert render.choose_member(tmp_path, 3, 2, 100) == 2  # asked for
    assert render.choose_member(tmp_path, 1, None, 100) == 0  # one member
    assert render.choose_member(tmp_path / "none", 4, None, 100) == 0  # no metrics.jsonl


def test_pendulum_gif_has_one_frame_per_step(tmp_path):
    # gymnax's Pendulum never terminates: every episode runs to the time limit.
    run = make_run(tmp_path / "pendulum", "gymnax/Pendulum-v1", episode_length=12)
    result = render.render_run(run, run / "p.gif", episodes=2, seed=SEED, width=32, height=32)
    frames = np.asarray(imageio.mimread(run / "p.gif"))
    assert result.lengths == [12, 12] and frames.shape == (24, 32, 32, 3)
    _, _, _, returns = finished.evaluate_run(run, 2, SEED)
    np.testing.assert_allclose(result.returns, returns[0], rtol=1e-6)
    assert np.abs(np.diff(frames.astype(np.int16), axis=0)).max() > 30


def test_eval_and_render_compile_with_the_runs_compile_options(tmp_path, monkeypatch):
    """A finished run's evaluation (``td3-jax eval``) and recorded rollout (``render``) are
    compiled with the options its training programs get (:func:`upstream.compile_options` of
    its ``--matmuls`` on this platform): an option the compiler does not know, given for
    ``cublas``, fails both."""
    run = make_run(tmp_path / "run", "gymnax/Pendulum-v1", episode_length=12, matmuls="cublas")
    asked = []

    def options(platform, matmuls="auto", xla_flags=None):
        asked.append((platform, matmuls))
        return {"xla_no_such_option": True} if matmuls == "cublas" else {}

    monkeypatch.setattr(upstream, "compile_options", options)
    with pytest.raises(jax.errors.JaxRuntimeError, match="xla_no_such_option"):
        finished.evaluate_run(run, 2, SEED)
    with pytest.raises(jax.errors.JaxRuntimeError, match="xla_no_such_option"):
        render.rollout(run, episodes=1, seed=SEED)
    assert asked == [(jax.devices()[0].platform, "cublas")] * 2


def test_pendulum_drawing_points_at_the_angle():
    up, right = render.draw_pendulum(0.0, 40, 40), render.draw_pendulum(np.pi / 2, 40, 40)
    red = lambda image: np.argwhere((image[..., 0] > 150) & (image[..., 1] < 120))
    assert red(up)[:, 0].min() < 10 and np.ptp(red(up)[:, 1]) <= 4  # a vertical rod, upwards
    assert red(right)[:, 1].max() > 30 and np.ptp(red(right)[:, 0]) <= 4  # horizontal, rightwards


def test_errors_exit_2(tmp_path, capsys):
    code, _, err = main(["render", "--run", str(tmp_path)], capsys)
    assert_one_line_error(code, err, "not a td3-jax run directory")
    cfg = TrainConfig(env="gymnax/MountainCarContinuous-v0", **TINY)
    (tmp_path / "car").mkdir()
    (tmp_path / "empty").mkdir()
    rundir.save_config(cfg, members(cfg), tmp_path / "car")
    code, _, err = main(["render", "--run", str(tmp_path / "car")], capsys)
    assert_one_line_error(code, err, "gymnax/MountainCarContinuous-v0 cannot be rendered")
    pendulum = dataclasses.replace(cfg, env="gymnax/Pendulum-v1")
    rundir.save_config(pendulum, members(pendulum), tmp_path / "empty")
    code, _, err = main(["render", "--run", str(tmp_path / "empty")], capsys)
    assert_one_line_error(code, err, "no checkpoint")
    for flags, needle in ((["--out", "x.avi"], "must end in .mp4 or .gif"),
                          (["--gif", "--out", "x.mp4"], "ends in .gif"),
                          (["--episodes", "0"], "--episodes must be positive"),
                          (["--width", "100000"], "--width 100000 is more than the 8192 pixels"),
                          (["--height", "8193"], "--height 8193 is more than the 8192 pixels"),
                          (["--member", "3"], "--member 3 is out of range")):  # fmt: skip
        code, _, err = main(["render", "--run", str(tmp_path / "empty"), *flags], capsys)
        assert_one_line_error(code, err, needle)


@pytest.mark.parametrize(("seeds", "member", "said"), [
    (1, 3, "--member 3 is out of range: the run has 1 member (0)"),
    (1, -1, "--member -1 is out of range: the run has 1 member (0)"),
    (3, 3, "--member 3 is out of range: the run has 3 members (0 to 2)"),
    (3, -2, "--member -2 is out of range: the run has 3 members (0 to 2)"),
])  # fmt: skip
def test_export_and_render_say_a_member_out_of_range_alike(tmp_path, capsys, seeds, member, said):
    """One line, the same for both commands (a negative --member too), exit code 2, before
    anything is restored: the run directory holds config.json and members.json alone; each
    command keeps its own error class."""
    cfg = TrainConfig(env="gymnax/Pendulum-v1", **{**TINY, "seeds": seeds})
    rundir.save_config(cfg, members(cfg), tmp_path)
    for command in (["export", "--format", "npz"], ["render"]):
        code, _, err = main([*command, "--run", str(tmp_path), f"--member={member}"], capsys)
        assert_one_line_error(code, err)
        assert err.strip() == f"td3-jax: error: {said}", command
    with pytest.raises(export.ExportError, match=re.escape(said)):
        export.choose_member(member, seeds, [], 0)
    with pytest.raises(errors.RenderError, match=re.escape(said)) as caught:
        render.choose_member(tmp_path, seeds, member)
    assert not isinstance(caught.value, errors.ExportError)


def test_a_video_that_cannot_be_written_is_refused_before_the_rollout(tmp_path):
    """``check_destination`` writes for real (root passes permission checks; /proc does not
    take files) and leaves nothing behind; a missing folder is made; and ffmpeg, which only
    prints why it wrote nothing, is caught by :func:`render.write_video` itself."""
    with pytest.raises(render.RenderError, match="is a directory"):
        render.check_destination(tmp_path)
    (tmp_path / "file").write_text("")
    with pytest.raises(render.RenderError, match="file is a file, not a folder"):
        render.check_destination(tmp_path / "file" / "deeper" / "v.mp4")
    if Path("/proc/self").is_dir():
        with pytest.raises(render.RenderError, match="cannot write it"):
            render.check_destination(Path("/proc/v.mp4"))
        with pytest.raises(OSError, match="ffmpeg wrote nothing"):
            render.write_video(Path("/proc/v.mp4"), np.zeros((2, 8, 8, 3), np.uint8), 10.0)
    (tmp_path / "kept.gif").write_bytes(b"GIF89a")  # (a file of the user's: never replaced)
    with pytest.raises(render.RenderError, match=r"kept\.gif exists: remove it or choose another"):
        render.check_destination(tmp_path / "kept.gif")
    assert (tmp_path / "kept.gif").read_bytes() == b"GIF89a"
    assert render.check_destination(tmp_path / "kept.gif", replace=True) == []  # (a run's own)
    assert render.check_destination(tmp_path / "new" / "v.mp4") == [tmp_path / "new"]
    assert (tmp_path / "new").is_dir() and not (tmp_path / "new" / "v.mp4").exists()
    made = render.check_destination(tmp_path / "a" / "b" / "v.mp4")
    assert made == [tmp_path / "a", tmp_path / "a" / "b"]
    render._remove_folders(made)  # (as render_run does when the rollout fails)
    assert not (tmp_path / "a").exists()
    video = render.write_video(tmp_path / "new" / "v.mp4", np.zeros((2, 8, 8, 3), np.uint8), 10.0)
    assert video.stat().st_size > 0


# --------------------------------------------------------------------------------------------
# memory: frames drawn as the writer takes them
# --------------------------------------------------------------------------------------------

BIG_W, BIG_H = 160, 120  # 57,600 bytes a frame


@pytest.fixture(scope="module")
def pendulum():
    from td3_jax import envs

    return envs.make("gymnax/Pendulum-v1")


def pendulum_rollout(env, episodes: int, length: int = 30) -> render.Rollout:
    """A :class:`render.Rollout` made by hand (nothing compiles): ``episodes`` episodes of
    ``length`` steps, the angle sweeping and a reward of -1 a step."""
    positions = [(np.linspace(0.0, 6.0, length) + e)[:, None] for e in range(episodes)]
    rewards = [np.full(length, -1.0, np.float32) for _ in range(episodes)]
    return render.Rollout(env, 0, np.full(episodes, -float(length)), positions, rewards)


def peak_bytes_writing(path: Path, rollout_: render.Rollout) -> int:
    """The peak of Python's traced allocations (numpy's arrays among them) while the rollout's
    frames are drawn and written to ``path``, above what was allocated before."""
    tracemalloc.start()
    try:
        frames = render.frame_stream(rollout_, width=BIG_W, height=BIG_H)
        render.write_video(path, frames, 30.0)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_an_mp4_is_written_frame_by_frame_in_memory_that_does_not_grow_with_episodes(
    tmp_path, pendulum
):
    """render drew every frame into one array, then copied them all into one more before
    ffmpeg got the first: --episodes 40 on Pendulum peaked at 4.1 GB. Streamed, 20 episodes
    (600 frames, 34.6 MB if held) peak as 2 episodes do: a few frames' worth."""
    frame = BIG_W * BIG_H * 3
    few = peak_bytes_writing(tmp_path / "few.mp4", pendulum_rollout(pendulum, 2))
    many = peak_bytes_writing(tmp_path / "many.mp4", pendulum_rollout(pendulum, 20))
    assert many < 12 * frame and many < 1.5 * few + 2 * frame, (few, many)
    with render._forking():  # (ffmpeg reads it back)
        assert len(imageio.mimread(tmp_path / "many.mp4", memtest=False)) == 600  # every frame


def test_a_streamed_gif_is_the_gif_of_the_frames_held_at_once(tmp_path, pendulum):
    """Drawing frames as the writer takes them changes nothing in the file: the GIF written
    from :func:`render.frame_stream` is byte for byte the one written from every frame held
    (:func:`render.rollout_frames`), and it has each episode's frames in order."""
    rollout_ = pendulum_rollout(pendulum, 3, length=8)
    held = np.concatenate(render.rollout_frames(rollout_, width=32, height=24))
    render.write_video(tmp_path / "held.gif", held, 10.0)
    render.write_video(tmp_path / "streamed.gif",
                       render.frame_stream(rollout_, width=32, height=24), 10.0)  # fmt: skip
    assert (tmp_path / "streamed.gif").read_bytes() == (tmp_path / "held.gif").read_bytes()
    assert held.shape == (24, 24, 32, 3)
    first = render.label(render.draw_pendulum(0.0, 32, 24), "ep 1  return -1.0")
    np.testing.assert_array_equal(held[0], first)


def test_a_gif_that_would_not_fit_in_memory_is_refused_before_a_frame_is_drawn(
    tmp_path, capsys, monkeypatch
):
    """A GIF's encoder holds every frame (about 6 bytes a pixel): 2 episodes of 12 frames of
    32x32 need 147,456 bytes; with less available the render stops in one line, having drawn
    nothing and written nothing; an MP4 of the same is written (frame by frame)."""
    need = 2 * 12 * 32 * 32 * render.GIF_BYTES_PER_PIXEL
    render.check_gif_memory(24, 32, 32, available=need)  # fits exactly
    with pytest.raises(render.RenderError, match=r"^a GIF of 24 frames of 32x32 needs about "
                       r"0\.1 MB of memory .* and 0\.1 MB is available: write an MP4"):  # fmt: skip
        render.check_gif_memory(24, 32, 32, available=need - 1)
    run = make_run(tmp_path / "pendulum", "gymnax/Pendulum-v1", episode_length=12)
    drawn = []
    real_draw = render.draw_pendulum
    monkeypatch.setattr(render, "draw_pendulum", lambda *a: drawn.append(a) or real_draw(*a))
    monkeypatch.setattr(render, "available_memory", lambda: need - 1)
    flags = ["--episodes", "2", "--width", "32", "--height", "32"]
    code, _, err = main(["render", "--run", str(run), "--gif", *flags], capsys)
    assert_one_line_error(code, err, "a GIF of 24 frames of 32x32 needs about", "--episodes")
    assert drawn == [] and not (run / "rollout.gif").exists()
    code, _, err = main(["render", "--run", str(run), *flags], capsys)
    assert code == 0, err
    with render._forking():  # (ffmpeg reads it back)
        assert len(drawn) == 24 and len(imageio.mimread(run / "rollout.mp4")) == 24
