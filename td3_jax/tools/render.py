"""Rollout videos of a run's deterministic policy (``td3-jax render``).

* **The episodes are the evaluation's.** :func:`rollout` restores a run's newest checkpoint (as
  :func:`td3_jax.runner.finished.evaluate_run` does) and runs
  :func:`td3_jax.core.training.evaluate_recorded`: the evaluation's own step, which also emits each
  step's joint positions (``qpos``), reward and whether the step counts. Member ``k`` uses the
  ``k``-th key of ``jax.random.split(PRNGKey(seed), members)``, so the returns are those of
  ``td3-jax eval --run DIR --episodes N --seed S`` (tested for a single-seed run).
* **Which member.** ``member=None`` picks the member with the highest return in the last
  evaluation record of ``metrics.jsonl`` (diverged members, whose returns are null, never);
  a single-seed run has only member 0.
* **Frames are drawn on the host** from the recorded positions, up to each episode's end (a
  termination or the time limit): MuJoCo scenes (Brax and Playground environments) with
  MuJoCo's own renderer (``mjv_updateScene`` + ``mjr_render`` on an offscreen OpenGL context),
  gymnax's Pendulum as a 2-D drawing (Pillow, no OpenGL). Every frame is labelled with its
  episode and the return so far.
* **Headless OpenGL** (:func:`gl_backend`): ``MUJOCO_GL`` when set (``egl``, ``osmesa`` or
  ``glfw``), else the first of ``egl`` and ``osmesa`` whose context can be created, probed in a
  fresh Python each (PyOpenGL fixes its platform once per process, so the probes cannot share
  one). ``mujoco.Renderer`` takes its backend from ``MUJOCO_GL`` at ``import mujoco`` (which
  Brax has done long before), so the context is made here from the chosen backend's
  ``mujoco.egl`` / ``mujoco.osmesa`` module and MuJoCo's renderer is driven directly.
* **Writing** (:func:`write_video`): MP4 (H.264 through imageio-ffmpeg, whose wheel holds the
  ffmpeg binary) or GIF (Pillow).
* **Bounded memory.** Frames are drawn as the writer takes them (:func:`frame_stream`): an MP4
  holds one frame at a time whatever ``--episodes``. A GIF's encoder (Pillow) holds every frame
  until it writes the file, so a GIF that would not fit in the memory available now is refused
  in one line once the rollout's length is known, before any frame is drawn
  (:func:`check_gif_memory`).
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import functools
import importlib
import importlib.util
import os
import subprocess
import sys
import warnings
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np

from td3_jax import envs
from td3_jax.common.errors import GLUnavailableError, NotRenderableError, RenderError
from td3_jax.core import training
from td3_jax.runner.logger import probe_write
from td3_jax.runner.memory import available_memory

#: Headless OpenGL backends tried, in order, when ``MUJOCO_GL`` is not set.
GL_BACKENDS = ("egl", "osmesa")
#: The backends ``MUJOCO_GL`` may name (each a ``mujoco.<name>`` module with a ``GLContext``).
KNOWN_GL = ("egl", "osmesa", "glfw")
GL_HELP = (
    "install EGL (Debian/Ubuntu: apt-get install libegl1 libegl-mesa0 libgl1, with Mesa's or "
    "the GPU driver's libEGL) or OSMesa (apt-get install libosmesa6), and PyOpenGL (pip "
    "install PyOpenGL), or set MUJOCO_GL to a backend that works here"
)
VIDEO_SUFFIXES = (".mp4", ".gif")


# ---------------------------------------------------------------------------------------------
# Headless OpenGL
# ---------------------------------------------------------------------------------------------

_PROBE = """
import importlib, sys
import mujoco
context = importlib.import_module("mujoco." + sys.argv[1]).GLContext(8, 8)
context.make_current()
model = mujoco.MjModel.from_xml_string("<mujoco/>")
mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100.value).free()
context.free()
"""


@contextlib.contextmanager
def _forking() -> Iterator[None]:
    """Silences JAX's warning about ``os.fork`` for a subprocess that execs at once (the GL
    probe, ffmpeg), which cannot deadlock on JAX's threads."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "os.fork", RuntimeWarning)
        yield


