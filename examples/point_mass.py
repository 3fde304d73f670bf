"""Your own environment, end to end: a small MJX environment from an MJCF string, handed to
td3-jax as a :class:`td3_jax.envs.FunctionalEnv` by the factory :func:`make`.

A point mass on a plane, pushed by two motors toward a target at the origin. Reward: minus
its distance to the target at every step; the episode *terminates* when it comes within
:data:`TARGET_RADIUS` of the target (there is nothing left to do) and is *truncated* by
td3-jax after :data:`EPISODE_LENGTH` steps otherwise.

From the repository's root (the current directory is where ``examples`` is found)::

    td3-jax train --env examples.point_mass:make --total-steps 24000 --out runs/point_mass
    td3-jax eval --run runs/point_mass      # config.json names the factory: it is made again
    td3-jax render --run runs/point_mass --camera overview

or ``python examples/point_mass.py``: trains on a CPU in under a minute and prints the
evaluation returns against a random policy's.
"""

from __future__ import annotations

import sys
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from td3_jax import envs
from td3_jax.config.build import make_train
from td3_jax.config.schema import TrainConfig
from td3_jax.core.training import key_for_seed
from td3_jax.envs import FunctionalEnv

XML = """
<mujoco model="point_mass">
  <option timestep="0.02"/>
  <worldbody>
    <light pos="0 0 3"/>
    <camera name="overview" pos="0 -1.6 2.2" xyaxes="1 0 0 0 0.8 0.6"/>
    <geom name="floor" type="plane" size="1.2 1.2 0.1" rgba=".9 .9 .9 1"/>
    <site name="target" pos="0 0 0.01" size="0.05" rgba="1 0 0 1"/>
    <body name="mass" pos="0 0 0.05">
      <joint name="x" type="slide" axis="1 0 0" range="-1 1" limited="true" damping="1"/>
      <joint name="y" type="slide" axis="0 1 0" range="-1 1" limited="true" damping="1"/>
      <geom name="ball" type="sphere" size="0.05" mass="0.3" rgba=".2 .6 1 1"
            contype="0" conaffinity="0"/>
    </body>
  </worldbody>
  <actuator>
    <motor joint="x" ctrlrange="-1 1" ctrllimited="true"/>
    <motor joint="y" ctrlrange="-1 1" ctrllimited="true"/>
  </actuator>
</mujoco>
"""
#: Control steps per episode (td3-jax truncates there); each is :data:`SUBSTEPS` physics steps.
EPISODE_LENGTH = 100
SUBSTEPS = 2
#: The episode terminates within this distance of the target.
TARGET_RADIUS = 0.05
#: Initial positions are drawn uniformly in ``[-START, START]^2``.
START = 0.8


def make() -> FunctionalEnv:
    """The point-mass environment: observation ``[x, y, vx, vy]``, action ``[fx, fy]`` in
    the motors' ``ctrlrange`` (td3-jax rescales its ``[-1, 1]`` actions to it)."""
    model = mujoco.MjModel.from_xml_string(XML)
    physics = mjx.put_model(model)

    def observe(data: mjx.Data) -> jax.Array:
        return jnp.concatenate([data.qpos, data.qvel])  # [4]

    def reset(key: jax.Array) -> tuple[mjx.Data, jax.Array]:
        qpos = jax.random.uniform(key, (2,), minval=-START, maxval=START)
        data = mjx.make_data(physics).replace(qpos=qpos)
        return data, observe(data)

    def step(data: mjx.Data, action: jax.Array) -> tuple[mjx.Data, jax.Array, jax.Array, jax.Array]:
        data = data.replace(ctrl=action)
        data = jax.lax.fori_loop(0, SUBSTEPS, lambda _, d: mjx.step(physics, d), data)
        distance = jnp.linalg.norm(data.qpos)
        return data, observe(data), -distance, distance < TARGET_RADIUS

    return FunctionalEnv(
        reset=reset,
        step=step,
        observation_size=4,
        action_size=2,
        action_low=model.actuator_ctrlrange[:, 0],
        action_high=model.actuator_ctrlrange[:, 1],
        episode_length=EPISODE_LENGTH,
        name="point_mass",
        mj_model=model,  # td3-jax render draws it at qpos(state)
        qpos=lambda data: data.qpos,
    )


def random_policy_return(env: envs.Environment, key: jax.Array, episodes: int = 64) -> float:
    """The mean return of uniformly random actions over ``episodes`` episodes (each counted
    to its termination or time limit)."""
    reset_key, act_key = jax.random.split(key)
    state = envs.reset(env, reset_key, episodes)

    def one_step(carry, step_key):
        state, total, alive = carry
        action = jax.random.uniform(step_key, (episodes, env.action_size), minval=-1, maxval=1)
        state, result = envs.step(env, state, action, auto_reset=False)
        total = total + jnp.where(alive, result.reward, 0.0)
        return (state, total, alive & ~(result.terminated | result.truncated)), None

    start = (state, jnp.zeros(episodes), jnp.ones(episodes, bool))
    keys = jax.random.split(act_key, env.episode_length)
    (_, total, _), _ = jax.jit(lambda c, k: jax.lax.scan(one_step, c, k))(start, keys)
    return float(jnp.mean(total))


#: The settings ``python examples/point_mass.py`` trains with: the defaults (CPU-sized: 16
#: environments, 8 updates of 256 per step of them) for 24k steps.
CONFIG = TrainConfig(env="examples.point_mass:make", total_steps=24_000)


def train(cfg: TrainConfig = CONFIG, seed: int = 0) -> np.ndarray:
    """``[evaluations]`` mean evaluation returns of one run of ``cfg`` on :func:`make`'s
    environment (:func:`td3_jax.config.build.make_train`: one compiled program)."""
    run = jax.jit(make_train(cfg, env=make()))
    _, metrics = run(key_for_seed(seed))
    return np.asarray(metrics["eval_returns"]).mean(axis=-1)


def main() -> int:
    """Trains :data:`CONFIG`, prints the returns against a random policy's; exit status 0
    when the last evaluation's return is above a third of the random policy's (the returns
    are negative: minus the distance to the target, summed)."""
    start = time.perf_counter()
    env = envs.make(make(), episode_length=CONFIG.episode_length)
    random_return = random_policy_return(env, jax.random.PRNGKey(1))
    returns = train()
    learned = returns[-1] > random_return / 3
    print(
        f"random policy: {random_return:.1f}; evaluations every {CONFIG.eval_every} steps: "
        f"{', '.join(f'{r:.1f}' for r in returns)} ({time.perf_counter() - start:.0f} s)"
    )
    print("learned: the trained policy beats the random one" if learned else "did not learn")
    return 0 if learned else 1


if __name__ == "__main__":
    sys.exit(main())
