"""Start-up: what a run compiles, when, and what a second identical run compiles (nothing).

Counts come from JAX's own monitoring events: every XLA compilation (or persistent-cache
lookup) records ``/jax/core/compile/backend_compile_duration``; a persistent-cache miss records
``/jax/compilation_cache/cache_misses``.
"""

from __future__ import annotations

import json
import subprocess
import sys

import jax
import pytest

from td3_jax.config.schema import TrainConfig
from td3_jax.runner import run as run_module
from td3_jax.runner.logger import read_metrics

COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"

# 64 iterations of 2 environments per chunk: the first chunk is split (8 + 56 iterations).
SPLIT = TrainConfig(
    env="gymnax/Pendulum-v1",
    hidden_sizes=(8,),
    num_envs=2,
    eval_envs=2,
    episode_length=16,
    eval_every=128,
    total_steps=3 * 128,
    updates_per_iter=1,
    batch_size=8,
    buffer_size=256,
    warmup_steps=16,
)


@pytest.fixture
def compile_events():
    """Names of the compile events recorded while the test runs."""
    events: list[str] = []
    listener = lambda name, *_, **__: events.append(name) if name == COMPILE_EVENT else None
    jax.monitoring.register_event_duration_secs_listener(listener)
    yield events
    jax.monitoring.unregister_event_duration_listener(listener)


def test_nothing_compiles_after_the_start(tmp_path, monkeypatch, compile_events):
    # Every chunk call (the early part, the rest of the first chunk, later chunks) with its
    # evaluation compiles nothing; from the second chunk on (checkpoints included) nothing does.
    calls = []
    real = run_module._chunk_and_record

    def counted(run, compiled, state, iterations):
        before = len(compile_events)
        out = real(run, compiled, state, iterations)
        calls.append((iterations, before, len(compile_events)))
        return out

    monkeypatch.setattr(run_module, "_chunk_and_record", counted)
    run_module.train(SPLIT, tmp_path / "run", progress=False)
    assert SPLIT.early_iterations == 8 and SPLIT.iters_per_chunk == 64
    assert [c[0] for c in calls] == [8, 56, 64, 64]
    assert [c[2] - c[1] for c in calls] == [0, 0, 0, 0], calls
    assert len(compile_events) == calls[2][1], "compiled something after the first chunk"
    steps = [r["env_steps"] for r in read_metrics(tmp_path / "run" / "metrics.jsonl")]
    assert steps == [16, 128, 256, 384]


def test_the_early_evaluation_does_not_change_the_run(tmp_path):
    # Splitting the first chunk only adds a record: the evaluations are the same numbers, and so
    # are the later chunks' metrics (the first chunk's second record averages its second part).
    split = run_module.train(SPLIT, tmp_path / "split", progress=False)
    whole = run_module.train(
        TrainConfig(**{**SPLIT.__dict__, "early_evaluation": False}),
        tmp_path / "whole",
        progress=False,
    )
    assert [r["env_steps"] for r in whole] == [128, 256, 384]
    for a, b in zip(split[1:], whole, strict=True):
        assert a["eval_return_mean"] == pytest.approx(b["eval_return_mean"], rel=1e-5)
    for a, b in zip(split[2:], whole[1:], strict=True):
        for key in ("critic_loss", "actor_loss", "train_return_mean"):
            assert a[key] == pytest.approx(b[key], rel=1e-5, abs=1e-6), key


COUNTING_RUN = """
import json, sys, jax
counts = {"compiles": 0, "misses": 0, "hits": 0}
def on_duration(name, *_, **__):
    counts["compiles"] += name == "COMPILE_EVENT"
def on_event(name, *_, **__):
    counts["misses"] += name == "/jax/compilation_cache/cache_misses"
    counts["hits"] += name == "/jax/compilation_cache/cache_hits"
jax.monitoring.register_event_duration_secs_listener(on_duration)
jax.monitoring.register_event_listener(on_event)
from td3_jax.config import build
made = build.make_env
def counted_make_env(*args, **kwargs):
    counts["envs_made"] = counts.get("envs_made", 0) + 1
    return made(*args, **kwargs)
build.make_env = counted_make_env
from td3_jax.cli.app import main
try:
    main(sys.argv[1:])
finally:
    print("COUNTS " + json.dumps(counts))
""".replace("COMPILE_EVENT", COMPILE_EVENT)


def _counted_train(out, cache) -> dict[str, int]:
    args = ["train", "--out", str(out), "--compile-cache", str(cache), "--num-envs", "2",
            "--eval-envs", "2", "--episode-length", "16", "--eval-every", "32",
            "--total-steps", "64", "--hidden-sizes", "8", "--batch-size", "8",
            "--warmup-steps", "16", "--updates-per-iter", "1", "--quiet"]  # fmt: skip
    done = subprocess.run([sys.executable, "-c", COUNTING_RUN, *args], capture_output=True,
                          text=True, timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    line = [x for x in done.stdout.splitlines() if x.startswith("COUNTS ")][-1]
    return json.loads(line.removeprefix("COUNTS "))


@pytest.mark.subprocess
def test_a_second_identical_run_compiles_nothing(tmp_path):
    # ... and makes no environment: its programs come from the cache's programs/ folder, and
    # only the compiles of the first run's environment creation are not looked up again.
    first = _counted_train(tmp_path / "a", tmp_path / "cache")
    second = _counted_train(tmp_path / "b", tmp_path / "cache")
    assert first["compiles"] > 0 and first["misses"] > 0, first
    assert first["envs_made"] == 1, first
    assert second["misses"] == 0, f"the second run compiled again: {second}"
    assert "envs_made" not in second, f"the second run made its environment: {second}"
    assert 3 <= second["hits"] <= first["misses"], (first, second)


@pytest.mark.subprocess
def test_a_cache_filled_without_the_size_cap_still_takes_new_entries(tmp_path):
    # A cache directory written before the 4 GB cap (entries without access-time files) is
    # stamped, so the capped cache can evict and write: the run fills it as a fresh one would.
    cache = tmp_path / "cache"
    cache.mkdir()
    (cache / "jit_old-0123-cache").write_bytes(b"an entry from an uncapped cache")
    counts = _counted_train(tmp_path / "a", cache)
    assert counts["misses"] > 0
    assert (cache / "jit_old-0123-atime").exists()
    written = [p for p in cache.glob("*-cache") if p.name != "jit_old-0123-cache"]
    assert len(written) == counts["misses"], (counts, sorted(p.name for p in written))


def test_the_metrics_logger_does_not_import_pytorch(tmp_path):
    # tensorboardX's writer imports torch when it can (seconds at every start on a machine with
    # PyTorch); a stand-in torch package on the path records whether anything imported it.
    fake = tmp_path / "site" / "torch"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text("import builtins\nbuiltins.TORCH_IMPORTED = True\n")
    script = (
        "import builtins, sys\n"
        f"sys.path.insert(0, {str(tmp_path / 'site')!r})\n"
        "from td3_jax.runner.logger import MetricsLogger\n"
        f"logger = MetricsLogger({str(tmp_path / 'run')!r})\n"
        "logger.write({'env_steps': 1, 'eval_return_mean': 2.0})\n"
        "logger.close()\n"
        "assert not getattr(builtins, 'TORCH_IMPORTED', False), 'torch was imported'\n"
        "import torch\n"  # and torch stays importable afterwards
        "assert builtins.TORCH_IMPORTED\n"
    )
    (tmp_path / "run").mkdir()
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