def probe_gl(backend: str, timeout_s: float = 120.0) -> str | None:
    """``None`` when an offscreen OpenGL context of ``backend`` works in a fresh Python, else
    the last line of its error."""
    env = {**os.environ, "MUJOCO_GL": backend}  # (PYOPENGL_PLATFORM kept: this process has it)
    try:
        with _forking():
            proc = subprocess.run([sys.executable, "-c", _PROBE, backend], env=env,
                                  capture_output=True, text=True, timeout=timeout_s)  # fmt: skip
    except subprocess.TimeoutExpired:
        return f"no context after {timeout_s:.0f} s"
    if proc.returncode == 0:
        return None
    lines = [line.strip() for line in proc.stderr.splitlines() if line.strip()]
    return (lines[-1] if lines else f"exit code {proc.returncode}")[:160]


def gl_backend(environ: dict | None = None, probe: Any = probe_gl) -> str:
    """The OpenGL backend to render with: ``MUJOCO_GL`` when set (and probed), else the first of
    :data:`GL_BACKENDS` for which ``probe(backend)`` (error text or ``None``) succeeds; only
    ``PYOPENGL_PLATFORM``'s backend when that names one (PyOpenGL then loads no other).

    Raises :class:`GLUnavailableError` naming what to install when none works.
    """
    environ = os.environ if environ is None else environ
    given = environ.get("MUJOCO_GL", "").strip().lower()
    if given:
        if given not in KNOWN_GL:
            raise GLUnavailableError(f"MUJOCO_GL={given} is not one of {', '.join(KNOWN_GL)}")
        why = probe(given)
        if why is not None:
            raise GLUnavailableError(f"MUJOCO_GL={given} cannot render here ({why}); {GL_HELP}")
        return given
    platform = environ.get("PYOPENGL_PLATFORM", "").strip().lower()
    failures = []
    for backend in (platform,) if platform in GL_BACKENDS else GL_BACKENDS:
        why = probe(backend)
        if why is None:
            return backend
        failures.append(f"{backend}: {why}")
    raise GLUnavailableError(f"no headless OpenGL for rendering ({'; '.join(failures)}); {GL_HELP}")


@functools.cache
def default_gl_backend() -> str:
    """:func:`gl_backend` of this process's environment, probed once per process."""
    return gl_backend()


def gl_context(backend: str, width: int, height: int) -> Any:
    """A current offscreen OpenGL context of ``backend`` (free it with ``.free()``)."""
    try:
        context = importlib.import_module(f"mujoco.{backend}").GLContext(width, height)
        context.make_current()
    except Exception as err:  # ImportError, OSError, PyOpenGL and EGL errors alike
        raise GLUnavailableError(
            f"cannot create an OpenGL context with MUJOCO_GL={backend} "
            f"({type(err).__name__}: {str(err)[:160]}); {GL_HELP}"
        ) from err
    return context


# ---------------------------------------------------------------------------------------------
# Drawing frames
# ---------------------------------------------------------------------------------------------


def camera_id(model: Any, camera: str | None) -> int | None:
    """The camera ``camera`` names in ``model``: ``None`` (a free camera tracking the root
    body), ``-1`` (MuJoCo's free camera) or a fixed camera's index, given by name or index.

    Raises :class:`RenderError` naming the model's cameras for one it does not have.
    """
    import mujoco

    if camera is None:
        return None
    names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_CAMERA, i) or str(i)
             for i in range(model.ncam)]  # fmt: skip
    text = camera.strip()
    index = int(text) if text.lstrip("-").isdigit() else None
    if index is None:
        index = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, text)
        index = None if index < 0 else index
    if index is None or not -1 <= index < model.ncam:
        listing = ", ".join(f"{i}: {n}" for i, n in enumerate(names)) or "none"
        raise RenderError(f"--camera {camera}: not a camera of this model (-1: the free "
                          f"camera; the model's cameras: {listing})")  # fmt: skip
    return index


