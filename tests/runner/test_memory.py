"""The memory a run needs and has: the estimate of the training programs' working memory
against XLA's own analysis of the compiled programs, the memory available now, and the one
line that refuses a run before anything is allocated, naming the flags that shrink the part
that needs most."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import pytest
from configs import tiny_config

from td3_jax.common.errors import ConfigError
from td3_jax.config.build import make_population, members
from td3_jax.runner import memory, programs, sharding
from td3_jax.runner.memory import size_text, state_bytes, working_bytes, working_total


def abstract(cfg):
    return make_population(cfg, members(cfg)).abstract_state


def test_available_memory_is_meminfos_memavailable():
    """The host's memory available now, not its total: /proc/meminfo's MemAvailable."""
    fields = dict(line.split(":", 1) for line in Path("/proc/meminfo").read_text().splitlines())
    total = int(fields["MemTotal"].split()[0]) * 1024
    available = memory.available_memory()
    assert available is not None and 0 < available <= total
    # (read again: other processes may have moved it meanwhile, by far less than a GB)
    assert abs(available - int(fields["MemAvailable"].split()[0]) * 1024) < 1e9
    limit, what = sharding.memory_of(jax.devices()[0])
    assert abs(limit - available) < 1e9 and what == "this machine's memory has"


def test_a_devices_available_memory_is_its_limit_less_what_it_holds():
    class Gpu:
        platform, device_kind = "gpu", "Fake GPU"

        def memory_stats(self):
            return {"bytes_limit": 2_000_000, "bytes_in_use": 1_500_000}

    assert sharding.memory_of(Gpu()) == (500_000, "each Fake GPU's memory has")


@pytest.mark.parametrize(
    "overrides",
    [dict(), dict(batch_size=128, num_envs=32), dict(hidden_sizes=(64, 64), eval_envs=64)],
)
def test_the_working_memory_estimate_covers_xlas_analysis_of_the_programs(overrides):
    """XLA's memory analysis of the compiled chunk and evaluation (their temporaries) is at
    most the estimate, and the estimate at most 4 times it plus a MB: on the safe side, and
    not so far that it refuses runs that fit."""
    cfg = tiny_config(**overrides)
    population = make_population(cfg, members(cfg))
    jitted = programs.jitted(population, sharding.make_mesh(1))
    compiled = programs.compile_ahead(jitted, population, with_init=False)
    chunk = compiled.chunk.memory_analysis().temp_size_in_bytes
    evaluation = compiled.evaluate.memory_analysis().temp_size_in_bytes
    measured = max(chunk, evaluation)
    estimate = working_total(working_bytes(population.abstract_state, cfg))
    assert measured <= estimate <= 4 * measured + 1e6, (measured, estimate)


def test_the_working_memory_grows_with_what_makes_it():
    """Each part of the estimate follows its own flags: the physics the environments, the
    updates the batch, the evaluation its episodes (none when it runs in the chunk)."""
    base = tiny_config()
    parts = working_bytes(abstract(base), base)
    envs = dataclasses.replace(base, num_envs=8)
    assert working_bytes(abstract(envs), envs)["physics"] == 2 * parts["physics"]
    batch = dataclasses.replace(base, batch_size=32)
    assert working_bytes(abstract(batch), batch)["updates"] == 2 * parts["updates"]
    episodes = dataclasses.replace(base, eval_envs=4)
    assert working_bytes(abstract(episodes), episodes)["evaluation"] == 2 * parts["evaluation"]
    # the update's activations: 2 floats per batch row and unit of every layer (16 + 16 + 1
    # units of the actor, twice that of the two critics)
    assert parts["updates"] == 4 * 2 * 16 * 3 * (16 + 16 + 1)


def check(state, available: int, working=None, resident=False, monkeypatch=None):
    monkeypatch.setattr(sharding, "memory_of", lambda device: (available, "the test's memory has"))
    sharding.check_memory(state, sharding.make_mesh(1), working, resident=resident)


def test_the_refusal_names_what_is_needed_what_is_available_and_what_shrinks_it(monkeypatch):
    cfg = tiny_config()
    state = abstract(cfg)
    working = working_bytes(state, cfg)
    need = state_bytes(state) + working_total(working)
    check(state, need, working, monkeypatch=monkeypatch)  # exactly enough: accepted
    with pytest.raises(ConfigError) as refused:
        check(state, need - 1, working, monkeypatch=monkeypatch)
    line = str(refused.value)
    assert "\n" not in line
    assert f"the train state needs {size_text(state_bytes(state))} per device" in line
    assert f"about {size_text(working_total(working))} of working memory" in line
    assert f"{size_text(need)} in all, but the test's memory has {size_text(need - 1)} " in line
    # a restored train state is in memory already: only the working memory is still to come
    check(state, working_total(working), working, resident=True, monkeypatch=monkeypatch)
    with pytest.raises(ConfigError, match=r"^the training programs need about .* beside the "
                                          r"restored train state \(the replay ring"):  # fmt: skip
        check(state, working_total(working) - 1, working, resident=True, monkeypatch=monkeypatch)


@pytest.mark.parametrize(
    ("part", "advice"),
    [
        ("physics", "fewer --num-envs"),
        ("updates", "a smaller --batch-size"),
        ("evaluation", "fewer --eval-envs"),
    ],
)
def test_the_advice_is_the_flag_of_the_part_that_needs_most(monkeypatch, part, advice):
    state = abstract(tiny_config())
    working = {"physics": 0, "updates": 0, "networks": 0, "evaluation": 0, part: 10**9}
    with pytest.raises(ConfigError, match=rf"; use {advice}$"):
        check(state, 1, working, monkeypatch=monkeypatch)


def test_a_huge_ring_is_shrunk_by_buffer_size_alone(monkeypatch):
    """The ring's rows are --buffer-size (or the run's length): fewer environments do not
    shrink it, so they are not advised."""
    big = tiny_config(buffer_size=100_000, total_steps=100_000, eval_every=100_000)
    state = abstract(big)
    with pytest.raises(ConfigError, match=r"; use a smaller --buffer-size$"):
        check(state, 1, working_bytes(state, big), monkeypatch=monkeypatch)
