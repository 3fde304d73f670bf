"""MJX's default device made process-local (td3_jax.envs.mjx_devices), with stand-in devices."""

from __future__ import annotations

from types import SimpleNamespace

import jax
import pytest
from support import python

from td3_jax.envs import mjx_devices


@pytest.fixture
def two_processes(monkeypatch):
    """Process 1's view: global devices g0 (process 0's GPU), then its own c1 (CPU), g1 (GPU)."""
    kinds = (("gpu", 0), ("cpu", 1), ("gpu", 2))
    g0, c1, g1 = (SimpleNamespace(platform=p, id=i) for p, i in kinds)
    local = [c1, g1]

    def local_devices(backend=None):
        return [d for d in local if backend in (None, d.platform)]

    monkeypatch.setattr(jax, "local_devices", local_devices)
    return g0, c1, g1


def test_a_remote_default_becomes_the_local_device_of_its_platform(two_processes):
    g0, _c1, g1 = two_processes
    resolve = mjx_devices.with_local_default(lambda impl, device: ("jax", device or g0))
    assert resolve("jax") == ("jax", g1)  # not c1: same platform as MJX's pick
    assert resolve(None, None) == ("jax", g1)


def test_an_explicit_or_local_device_is_kept(two_processes):
    g0, c1, _g1 = two_processes
    resolve = mjx_devices.with_local_default(lambda impl, device: ("cpp", device or c1))
    assert resolve("cpp") == ("cpp", c1)
    assert resolve("jax", g0) == ("cpp", g0)  # asked for by name: not ours to change


@pytest.mark.usefixtures("two_processes")  # stand-in local devices: a CPU and a GPU, no TPU
def test_a_platform_this_process_lacks_is_left_to_mjx():
    tpu = SimpleNamespace(platform="tpu", id=9)
    resolve = mjx_devices.with_local_default(lambda impl, device: ("jax", tpu))
    assert resolve("jax") == ("jax", tpu)


def test_patching_mjx_is_idempotent_and_keeps_one_process_unchanged(monkeypatch):
    io = pytest.importorskip("mujoco.mjx._src.io")
    # restored after the test: no other test runs with the wrapped function
    monkeypatch.setattr(io, "_resolve_impl_and_device", io._resolve_impl_and_device)
    assert mjx_devices.place_on_local_devices()
    patched = io._resolve_impl_and_device
    assert mjx_devices.place_on_local_devices()
    assert io._resolve_impl_and_device is patched  # not wrapped twice
    _impl, device = io._resolve_impl_and_device("jax")
    assert device == jax.devices()[0]  # one process: MJX's own choice


@pytest.mark.subprocess  # a fresh process, where MJX is first imported here (a gymnax run's)
def test_placing_on_local_devices_drops_mjx_notes_on_a_missing_warp():
    pytest.importorskip("mujoco.mjx")
    code = (
        "import sys; sys.modules['warp'] = None; sys.modules['mujoco_warp'] = None\n"
        "from td3_jax.envs import mjx_devices\n"
        "print(mjx_devices.place_on_local_devices())\n"
    )
    proc = python(code)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == "True\n"  # without "Failed to import warp: ..." before it