def _camera(model: Any, index: int | None, qpos: np.ndarray | None = None) -> Any:
    """An ``MjvCamera`` for :func:`camera_id`'s ``index``; the default tracking camera stands
    three robot radii (:func:`robot_radius` at ``qpos``) from the robot, nearer than MuJoCo's
    default free camera when the model's extent is set by a large floor."""
    import mujoco

    camera = mujoco.MjvCamera()
    if index is not None and index >= 0:
        camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        camera.fixedcamid = index
        return camera
    mujoco.mjv_defaultFreeCamera(model, camera)
    if index is None and model.nbody > 1:
        camera.type = mujoco.mjtCamera.mjCAMERA_TRACKING
        camera.trackbodyid = 1
        radius = robot_radius(model, qpos) if qpos is not None else None
        if radius:
            camera.distance = min(camera.distance, 3.0 * radius)
    return camera


def robot_radius(model: Any, qpos: np.ndarray) -> float | None:
    """The radius around body 1's subtree centre of mass that holds the bounding spheres of
    every geom of body 1's tree at ``qpos [nq]`` (``None`` when that tree has no geom)."""
    import mujoco

    root = model.body_rootid[1]
    robot = model.body_rootid[model.geom_bodyid] == root
    if not robot.any():
        return None
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_forward(model, data)
    offsets = np.linalg.norm(data.geom_xpos[robot] - data.subtree_com[root], axis=1)
    return float(np.max(offsets + model.geom_rbound[robot]))


def _with_buffer(model: Any, width: int, height: int) -> Any:
    """``model``, copied with an offscreen buffer of at least ``width x height`` if smaller."""
    size = model.vis.global_
    if size.offwidth >= width and size.offheight >= height:
        return model
    model = copy.deepcopy(model)
    model.vis.global_.offwidth = max(width, size.offwidth)
    model.vis.global_.offheight = max(height, size.offheight)
    return model


def _draw_scene(model: Any, camera_index: int | None, positions: np.ndarray,
                width: int, height: int) -> Iterator[np.ndarray]:  # fmt: skip
    """``[height, width, 3]`` uint8 frames of ``positions [n, nq]``, one per row, each drawn as
    it is taken (a GL context is current while they are)."""
    import mujoco

    data, scene = mujoco.MjData(model), mujoco.MjvScene(model, maxgeom=10_000)
    context = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_150.value)
    camera = _camera(model, camera_index, positions[0] if len(positions) else None)
    option, perturb = mujoco.MjvOption(), mujoco.MjvPerturb()
    viewport = mujoco.MjrRect(0, 0, width, height)
    try:
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, context)
        for qpos in positions:
            data.qpos[:] = qpos
            mujoco.mj_forward(model, data)
            mujoco.mjv_updateScene(model, data, option, perturb, camera,
                                   mujoco.mjtCatBit.mjCAT_ALL.value, scene)  # fmt: skip
            mujoco.mjr_render(viewport, scene, context)
            frame = np.empty((height, width, 3), np.uint8)
            mujoco.mjr_readPixels(frame, None, viewport, context)
            yield frame[::-1]  # OpenGL's rows run bottom-up
    finally:
        context.free()


def scene_frames(
    model: Any,
    positions: np.ndarray,
    *,
    camera: str | None = None,
    width: int = 320,
    height: int = 240,
    backend: str | None = None,
) -> Iterator[np.ndarray]:
    """``[height, width, 3]`` uint8 frames of MuJoCo ``model`` at each row of ``positions [n,
    nq]`` (``qpos``), seen by ``camera`` (:func:`camera_id`), on ``backend`` (default
    :func:`default_gl_backend`), drawn one at a time as they are taken (the OpenGL context
    lives until the last one is taken or the iterator is closed)."""
    model = _with_buffer(model, width, height)
    index = camera_id(model, camera)
    context = gl_context(backend or default_gl_backend(), width, height)
    try:
        with contextlib.closing(_draw_scene(model, index, np.asarray(positions, np.float64),
                                            width, height)) as frames:  # fmt: skip
            yield from frames
    finally:
        context.free()


def render_positions(
    model: Any,
    positions: np.ndarray,
    *,
    camera: str | None = None,
    width: int = 320,
    height: int = 240,
    backend: str | None = None,
) -> np.ndarray:
    """``[n, height, width, 3]`` uint8: :func:`scene_frames`, all held at once."""
    frames = list(scene_frames(model, positions, camera=camera, width=width, height=height,
                               backend=backend))  # fmt: skip
    return np.stack(frames) if frames else np.empty((0, height, width, 3), np.uint8)


