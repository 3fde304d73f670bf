"""Tests of the checksum program compiled before a run's first checkpoint
(:meth:`td3_jax.runner.checkpoint.Checkpointer.prepare`): the saves use it and record the
checksums the program compiled at the save records, and a compile that fails costs one line."""

from __future__ import annotations

import json
from concurrent.futures import Future

import jax
import jax.numpy as jnp
import pytest

from td3_jax.config.build import members
from td3_jax.runner import checkpoint, programs, run
from td3_jax.runner.checkpoint import Checkpointer
from td3_jax.runner.sharding import make_mesh, state_shardings
from tests.configs import tiny_config


def _spec(x):
    weak = getattr(x, "weak_type", False)  # (a typed key has none)
    return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=x.sharding, weak_type=weak)


def _specs(state):
    return jax.tree.map(_spec, state)


class _CountingChecksums:
    """Stands in for checkpoint._device_checksums: lowers as it does, counts its calls."""

    def __init__(self, real):
        self.real, self.calls = real, 0

    def lower(self, *args):
        return self.real.lower(*args)

    def __call__(self, leaves):
        self.calls += 1
        return self.real(leaves)


def _saved_checksums(directory, state, prepare: bool) -> list[str]:
    saver = Checkpointer(directory, keep=1)
    if prepare:
        saver.prepare(_specs(state))
    saver.save(1, state, {"env_steps": 0})
    saver.close()
    return json.loads((directory / "1" / "meta" / "metadata").read_text())["checksums"]


def test_a_prepared_save_uses_the_compiled_checksums_and_records_the_same_ones(
    tmp_path, monkeypatch
):
    state = {"w": jnp.arange(12.0).reshape(3, 4), "n": jnp.int32(5), "b": jnp.ones(7, jnp.bfloat16),
             "key": jax.random.split(jax.random.key(3), 4)}  # (a typed key has no weak type)
    plain = _saved_checksums(tmp_path / "plain", state, prepare=False)
    counting = _CountingChecksums(checkpoint._device_checksums)
    monkeypatch.setattr(checkpoint, "_device_checksums", counting)
    assert _saved_checksums(tmp_path / "prepared", state, prepare=True) == plain
    assert counting.calls == 0  # (the program prepare compiled ran instead)
    other = {"w": jnp.zeros((2, 2))}  # another layout: compiled when it comes
    _saved_checksums(tmp_path / "other", other, prepare=False)
    assert counting.calls == 1


def test_the_layout_prepared_from_a_runs_shapes_is_that_of_its_state():
    """What the run prepares (its state's shapes placed as its programs place them) has the
    layout of the state its init program returns, so its saves find the compiled program."""
    cfg = tiny_config()
    mesh = make_mesh(1)
    program = programs.find(cfg, members(cfg), mesh, None).program
    shapes = program.abstract_state
    prepared = jax.tree.leaves(programs.with_sharding(shapes, state_shardings(shapes, mesh)))
    state = jax.tree.leaves(programs.jitted(program, mesh).init())
    assert checkpoint._layout(prepared) == checkpoint._layout(state)


@pytest.mark.runs
def test_a_runs_checkpoints_use_the_checksums_compiled_while_its_programs_compile(
    tmp_path, monkeypatch
):
    """A tiny run's two checkpoints (one per chunk) compute their checksums with the program
    its warm-up compiled: the run's state has the layout the warm-up was given."""
    counting = _CountingChecksums(checkpoint._device_checksums)
    monkeypatch.setattr(checkpoint, "_device_checksums", counting)
    records = run.train(tiny_config(), tmp_path / "run", progress=False)
    assert [r["env_steps"] for r in records] == [64, 128]
    assert sorted(int(p.name) for p in (tmp_path / "run" / "checkpoints").iterdir()) == [1, 2]
    assert counting.calls == 0


@pytest.mark.runs
def test_a_warm_up_that_fails_is_said_in_one_line_and_the_run_goes_on(
    tmp_path, monkeypatch, capsys
):
    def no_memory(self, specs):  # (as a compile that runs out of memory on its thread)
        failed = Future()
        failed.set_exception(RuntimeError("RESOURCE_EXHAUSTED: out of memory compiling\nmore"))
        return failed

    monkeypatch.setattr(Checkpointer, "prepare", no_memory)
    records = run.train(tiny_config(), tmp_path / "run", progress=False)
    assert [r["env_steps"] for r in records] == [64, 128]
    warnings = [line for line in capsys.readouterr().err.splitlines() if "prepared" in line]
    assert warnings == [
        "td3-jax: warning: the first checkpoint could not be prepared ahead (RESOURCE_EXHAUSTED: "
        "out of memory compiling); it does that work when it is written"
    ]


@pytest.mark.runs
def test_a_run_prepares_its_checksums_once_its_programs_are_traced(tmp_path, monkeypatch):
    """The run's room check (``check``) prepares nothing; its ``traced`` callback prepares the
    checksum program, once (the programs' tracing is not delayed by it)."""
    events, real_compiled, real_prepare = [], programs.compiled, Checkpointer.prepare

    def spied(source, stop=None, check=None, traced=None):
        def check_spied(shapes):
            check(shapes)
            events.append("checked")

        def traced_spied(shapes):
            events.append("traced")
            traced(shapes)

        return real_compiled(source, stop, check=check_spied, traced=traced_spied)

    def prepare_spied(self, specs):
        events.append("prepared")
        return real_prepare(self, specs)

    monkeypatch.setattr(programs, "compiled", spied)
    monkeypatch.setattr(Checkpointer, "prepare", prepare_spied)
    run.train(tiny_config(), tmp_path / "run", progress=False)
    assert events == ["checked", "traced", "prepared"]
