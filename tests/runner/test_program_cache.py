"""The traced-program store: a repeated run makes no environment and traces nothing, and its
numbers are those of a run traced from scratch (seed and learning rates included)."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import jax
import numpy as np
import pytest

from td3_jax.config import build
from td3_jax.config.schema import TrainConfig
from td3_jax.runner import program_cache, programs
from td3_jax.runner.programs import compiled, find
from td3_jax.runner.run import train
from td3_jax.runner.sharding import make_mesh

TINY = TrainConfig(
    env="gymnax/Pendulum-v1",
    hidden_sizes=(8,),
    num_envs=2,
    eval_envs=2,
    episode_length=16,
    eval_every=32,
    total_steps=3 * 32,
    updates_per_iter=1,
    batch_size=8,
    buffer_size=256,
    warmup_steps=16,
)
NUMBERS = ("env_steps", "eval_return_mean", "critic_loss", "actor_loss", "train_return_mean")


def _numbers(records: list[dict]) -> list[tuple]:
    return [tuple(r[k] for k in NUMBERS) for r in records]


def _refuse(*_, **__):
    """Stands in for making an environment (which tracing any program of one needs)."""
    raise AssertionError("the environment was made: the programs were traced again")


def _key(cfg: TrainConfig) -> str:
    return program_cache.fingerprint(cfg, [()], make_mesh(None))


def test_the_key_covers_what_shapes_the_programs_and_nothing_else():
    base = _key(TINY)
    same = [
        {"seed": 7},
        {"actor_lr": 3e-4, "critic_lr": 2e-4, "tau": 0.01, "discount": 0.9},
        {"expl_noise": 0.3, "policy_noise": 0.1, "noise_clip": 0.2},
        {"total_steps": 2 * 32 + 1},  # a constant learning rate: the length is the host's
        {"keep_checkpoints": 1, "checkpoint_every": 2, "early_evaluation": False},
    ]
    for change in same:
        assert _key(dataclasses.replace(TINY, **change)) == base, change
    different = [
        {"hidden_sizes": (16,)},
        {"num_envs": 4},
        {"eval_envs": 4},
        {"seeds": 2},
        {"algo": "ddpg"},
        {"env": "brax/ant"},
        {"max_grad_norm": 1.0},  # clipping on: a different program
        {"lr_schedule": "cosine"},
        {"episode_length": 8},
        {"expl_noise_min": 0.01, "expl_noise_max": 0.4},  # per-environment stds: a draw state
        {"actor_obs_key": "privileged_state"},
        {"pushes": "off"},
        {"domain_randomization": True},
        {"total_steps": 10 * 32},  # the ring (capped at the run's 96 steps) grows to 256 rows
    ]
    keys = {_key(dataclasses.replace(TINY, **change)) for change in different}
    assert base not in keys and len(keys) == len(different)
    cosine = dataclasses.replace(TINY, lr_schedule="cosine")
    assert _key(cosine) != _key(dataclasses.replace(cosine, total_steps=10 * 32))
    mesh = make_mesh(None)
    assert program_cache.fingerprint(TINY, [("actor_lr",)], mesh) != base  # a sweep's members
    with jax.default_matmul_precision("highest"):  # a JAX setting that changes the trace
        assert _key(TINY) != base


def test_a_robots_key_follows_its_asset_files(tmp_path):
    robot = tmp_path / "booster_t1"
    robot.mkdir()
    (robot / "t1.xml").write_text("<mujoco/>")
    cfg = dataclasses.replace(TINY, env="playground/T1JoystickFlatTerrain", menagerie=str(tmp_path))
    first = program_cache.assets_digest(cfg)
    assert first is not None and program_cache.assets_digest(cfg) == first
    (robot / "t1.xml").write_text("<mujoco model='changed'/>")
    assert program_cache.assets_digest(cfg) != first
    assert program_cache.assets_digest(TINY) is None  # gymnax: its package's version covers it


@pytest.mark.runs
def test_a_stored_run_traces_nothing_and_matches_a_traced_one(tmp_path, monkeypatch):
    programs = tmp_path / "programs"
    first = train(TINY, tmp_path / "a", progress=False, program_dir=programs)
    (entry,) = [p for p in programs.iterdir() if not p.name.startswith(".")]
    assert sorted(p.name for p in entry.iterdir()) == [
        "chunk.bin", "evaluate.bin", "init.bin", "layout.pkl", "trees.pkl"]  # fmt: skip
    traced = train(TINY, tmp_path / "b", progress=False)  # stored nowhere, jitted as usual
    assert _numbers(first) == _numbers(traced)

    monkeypatch.setattr(build, "make_env", _refuse)
    again = train(TINY, tmp_path / "c", progress=False, program_dir=programs)
    assert _numbers(again) == _numbers(first)

    # Another seed and learning rate are arguments of the same programs: still nothing traced,
    # and the numbers are a traced run's with those settings.
    other = dataclasses.replace(TINY, seed=5, actor_lr=3e-4, critic_lr=5e-4)
    stored = train(other, tmp_path / "d", progress=False, program_dir=programs)
    monkeypatch.undo()
    fresh = train(other, tmp_path / "e", progress=False)
    assert _numbers(stored) == _numbers(fresh) != _numbers(first)


def test_a_stored_run_with_in_chunk_evaluation_keeps_its_round_program(tmp_path, monkeypatch):
    in_chunk = dataclasses.replace(TINY, eval_in_chunk=True)
    programs = tmp_path / "programs"
    first = train(in_chunk, tmp_path / "a", progress=False, program_dir=programs)
    (entry,) = [p for p in programs.iterdir() if not p.name.startswith(".")]
    assert (entry / "round.bin").is_file()
    monkeypatch.setattr(build, "make_env", _refuse)
    again = train(in_chunk, tmp_path / "b", progress=False, program_dir=programs)
    assert _numbers(again) == _numbers(first)
    assert [r["eval_policy_env_steps"] for r in again] == [0, 32, 64]


def test_the_programs_a_run_needs_are_named_in_the_order_they_are_traced():
    assert program_cache.names() == ("chunk", "evaluate", "init")
    assert program_cache.names(with_init=False) == ("chunk", "evaluate")
    assert program_cache.names(True, eval_in_chunk=True) == ("chunk", "round", "evaluate",
                                                             "init")  # fmt: skip


def test_the_source_digest_reads_every_subpackage(tmp_path):
    import td3_jax

    assert program_cache.PACKAGE_ROOT == Path(td3_jax.__file__).resolve().parent
    (tmp_path / "core").mkdir()
    (tmp_path / "core" / "training.py").write_text("A = 1\n")
    (tmp_path / "top.py").write_text("")
    before = program_cache.source_digest(tmp_path)
    (tmp_path / "core" / "training.py").write_text("A = 2\n")
    changed = program_cache.source_digest(tmp_path)
    assert changed != before
    (tmp_path / "core" / "notes.txt").write_text("not code")  # (only Python files count)
    assert program_cache.source_digest(tmp_path) == changed
    package = program_cache.PACKAGE_ROOT
    assert program_cache.source_digest() == program_cache.source_digest(package)
    assert program_cache.source_digest() != program_cache.source_digest(package / "runner")


def test_the_programs_are_one_type_whatever_their_origin(tmp_path):
    """programs.compiled gives the same Programs traced and read back from the store (shapes,
    shardings, numbers), calling the room check once with the state's shapes either way, then
    the caller's ``traced`` once."""
    population, mesh, checked, order = build.members(TINY), make_mesh(None), {}, []

    def compile_from(origin: str):
        source = find(TINY, population, mesh, tmp_path / "programs")

        def check(shapes):
            order.append(("check", origin))
            checked.setdefault(origin, []).append(shapes)

        traced = lambda shapes: order.append(("traced", origin))
        return source, compiled(source, check=check, traced=traced)

    (traced_source, traced), (stored_source, stored) = map(compile_from, ("traced", "stored"))
    assert traced_source.stored is None and traced_source.env is not None
    assert stored_source.stored is not None and stored_source.env is None  # nothing made
    shapes = lambda tree: jax.tree.map(lambda x: (x.shape, x.dtype), tree)
    assert [len(calls) for calls in checked.values()] == [1, 1]
    steps = ("check", "traced")
    assert order == [(step, origin) for origin in ("traced", "stored") for step in steps]
    assert shapes(checked["traced"][0]) == shapes(checked["stored"][0])
    assert shapes(traced.abstract_state) == shapes(stored.abstract_state)
    assert jax.tree.leaves(traced.shardings) == jax.tree.leaves(stored.shardings)
    out = [
        p.chunk(p.hyperparams, p.init(), np.int32(TINY.iters_per_chunk)) for p in (traced, stored)
    ]
    for a, b in zip(*(jax.tree.leaves(o) for o in out), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(traced.evaluate(out[0][0]), stored.evaluate(out[1][0]))


def test_a_resume_takes_the_stored_programs(tmp_path, monkeypatch):
    programs = tmp_path / "programs"
    whole = train(TINY, tmp_path / "whole", progress=False, program_dir=programs)
    train(TINY, tmp_path / "run", progress=False, program_dir=programs, stop_after_chunks=1)
    monkeypatch.setattr(build, "make_env", _refuse)
    rest = train(TINY, tmp_path / "run", progress=False, program_dir=programs, resume=True)
    assert _numbers(rest) == _numbers(whole)[-len(rest) :] and len(rest) == 2


def test_a_resume_that_traces_stores_what_a_fresh_run_needs(tmp_path, monkeypatch):
    # The first store is a resume's (it compiles no init, but stores it): a fresh run after it
    # then makes no environment either.
    expected = train(TINY, tmp_path / "plain", progress=False)
    train(TINY, tmp_path / "run", progress=False, stop_after_chunks=1)
    programs = tmp_path / "programs"
    train(TINY, tmp_path / "run", progress=False, program_dir=programs, resume=True)
    monkeypatch.setattr(build, "make_env", _refuse)
    fresh = train(TINY, tmp_path / "fresh", progress=False, program_dir=programs)
    assert _numbers(fresh) == _numbers(expected)


@pytest.mark.runs
def test_an_unusable_entry_is_a_warning_and_is_traced_again(tmp_path, capsys):
    # Unreadable bytes, a program that reads back but does not compile (another program's in
    # its place) and an unreadable structure: each is reported, traced again and stored anew.
    programs = tmp_path / "programs"
    first = train(TINY, tmp_path / "a", progress=False, program_dir=programs)
    (entry,) = [p for p in programs.iterdir() if not p.name.startswith(".")]
    breakages = {
        "chunk.bin": lambda: b"not a program",
        "evaluate.bin": lambda: (entry / "init.bin").read_bytes(),
        "trees.pkl": lambda: b"not a pickle",
    }
    for run, (name, broken) in enumerate(breakages.items()):
        bad = broken()
        (entry / name).write_bytes(bad)
        again = train(TINY, tmp_path / f"b{run}", progress=False, program_dir=programs)
        assert "ignored the unusable traced programs" in capsys.readouterr().err, name
        assert _numbers(again) == _numbers(first), name
        assert (entry / name).read_bytes() != bad, name  # stored anew


def test_a_program_export_refuses_is_compiled_as_usual(tmp_path, monkeypatch, capsys):
    def refuse(*_, **__):
        raise ValueError("custom call not exportable")

    monkeypatch.setattr(program_cache, "export_flat", refuse)
    records = train(TINY, tmp_path / "a", progress=False, program_dir=tmp_path / "programs")
    assert "cannot be kept (custom call not exportable)" in capsys.readouterr().err
    assert len(records) == 3
    assert not (tmp_path / "programs").exists() or not os.listdir(tmp_path / "programs")


def test_the_readme_install_can_serialise_the_stored_programs():
    """The programs are stored with ``jax.export``, whose serialisation needs ``flatbuffers``:
    it must be a dependency of the plain install (not only of an extra), and serialising and
    reading back an exported program must work in this environment."""
    from importlib import metadata

    from jax import export

    plain = [r for r in metadata.requires("td3-jax") or [] if "extra ==" not in r]
    assert any(r.replace("_", "-").lower().startswith("flatbuffers") for r in plain), plain
    shape = jax.ShapeDtypeStruct((3,), "float32")
    exported = export.export(jax.jit(lambda x: 2.0 * x + 1.0))(shape)
    restored = export.deserialize(bytearray(exported.serialize()))
    assert restored.call(jax.numpy.arange(3.0)).tolist() == [1.0, 3.0, 5.0]


def test_a_run_compiles_with_its_matmul_choice_on_a_gpu_and_plainly_elsewhere(monkeypatch):
    """``--matmuls cublas`` reaches the compile as XLA's Triton GEMM option on a GPU mesh;
    ``auto`` and a CPU mesh add no option (what every compile path of the run is given)."""
    from types import SimpleNamespace

    from td3_jax.common import upstream
    from td3_jax.runner import programs

    monkeypatch.delenv("XLA_FLAGS", raising=False)

    def source(platform: str, matmuls: str) -> SimpleNamespace:
        devices = np.array([SimpleNamespace(platform=platform)])
        mesh = SimpleNamespace(devices=devices)
        return SimpleNamespace(mesh=mesh, cfg=TrainConfig(matmuls=matmuls))

    assert programs.compile_options(source("gpu", "cublas")) == {upstream.XLA_TRITON_GEMM: False}
    assert programs.compile_options(source("gpu", "auto")) == {}
    assert programs.compile_options(source("cpu", "cublas")) == {}


def test_every_compile_path_of_a_run_gets_its_compile_options(tmp_path, monkeypatch):
    """Options no XLA knows make the compile fail on every path (traced in this process and
    stored nowhere, traced and stored, read back from the store): each one compiles with what
    ``programs.compile_options`` gives (a CPU rejects unknown option names too)."""
    from td3_jax.runner import programs

    population, mesh = build.members(TINY), make_mesh(None)
    compiled(find(TINY, population, mesh, tmp_path / "stored"))  # a stored entry to read back
    monkeypatch.setattr(programs, "compile_options", lambda source: {"no_such_option": 1})
    for directory in (None, tmp_path / "fresh", tmp_path / "stored"):
        source = find(TINY, population, mesh, directory)
        with pytest.raises(Exception, match="no_such_option"):
            compiled(source)


def test_traced_runs_once_without_a_store():
    """Without a store (the programs jitted and compiled as usual) ``traced`` runs once too,
    after the room check."""
    source, order = find(TINY, build.members(TINY), make_mesh(None), None), []
    compiled(source, check=lambda _: order.append("check"), traced=lambda _: order.append("traced"))
    assert source.stored is None and order == ["check", "traced"]


@pytest.mark.parametrize("store", [False, True])
def test_traced_runs_once_every_compile_is_handed_over_and_before_any_is_waited_for(
    tmp_path, monkeypatch, store
):
    """Without a store, then traced and stored, then read back: ``traced`` runs once each time,
    after every compile is submitted and before the first is waited for."""
    events = []
    real_background, real_result = programs.in_background, programs.result
    monkeypatch.setattr(programs, "in_background",
                        lambda *a, **k: events.append("submit") or real_background(*a, **k))
    monkeypatch.setattr(programs, "result", lambda *a: events.append("wait") or real_result(*a))
    population, mesh = build.members(TINY), make_mesh(None)
    for origin in ("traced", "stored") if store else ("plain",):
        events.clear()
        source = find(TINY, population, mesh, tmp_path / "programs" if store else None)
        compiled(source, traced=lambda _: events.append("traced"))
        at = events.index("traced")
        assert events.count("traced") == 1 and events.count("submit") >= 3, (origin, events)
        assert "wait" not in events[:at] and "submit" not in events[at:], (origin, events)


def test_traced_runs_once_where_stored_programs_are_given_up(tmp_path, monkeypatch):
    """Stored programs that read back but fail to compile are traced again: ``traced`` still
    runs once, after those are handed over."""
    population, mesh = build.members(TINY), make_mesh(None)
    compiled(find(TINY, population, mesh, tmp_path / "programs"))  # (stores them)

    def failing(*_):
        raise RuntimeError("a stored program that does not compile")

    monkeypatch.setattr(programs, "_stored_programs", failing)
    source, calls = find(TINY, population, mesh, tmp_path / "programs"), []
    assert source.stored is not None
    compiled(source, traced=lambda _: calls.append(source.program is not None))
    assert calls == [False]  # (once, where the stored programs were still held)