def draw_pendulum(angle: float, width: int, height: int) -> np.ndarray:
    """``[height, width, 3]`` uint8: a pendulum at ``angle`` (radians, 0 upright, as gymnax's
    Pendulum), drawn from the centre."""
    from PIL import Image, ImageDraw

    image = Image.new("RGB", (width, height), (245, 245, 245))
    draw = ImageDraw.Draw(image)
    cx, cy, length = width / 2, height / 2, 0.4 * min(width, height)
    tip = (cx + length * np.sin(angle), cy - length * np.cos(angle))
    draw.line([(cx, cy), tip], fill=(200, 60, 40), width=max(2, min(width, height) // 24))
    r = max(2, min(width, height) // 40)
    draw.ellipse([cx - r, cy - r, cx + r, cy + r], fill=(40, 40, 40))
    return np.asarray(image)


def label(frame: np.ndarray, text: str) -> np.ndarray:
    """``frame [h, w, 3]`` with ``text`` written in its top-left corner."""
    from PIL import Image, ImageDraw

    image = Image.fromarray(np.ascontiguousarray(frame))
    ImageDraw.Draw(image).text((3, 2), text, fill=(255, 255, 255), stroke_width=1,
                               stroke_fill=(0, 0, 0))  # fmt: skip
    return np.asarray(image)


# ---------------------------------------------------------------------------------------------
# The rollout
# ---------------------------------------------------------------------------------------------


class Rollout(NamedTuple):
    """Episodes of a run's deterministic policy, for rendering.

    ``returns [episodes]`` as the evaluation computes them; ``positions[e] [length_e, nq]`` and
    ``rewards[e] [length_e]``: the state after, and the reward of, each step of episode ``e``
    up to its end (a termination or the time limit).
    """

    env: envs.Environment
    member: int
    returns: np.ndarray
    positions: list[np.ndarray]
    rewards: list[np.ndarray]
    env_steps: int | None = None  # the checkpoint's


def check_renderable(env: envs.Environment) -> None:
    """Raises :class:`NotRenderableError` for an environment without a scene to draw."""
    if env.qpos_fn is None:
        raise NotRenderableError(
            f"{env.name} cannot be rendered (renderable: brax/*, playground/*, gymnax/Pendulum-v1, "
            "and your own environments with a MuJoCo model: a FunctionalEnv's mj_model and qpos)"
        )


def choose_member(
    run_dir: Path, count: int, member: int | None, env_steps: int | None = None
) -> int:
    """``member`` checked against the ``count`` members; by default the member ``td3-jax
    export`` picks: the highest return of the evaluation at the checkpoint's ``env_steps``
    in metrics.jsonl (else of the last one), else 0: :func:`td3_jax.tools.export.choose_member`,
    whose out-of-range line it gives as a :class:`RenderError`."""
    from td3_jax.runner.logger import read_metrics
    from td3_jax.tools.export import choose_member as export_choose_member

    wanted = member is None and count > 1
    records = read_metrics(Path(run_dir) / "metrics.jsonl") if wanted else []
    return export_choose_member(member, count, records, env_steps, error=RenderError)


def split_episodes(recording: training.Recording) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """``(positions, rewards)`` per recorded environment: the steps it counted (``[T, E, ...]``
    in, ``E`` lists of ``[length_e, ...]`` out)."""
    counted = np.asarray(recording.counted, bool)
    positions, rewards = np.asarray(recording.positions), np.asarray(recording.reward)
    columns = range(counted.shape[1])
    return ([positions[counted[:, e], e] for e in columns],
            [rewards[counted[:, e], e] for e in columns])  # fmt: skip


def rollout(run_dir: Path, *, episodes: int = 1, seed: int = 12345, member: int | None = None,
            check: Any = None, env: Any = None) -> Rollout:  # fmt: skip
    """``episodes`` episodes of member ``member`` (default: :func:`choose_member`) of the newest
    checkpoint in ``run_dir``, as ``td3-jax eval --episodes episodes --seed seed`` runs them.

    ``check(env)``, if given, runs once the environment is made, before anything compiles.
    ``env``: the environment object of a run trained on one.
    """
    from td3_jax.common.runtime import awaiting_device
    from td3_jax.runner.finished import restore_on_one_device, run_program
    from td3_jax.runner.programs import run_compiled

    cfg, population, program = run_program(run_dir, eval_envs=episodes, env=env)
    choose_member(run_dir, len(population), member)  # a bad --member fails before compiling
    check_renderable(program.env)
    if check is not None:
        check(program.env)
    state, meta = restore_on_one_device(program, run_dir)
    k = choose_member(run_dir, len(population), member, meta.get("env_steps"))
    key = jax.random.split(jax.random.PRNGKey(seed), len(population))[k]
    spec = dataclasses.replace(program.spec, axis_name=None)
    run = functools.partial(training.evaluate_recorded, spec, record=episodes)
    with awaiting_device():  # (a Ctrl-C leaves the rollout running on the device)
        returns, recording = run_compiled(
            cfg,
            run,
            jax.tree.map(lambda x: x[k], state),
            key,
            doing=f"recording {episodes:,} episodes",
        )
        returns, recording = np.asarray(returns), jax.device_get(recording)
    return Rollout(program.env, k, returns, *split_episodes(recording),
                   env_steps=meta.get("env_steps"))  # fmt: skip


def episode_frames(
    rollout_: Rollout,
    episode: int,
    *,
    camera: str | None = None,
    width: int = 320,
    height: int = 240,
    backend: str | None = None,
) -> Iterator[np.ndarray]:
    """Labelled frames ``[height, width, 3]`` (uint8) of episode ``episode`` of a
    :class:`Rollout`, one per step, each drawn as it is taken (see :func:`scene_frames` for
    ``camera`` and ``backend``)."""
    env = rollout_.env
    check_renderable(env)
    positions, rewards = rollout_.positions[episode], rollout_.rewards[episode]
    if env.mj_model is None:
        drawn = (draw_pendulum(float(q[0]), width, height) for q in positions)
    else:
        drawn = scene_frames(env.mj_model, positions, camera=camera, width=width,
                             height=height, backend=backend)  # fmt: skip
    with contextlib.closing(drawn):
        for frame, so_far in zip(drawn, np.cumsum(rewards), strict=True):
            yield label(frame, f"ep {episode + 1}  return {so_far:.1f}")


def frame_stream(rollout_: Rollout, **drawing: Any) -> Iterator[np.ndarray]:
    """:func:`episode_frames` of every episode, one after another (``drawing``: its
    ``camera``, ``width``, ``height`` and ``backend``): one frame in memory at a time."""
    for episode in range(len(rollout_.positions)):
        with contextlib.closing(episode_frames(rollout_, episode, **drawing)) as frames:
            yield from frames


def rollout_frames(
    rollout_: Rollout,
    *,
    camera: str | None = None,
    width: int = 320,
    height: int = 240,
    backend: str | None = None,
) -> list[np.ndarray]:
    """Labelled frames ``[length_e, height, width, 3]`` (uint8) of each episode of a
    :class:`Rollout`, all held at once (:func:`frame_stream` draws them one at a time)."""
    drawing = dict(camera=camera, width=width, height=height, backend=backend)
    return [np.stack(list(episode_frames(rollout_, e, **drawing)))
            for e in range(len(rollout_.positions))]  # fmt: skip


# ---------------------------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------------------------


def video_path(run_dir: Path, out: Path | None, gif: bool) -> Path:
    """Where to write: ``out`` (``.mp4`` or ``.gif``), else ``run_dir/rollout.mp4`` (``.gif``
    with ``gif``)."""
    if out is None:
        return Path(run_dir) / ("rollout.gif" if gif else "rollout.mp4")
    out = Path(out)
    if out.suffix.lower() not in VIDEO_SUFFIXES:
        raise RenderError(f"--out {out}: the video must end in .mp4 or .gif")
    if gif and out.suffix.lower() != ".gif":
        raise RenderError(f"--gif with --out {out}: a GIF's name ends in .gif")
    return out


def write_video(path: Path, frames: Iterable[np.ndarray], fps: float) -> Path:
    """Writes ``frames`` (``[h, w, 3]`` uint8 each: an array ``[n, h, w, 3]``, a list or an
    iterator) to ``path``: H.264 MP4 (imageio-ffmpeg; odd sizes are padded to even), each
    frame handed to ffmpeg as it comes, or a looping GIF (Pillow, which holds them all until
    it writes), by its suffix. ``OSError`` where nothing was written."""
    import imageio.v2 as imageio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    gif = path.suffix.lower() == ".gif"
    if gif:
        options = dict(format="GIF", duration=1000.0 / fps, loop=0)
    else:
        options = dict(format="FFMPEG", fps=fps, macro_block_size=2, ffmpeg_log_level="error")
    before = _written(path)
    with _forking(), imageio.get_writer(path, mode="I", **options) as writer:
        for frame in frames:
            writer.append_data(frame)
    if not gif and (_written(path) in (before, None) or path.stat().st_size == 0):
        raise OSError(f"ffmpeg wrote nothing to {path}")  # (ffmpeg only says why)
    return path


def _written(path: Path) -> int | None:
    """When ``path`` was last written (ns), ``None`` where it is no file."""
    return path.stat().st_mtime_ns if path.is_file() else None


def check_scene(env: envs.Environment, camera: str | None) -> None:
    """Fails early (before a rollout compiles) on what would stop :func:`rollout_frames`: no
    OpenGL for a MuJoCo scene, a camera the model does not have."""
    check_renderable(env)
    if env.mj_model is not None:
        camera_id(env.mj_model, camera)
        default_gl_backend()
    elif camera is not None:
        raise RenderError(f"--camera {camera}: {env.name} is drawn without cameras")


class Rendered(NamedTuple):
    """What :func:`render_run` wrote: the video, the member, per-episode frames and returns."""

    path: Path
    member: int
    lengths: list[int]
    returns: list[float]
    env_steps: int | None = None  # the checkpoint's


def check_writer(path: Path) -> None:
    """Raises :class:`RenderError` when the packages writing ``path``'s format are missing."""
    needed = ["imageio", "PIL"] + (["imageio_ffmpeg"] if Path(path).suffix.lower() != ".gif"
                                   else [])  # fmt: skip
    missing = [name for name in needed if importlib.util.find_spec(name) is None]
    if missing:
        raise RenderError(f"writing {Path(path).name} needs {', '.join(missing)}: "
                          "pip install 'td3-jax[render]'")  # fmt: skip


def check_destination(path: Path, replace: bool = False) -> list[Path]:
    """Raises :class:`RenderError` before a rollout when ``path`` cannot be written: a folder of
    that name, a file already there (unless ``replace``: a run's own default video), a folder
    that cannot be made, or one this process may not write in. A missing folder is made;
    returns the folders made, outermost first."""
    path = Path(path)
    made = [up for up in path.parents if not up.exists()][::-1]
    if path.is_dir():
        raise RenderError(f"--out {path} is a directory; name the video file (.mp4 or .gif)")
    if path.exists() and not replace:
        raise RenderError(f"--out {path} exists: remove it or choose another name (nothing is "
                          "overwritten)")  # fmt: skip
    blocking = next((up for up in path.parents if up.exists() and not up.is_dir()), None)
    if blocking is not None:
        raise RenderError(f"--out {path}: {blocking} is a file, not a folder")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise RenderError(f"--out {path}: cannot make its folder ({err.strerror or err})") from err
    try:
        probe_write(path)
    except OSError as err:
        raise RenderError(f"--out {path}: cannot write it ({err.strerror or err})") from err
    return made


def _write(out: Path, frames: Iterable[np.ndarray], fps: float) -> None:
    """:func:`write_video`, its OSError (a full disk) a RenderError; a video left unfinished
    (the write or a frame's drawing failed, a Ctrl-C) is removed."""
    before = _written(Path(out))
    try:
        write_video(out, frames, fps)
    except BaseException as err:
        if _written(Path(out)) != before:
            Path(out).unlink(missing_ok=True)
        if isinstance(err, OSError):
            raise RenderError(f"--out {out}: cannot write it ({err.strerror or err})") from err
        raise


def _remove_folders(made: list[Path]) -> None:
    """Removes the folders :func:`check_destination` made, innermost first, where empty."""
    for folder in reversed(made):
        with contextlib.suppress(OSError):
            folder.rmdir()


#: Bytes of memory per pixel of each frame that a GIF's encoder holds until it writes the file
#: (imageio keeps every frame as an RGB image, 3 bytes, and Pillow adds its paletted copy and
#: deltas: 5.2 to 5.6 measured for 300 to 1200 frames of 320 x 240), rounded up.
GIF_BYTES_PER_PIXEL = 6


def check_gif_memory(frames: int, width: int, height: int, available: int | None = None) -> None:
    """Raises :class:`RenderError` before any frame is drawn where a GIF of ``frames`` frames
    of ``width x height`` would not fit in the memory available now (``available`` bytes,
    default :func:`~td3_jax.runner.memory.available_memory`; unknown: no check): its encoder
    holds every frame (:data:`GIF_BYTES_PER_PIXEL`), where an MP4 is written frame by frame."""
    from td3_jax.runner.memory import size_text

    available = available_memory() if available is None else available
    need = frames * width * height * GIF_BYTES_PER_PIXEL
    if available is None or need <= available:
        return
    raise RenderError(
        f"a GIF of {frames:,} frames of {width}x{height} needs about {size_text(need)} of memory "
        f"(its encoder holds every frame until it writes the file) and {size_text(available)} "
        "is available: write an MP4 instead (no --gif, and an --out ending in .mp4 if one is "
        "given; it is written frame by frame), or render fewer --episodes or smaller frames "
        "(--width, --height)"
    )


#: The largest frame side ``render`` draws (8K; a frame of 100000 x 100000 pixels is 30 GB).
MAX_FRAME_SIDE = 8192


def check_settings(episodes: int, width: int, height: int, fps: float) -> None:
    """Raises :class:`RenderError` for a non-positive count, size or rate, or a frame side
    over :data:`MAX_FRAME_SIDE`."""
    for name, value in (("episodes", episodes), ("width", width), ("height", height),
                        ("fps", fps)):  # fmt: skip
        if not value > 0:
            raise RenderError(f"--{name} must be positive, got {value}")
    for name, value in (("width", width), ("height", height)):
        if value > MAX_FRAME_SIDE:
            raise RenderError(
                f"--{name} {value} is more than the {MAX_FRAME_SIDE} pixels a frame side may "
                "have (each frame is width x height x 3 bytes)"
            )


def render_run(run_dir: Path, out: Path, *, episodes: int = 1, seed: int = 12345,
               member: int | None = None, camera: str | None = None, width: int = 320,
               height: int = 240, fps: float = 30.0, env: Any = None) -> Rendered:  # fmt: skip
    """Renders ``episodes`` evaluation episodes of a run (:func:`rollout`) one after the other
    into the video ``out``, each frame drawn as the writer takes it (:func:`frame_stream`; a
    GIF that would not fit in memory is refused first, :func:`check_gif_memory`). ``env``: the
    environment object of a run trained on one."""
    check_settings(episodes, width, height, fps)
    check_writer(out)
    from td3_jax.runner.rundir import require_run_dir

    require_run_dir(run_dir)  # (the line eval and plot give; before a folder is made)
    own = Path(out).resolve() in {video_path(run_dir, None, g).resolve() for g in (False, True)}
    made = check_destination(out, replace=own)  # (the run's own rollout video is replaced)
    try:
        result = rollout(run_dir, episodes=episodes, seed=seed, member=member,
                         check=functools.partial(check_scene, camera=camera), env=env)  # fmt: skip
        lengths = [len(p) for p in result.positions]
        if Path(out).suffix.lower() == ".gif":
            check_gif_memory(sum(lengths), width, height)
        _write(out, frame_stream(result, camera=camera, width=width, height=height), fps)
    except BaseException:  # (no checkpoint, no OpenGL, a bad member: no folder left behind)
        _remove_folders(made)
        raise
    return Rendered(Path(out), result.member, lengths, [float(r) for r in result.returns],
                    result.env_steps)  # fmt: skip


__all__ = [
    "VIDEO_SUFFIXES",
    "GLUnavailableError",
    "NotRenderableError",
    "RenderError",
    "check_gif_memory",
    "frame_stream",
    "render_run",
    "rollout",
    "write_video",
]
