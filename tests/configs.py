"""The tiny training config the tests share, as a library :class:`TrainConfig`.

:data:`TINY` holds the values of ``support.TINY_FLAGS`` (a run of 128 steps of 4 Pendulums in
two chunks of 64: one evaluation and checkpoint each), so a test that trains through the library
and one that trains through the command line build the same programs, which the test run's
compilation cache (tests/conftest.py) then compiles once. ``tests/config/test_tiny_config.py``
checks that the two stay equal.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from td3_jax.config.schema import TrainConfig

#: The fields ``support.TINY_FLAGS`` sets; every other field keeps its default.
TINY: dict[str, Any] = dict(
    env="gymnax/Pendulum-v1",
    num_envs=4,
    total_steps=128,
    eval_every=64,
    warmup_steps=32,
    batch_size=16,
    updates_per_iter=1,
    hidden_sizes=(16, 16),
    eval_envs=2,
    episode_length=16,
    seed=7,
    buffer_size=256,
)


def tiny_config(**overrides: Any) -> TrainConfig:
    """The smallest config that trains (:data:`TINY`), with ``overrides`` (field=value) replacing
    its values; a name that is not a :class:`TrainConfig` field raises ``TypeError``."""
    return dataclasses.replace(TrainConfig(**TINY), **overrides)
