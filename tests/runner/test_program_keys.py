"""The traced-program store's key for settings left to the algorithm: a run that leaves its
hidden widths to the algorithm (a library caller's ``hidden_sizes=None``) and one that names
them, as its config.json and so a resume from the command line do, share their programs."""

from __future__ import annotations

import dataclasses

import pytest
from test_program_cache import TINY as SMALL

from td3_jax.config import build
from td3_jax.config.schema import TrainConfig
from td3_jax.runner import program_cache
from td3_jax.runner.run import train
from td3_jax.runner.rundir import load_config
from td3_jax.runner.sharding import make_mesh

# test_program_cache.py's tiny run, its widths left to the algorithm (TD3 400 300, DDPG 256 256).
TINY = dataclasses.replace(SMALL, hidden_sizes=None, total_steps=2 * 32)


def _key(cfg: TrainConfig) -> str:
    return program_cache.fingerprint(cfg, [()], make_mesh(None))


def test_widths_left_to_the_algorithm_key_as_the_algorithms_own():
    assert _key(TINY) == _key(dataclasses.replace(TINY, hidden_sizes=(400, 300)))
    assert _key(TINY) != _key(dataclasses.replace(TINY, hidden_sizes=(256, 256)))
    ddpg = dataclasses.replace(TINY, algo="ddpg")
    assert _key(ddpg) == _key(dataclasses.replace(ddpg, hidden_sizes=(256, 256)))
    assert _key(ddpg) != _key(dataclasses.replace(ddpg, hidden_sizes=(400, 300)))


def _refuse(*_, **__):
    raise AssertionError("the environment was made: the programs were traced again")


@pytest.mark.runs
def test_a_library_run_resumed_with_its_saved_config_traces_nothing(tmp_path, monkeypatch):
    """The resume reads config.json (widths 400 300, as the CLI's --resume does) and finds
    the programs the library run (widths None) stored."""
    programs, out = tmp_path / "programs", tmp_path / "run"
    train(TINY, out, progress=False, program_dir=programs, stop_after_chunks=1)
    saved = load_config(out)
    assert saved.hidden_sizes == (400, 300)
    monkeypatch.setattr(build, "make_env", _refuse)
    records = train(saved, out, progress=False, program_dir=programs, resume=True)
    assert [r["env_steps"] for r in records] == [64]
