"""A batch split over devices, each device running its own block (:mod:`td3_jax.envs.per_device`),
on two forced CPU devices (a fresh process: JAX fixes its device count at import).

MuJoCo Warp's own check (a T1 run on two devices gives the one-device numbers) is in
tests/envs/test_warp_cpu.py; here a batched function stands in for its physics call. Not marked
``processes``: one child process of about 30 s, so the suite CI runs keeps it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import jax
import pytest

_CODE = """
import json
import jax, jax.numpy as jnp, numpy as np
from jax.sharding import Mesh
from td3_jax.common.errors import ConfigError
from td3_jax.envs.per_device import split_call
from td3_jax.runner.sharding import state_shardings

mesh = Mesh(np.array(jax.devices()), ("data",))

def physics(x, shared):
    # x [n] batched; shared [3] one buffer for the batch: this call's own sum of x, and n
    return x * 2.0 + 1.0, shared.at[0].set(jnp.sum(x)).at[1].set(x.shape[0])

x = jnp.arange(6.0)
shared_arg = lambda path: path[0].idx == 1  # (the second argument, and its result)
y, shared = jax.jit(split_call(physics, 6, mesh=mesh, shared=shared_arg))(x, jnp.zeros(3))
per_device = [np.asarray(s.data).tolist() for s in shared.addressable_shards]
try:
    split_call(physics, 5, mesh=mesh, shared=shared_arg)
    refused = None
except ConfigError as err:
    refused = str(err)

from typing import NamedTuple
class Env(NamedTuple):
    steps: jax.Array
    contacts: jax.Array
    qpos: jax.Array
class State(NamedTuple):
    env_state: Env
state = State(Env(jnp.zeros((1, 6), jnp.int32), jnp.zeros((1, 4)), jnp.zeros((1, 6, 2))))
specs = {name: list(s.spec) for name, s in
         zip(Env._fields, state_shardings(state, mesh).env_state)}

import dataclasses
from td3_jax.config.build import make_env, members
from td3_jax.config.schema import TrainConfig
from td3_jax.runner.programs import find
cfg = TrainConfig(env="gymnax/Pendulum-v1", num_envs=8, eval_envs=4, total_steps=512,
                  batch_size=32, warmup_steps=64, eval_every=256)
needs_it = dataclasses.replace(make_env(cfg), per_device=True)
from td3_jax.envs.per_device import over_devices
one_device = Mesh(np.array(jax.devices()[:1]), ("data",))
shardy = [jax.config.jax_use_shardy_partitioner]
over_devices(make_env(cfg), mesh)  # (JAX physics: XLA splits it, Shardy or not)
over_devices(needs_it, one_device)  # (nothing to split)
shardy.append(jax.config.jax_use_shardy_partitioner)
maps = [find(cfg, members(cfg), mesh, None, env=env).program.spec.env.batch_map is not None
        for env in (needs_it, make_env(cfg))]
seeds = dataclasses.replace(cfg, seeds=2)
find(seeds, members(seeds), mesh, None, env=needs_it)  # (builds: members split as above)
find(seeds, members(seeds), mesh, None, env=make_env(seeds))  # (JAX physics: split by XLA)
# two members (a vmap around the split call): member 0 steps x = 0..5, member 1 x = 6..11;
# the shared buffer, one for every world a device steps, counts them
def counting(x, shared):
    return x * 2.0 + 1.0, shared.at[1].add(x.shape[0])

from td3_jax.envs import per_device as module
inside = []  # the functions the members' vmap mapped inside the split
real_members_map = module.members_map
module.members_map = lambda fn, shared: inside.append(fn) or real_members_map(fn, shared)
split = split_call(counting, 6, mesh=mesh, shared=shared_arg)
my, mshared = jax.jit(jax.vmap(split, in_axes=(0, None), out_axes=(0, None)))(
    jnp.arange(12.0).reshape(2, 6), jnp.zeros(3))
module.members_map = real_members_map
try:
    jax.vmap(split)(jnp.zeros((2, 6)), jnp.zeros((2, 3)))
    per_member = None
except ValueError as err:
    per_member = str(err)
population = {"y": np.asarray(my).tolist(), "shape": list(mshared.shape),
              "per_device": [np.asarray(s.data).tolist() for s in mshared.addressable_shards],
              "per_member": per_member, "mapped_inside": len(inside)}
print(json.dumps({"y": np.asarray(y).tolist(), "shape": list(shared.shape),
                  "per_device": per_device, "refused": refused, "specs": specs, "maps": maps,
                  "shardy": shardy + [jax.config.jax_use_shardy_partitioner],
                  "population": population}))
