"""The tests' shared tiny config (tests/configs.py) against the tiny flags (tests/support.py):
the command line given ``TINY_FLAGS`` trains exactly ``tiny_config()``."""

from __future__ import annotations

import pytest
from configs import tiny_config
from support import TINY_FLAGS

from td3_jax.cli import app as cli
from td3_jax.config.schema import validate
from td3_jax.runner import run as run_module


def test_the_cli_trains_tiny_config_from_the_tiny_flags(tmp_path, monkeypatch, capsys):
    """``train`` is stopped before anything compiles; the config it was handed is kept."""
    real_train, handed = run_module.train, []

    def train_stopped_at_once(cfg, *args, stop, **kwargs):
        handed.append(cfg)
        stop.set()
        return real_train(cfg, *args, stop=stop, **kwargs)

    monkeypatch.setattr(run_module, "train", train_stopped_at_once)
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as exit_:
        cli.main(["train", *TINY_FLAGS, "--out", str(out), "--quiet", "--compile-cache", "off"])
    capsys.readouterr()
    assert exit_.value.code == 130 and len(handed) == 1
    assert handed[0] == tiny_config()


def test_an_override_replaces_one_value_of_a_copy():
    small = tiny_config(seed=3, hidden_sizes=(8,))
    assert (small.seed, small.hidden_sizes, small.num_envs, small.total_steps) == (3, (8,), 4, 128)
    assert (tiny_config().seed, tiny_config().hidden_sizes) == (7, (16, 16))  # (shared: unchanged)
    assert validate(small) is small
    with pytest.raises(TypeError, match="no_such_field"):
        tiny_config(no_such_field=1)
