"""Domain randomisation and pushes on MuJoCo Warp (its CPU kernels, ``TD3_JAX_WARP_ON_CPU=1``),
against MJX's JAX physics stepping the same states with the same drawn models: under
``jax.vmap`` each Warp world simulates its own drawn model (not one model for all), step for step
as the JAX physics does, and a push at the push interval kicks the base's velocity as on JAX. A
tiny T1 run with both options trains on Warp. Skipped where Warp is not installed.

Three T1 worlds, three steps: two programs compiled per physics (reset, step)."""

from __future__ import annotations

import importlib.util
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support import main
from test_locomotion import T1, needs_assets
from test_warp_cpu import TINY_T1

from td3_jax import envs
from td3_jax.envs import physics
from td3_jax.envs.base import EnvOptions

pytestmark = [
    pytest.mark.robots,
    pytest.mark.skipif(
        importlib.util.find_spec("warp") is None, reason="MuJoCo Warp (warp-lang) is not installed"
    ),
]

WORLDS, STEPS = 3, 3


def _rollout(step, inner, action, keys) -> np.ndarray:
    """``[WORLDS, STEPS, nq]`` joint positions over ``STEPS`` steps of the same ``action``."""
    positions = []
    for _ in range(STEPS):
        inner = step(inner, action, keys)[0]
        positions.append(np.asarray(inner[0].data.qpos))
    return np.stack(positions, axis=1)


def _push_now(state):
    """The Playground ``state`` one step short of its push interval: its next step pushes."""
    return state.replace(info={**state.info, "push_step": state.info["push_interval_steps"] - 1})


def _simulate(impl: str) -> dict[str, np.ndarray]:
    """T1 on ``impl`` with randomised physics and pushes: every world starts from one state
    and steps the same actions; ``drawn``/``same``: the joint positions of worlds holding
    different drawn models / one drawn model; ``kick``: ``[WORLDS, nv]`` the velocity a
    pushing step gives beyond a plain one; ``push``/``no_push``: the pushes they report."""
    options = EnvOptions(impl=impl, domain_randomization=True, pushes=True, worlds=WORLDS)
    env = envs.make(f"playground/{T1}", options=options)
    reset, step = jax.jit(jax.vmap(env.reset_fn)), jax.jit(jax.vmap(env.step_fn))
    keys = jnp.stack([jax.random.PRNGKey(0)] * WORLDS)  # one state, one model, in every world
    (state, fields), _ = reset(keys)
    drawn = reset(jax.random.split(jax.random.PRNGKey(7), WORLDS))[0][1]  # a model per world
    action = jnp.tile(0.3 * jnp.sin(jnp.arange(env.action_size)), (WORLDS, 1))
    pushed = step((_push_now(state), fields), action, keys)[0][0]
    plain = step((state, fields), action, keys)[0][0]
    return {
        "drawn": _rollout(step, (state, drawn), action, keys),
        "same": _rollout(step, (state, fields), action, keys),
        "kick": np.asarray(pushed.data.qvel - plain.data.qvel),
        "push": np.asarray(pushed.info["push"]),
        "no_push": np.asarray(plain.info["push"]),
    }


@pytest.fixture(scope="module")
def runs():
    """:func:`_simulate` on Warp (its CPU kernels) and on JAX physics."""
    needs_assets(T1)
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv(physics.WARP_ON_CPU, "1")
        return {impl: _simulate(impl) for impl in ("warp", "jax")}


def test_each_warp_world_simulates_its_own_drawn_model(runs):
    """Measured: worlds with different drawn models end 0.07 and 0.08 (largest joint position
    difference) from the first world after three steps, on both physics, and worlds with one
    model do not differ; Warp and JAX agree per world to 3e-6."""
    warp, jax_physics = runs["warp"], runs["jax"]
    for run in (warp, jax_physics):
        assert np.abs(run["drawn"] - run["drawn"][:1]).max(axis=(1, 2))[1:].min() > 0.01
        np.testing.assert_array_equal(
            run["same"], np.broadcast_to(run["same"][:1], run["same"].shape)
        )
    np.testing.assert_allclose(warp["drawn"], jax_physics["drawn"], atol=1e-4)
    np.testing.assert_allclose(warp["same"], jax_physics["same"], atol=1e-4)


def test_a_push_on_warp_kicks_the_base_as_on_jax(runs):
    """A step at the push interval adds the push to the base's planar velocity (0.62 here;
    Warp and JAX agree to 2e-4); a step before it pushes nothing."""
    warp, jax_physics = runs["warp"], runs["jax"]
    for run in (warp, jax_physics):
        np.testing.assert_allclose(np.linalg.norm(run["push"], axis=-1), 1.0, rtol=1e-5)
        np.testing.assert_array_equal(run["no_push"], 0.0)
        assert np.linalg.norm(run["kick"][:, :2], axis=-1).min() > 0.1  # the least magnitude
    np.testing.assert_allclose(warp["kick"], jax_physics["kick"], atol=1e-3)


def test_a_tiny_robot_run_trains_on_warp_with_randomised_physics_and_pushes(
    monkeypatch, tmp_path, capsys
):
    monkeypatch.setenv(physics.WARP_ON_CPU, "1")
    out = tmp_path / "run"
    args = [*TINY_T1, "--domain-randomization", "--pushes", "on", "--out", str(out)]
    code, stdout, err = main(args, capsys)
    assert code == 0, err
    assert "physics: MuJoCo Warp (--impl warp)" in stdout
    saved = json.loads((out / "config.json").read_text())
    assert saved["impl"] == "warp" and saved["domain_randomization"] and saved["pushes"] == "on"
    records = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["env_steps"] for r in records] == [32, 64]
    assert all(r["physics_overflow"] == 0 for r in records)
    assert all(np.isfinite(r["critic_loss"]) for r in records)