"""


@pytest.fixture(scope="module")
def two_devices() -> dict:
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=2",
           "JAX_PLATFORMS": "cpu"}  # fmt: skip
    env.pop("JAX_USE_SHARDY_PARTITIONER", None)  # (JAX's own default partitioner)
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(_CODE)], env=env,
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_batched_leaves_give_the_one_device_values(two_devices):
    assert two_devices["y"] == [2.0 * v + 1.0 for v in range(6)]


def test_each_device_runs_its_own_block_and_keeps_its_own_shared_buffer(two_devices):
    """Device 0 saw x = 0, 1, 2 (sum 3), device 1 saw 3, 4, 5 (sum 12), each a batch of 3; the
    buffer keeps its one-device shape, though its length is that of a device's batch."""
    assert two_devices["shape"] == [3]
    assert two_devices["per_device"] == [[3.0, 3.0, 0.0], [12.0, 3.0, 0.0]]


def test_a_batch_that_does_not_divide_is_refused_in_one_line(two_devices):
    assert two_devices["refused"] == (
        "5 environments cannot be split evenly over 2 devices: use a number of environments "
        "divisible by 2"
    )


def test_environment_leaves_without_the_batch_axis_are_replicated(two_devices):
    """The train state's shardings: ``[members, worlds, ...]`` leaves split along the worlds,
    a shared buffer (its second axis is not the batch) whole on every device."""
    assert two_devices["specs"] == {"steps": [None, "data"], "qpos": [None, "data"],
                                    "contacts": []}


def test_a_runs_programs_step_a_per_device_environment_on_each_device(two_devices):
    """The run's programs (``runner.programs.find`` on a two-device mesh) give an environment
    that needs it (``per_device``) the split physics, and one whose physics XLA splits
    (gymnax's) none."""
    assert two_devices["maps"] == [True, False]


def test_an_environment_split_over_devices_compiles_with_gspmd(two_devices):
    """Shardy, JAX's default partitioner (in jax 0.10 and 0.11), stays as it was for physics
    XLA splits and for one device, and is off once a run splits a per-device environment over
    two (Shardy's compile of MuJoCo Warp's calls under ``shard_map`` crashed on two GPUs;
    GSPMD's does not). The flag is checked, not a GPU compile: a CPU compiles either way."""
    before = two_devices["shardy"][0]
    assert two_devices["shardy"] == [before, before, False]
    if jax.__version_info__ >= (0, 10):
        assert before is True


def test_members_of_a_split_call_each_run_their_own_blocks_on_each_device(two_devices):
    """Seeds (or a sweep) vmapped around the split call: each member's values are its own
    (2x + 1); the shared buffer is not batched by the members' vmap (the vmap runs inside the
    ``shard_map``), one buffer for every member, as MuJoCo Warp keeps it: each device's copy
    counted its own 3 environments, once."""
    population = two_devices["population"]
    assert population["y"] == [[2.0 * v + 1.0 for v in range(6)],
                               [2.0 * v + 1.0 for v in range(6, 12)]]  # fmt: skip
    assert population["mapped_inside"] == 1  # (one vmap: the physics traced once inside)
    assert population["shape"] == [3]
    assert population["per_device"] == [[0.0, 3.0, 0.0], [0.0, 3.0, 0.0]]


def test_a_shared_buffer_that_differs_between_members_is_refused(two_devices):
    assert two_devices["population"]["per_member"] == (
        "[1] is kept once for all environments but differs between members"
    )


_SHARDY_ASKED = """
import dataclasses
import jax, numpy as np
from jax.sharding import Mesh
from td3_jax.config.build import make_env
from td3_jax.config.schema import TrainConfig
from td3_jax.envs.per_device import over_devices
mesh = Mesh(np.array(jax.devices()), ("data",))
env = dataclasses.replace(make_env(TrainConfig(env="gymnax/Pendulum-v1", num_envs=8)),
                          per_device=True)
over_devices(env, mesh)
over_devices(env, mesh)
print(jax.config.jax_use_shardy_partitioner)
"""


@pytest.mark.parametrize("asked", ["true", "1", "t"])
def test_shardy_asked_for_in_the_environment_is_kept_with_one_warning(asked):
    """``JAX_USE_SHARDY_PARTITIONER`` set to a value JAX reads as true: the user's choice
    stands (two splits), and stderr says once what it risks."""
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=2",
           "JAX_PLATFORMS": "cpu", "JAX_USE_SHARDY_PARTITIONER": asked}  # fmt: skip
    proc = subprocess.run([sys.executable, "-c", _SHARDY_ASKED], env=env, capture_output=True,
                          text=True, timeout=300)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.strip() == "True"
    warnings = [line for line in proc.stderr.splitlines() if line.startswith("td3-jax: warning")]
    assert warnings == [
        f"td3-jax: warning: JAX_USE_SHARDY_PARTITIONER={asked} keeps Shardy for MuJoCo Warp "
        "split over several devices, whose compile crashed the process on two GPUs (jax "
        "0.11.2); unset it to compile with GSPMD"
    ]
