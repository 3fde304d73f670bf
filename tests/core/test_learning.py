"""It learns: whole training runs of the presets from the command line (minutes on a CPU).

The runs are real ``td3-jax train`` processes. Their wall time is mostly XLA compilation, which
is single-threaded, so every run a test run selects is started at once when the first learning
test needs it (each test then waits for its own), and a run nobody selected never starts.
Returns are deterministic for a seed on a given installation; the thresholds leave a wide margin
over the values measured when the tests were written (quoted next to each assertion).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from support import optimised_env

pytestmark = pytest.mark.slow

TIMEOUT_S = 600

# Random policy on gymnax/Pendulum-v1 (200-step episodes): about -1200.
PENDULUM_RANDOM = -1200.0
# A reference DDPG implementation's own log on the same experiment: the 10-episode average ends
# around -590, never beats -457.
REFERENCE_DDPG_BEST = -457.0
# brax/inverted_pendulum (reward 1 per step alive; its own 1000-step episodes, so at most 1000),
# measured with the trainer's evaluate and with uniform random actions (with 200-step episodes,
# which no such policy outlives): freshly initialised deterministic policy: 32.3 on average over
# 16 episodes (19 to 52); uniform random actions: 5.8 on average over 64 episodes (2 to 19).
INVERTED_PENDULUM_MAX = 1000.0
INVERTED_PENDULUM_FRESH_POLICY = 32.3
INVERTED_PENDULUM_RANDOM = 5.8

RUNS = {
    # TD3, 16 environments, (256, 256), the preset's own 20k steps: README's main job.
    "pendulum": ["--preset", "pendulum"],
    # The DDPG Pendulum baseline (OU noise, batch 128, one Pendulum, 20k steps); measured: last
    # three evaluations -124, -124, -150.
    "ddpg-pendulum": ["--preset", "ddpg-pendulum"],
    # TD3 on MJX, 16 environments, 32 updates per iteration, the preset's own 20,480 steps
    # (about a minute on 2 CPU cores, half of it compiling MJX).
    "inverted-pendulum": ["--preset", "inverted-pendulum"],
}
TEST_RUN = {
    "test_td3_learns_pendulum": "pendulum",
    "test_ddpg_pendulum_preset_beats_the_reference_ddpg": "ddpg-pendulum",
    "test_td3_learns_mjx_inverted_pendulum": "inverted-pendulum",
}


class Run:
    def __init__(self, name: str, out: Path):
        self.name, self.out = name, out
        self.log = out.parent / f"{name}.log"
        cmd = [sys.executable, "-m", "td3_jax", "train", *RUNS[name], "--out", str(out)]
        self._log_file = self.log.open("w")
        self.proc = subprocess.Popen(
            [*cmd, "--quiet"],
            stdout=self._log_file,
            stderr=subprocess.STDOUT,
            text=True,
            env=optimised_env(),
        )

    def records(self) -> list[dict]:
        try:
            code = self.proc.wait(timeout=TIMEOUT_S)
        finally:
            self._log_file.close()
        output = self.log.read_text()
        assert code == 0, output[-3000:]
        assert "Traceback" not in output, output[-3000:]
        lines = (self.out / "metrics.jsonl").read_text().splitlines()
        return [json.loads(line) for line in lines if line.strip()]

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self._log_file.close()


@pytest.fixture(scope="module")
def runs(request, tmp_path_factory):
    """The learning runs of the selected tests, all started together."""
    collected = request.node.listchain()[0].items  # (the run's selected tests)
    selected = {item.originalname for item in collected if item.module.__name__ == __name__}
    base = tmp_path_factory.mktemp("learning")
    started = {
        TEST_RUN[t]: Run(TEST_RUN[t], base / TEST_RUN[t]) for t in sorted(selected) if t in TEST_RUN
    }
    yield started
    for run in started.values():
        run.stop()


def returns(records: list[dict]) -> list[float]:
    return [r["eval_return_mean"] for r in records]


def test_td3_learns_pendulum(runs):
    records = runs["pendulum"].records()
    curve = returns(records)
    assert records[-1]["env_steps"] == 20_000
    assert records[-1]["algo"] == "td3"
    # measured: -1408, -1036, -169, -347, -107 (seeds 1-4 ended at -158, -130, -178, -120)
    assert curve[-1] > -400, curve
    assert curve[-1] > curve[0] + 500, curve
    assert curve[-1] > PENDULUM_RANDOM + 800, curve


def test_ddpg_pendulum_preset_beats_the_reference_ddpg(runs):
    records = runs["ddpg-pendulum"].records()
    curve = returns(records)
    # the early evaluation (an eighth of the first 2000-iteration chunk), then every 2000 steps
    assert [r["env_steps"] for r in records] == [250, *range(2_000, 20_001, 2_000)]
    assert records[-1]["algo"] == "ddpg"
    assert all(r["eval_return_std"] >= 0 for r in records)
    # measured: -198, -195, -147, -144, -182, -179, -155, -124, -124, -150
    last3 = sum(curve[-3:]) / 3
    assert last3 > -400, curve
    assert last3 > REFERENCE_DDPG_BEST, curve
    assert max(curve) > REFERENCE_DDPG_BEST + 200, curve


def test_td3_learns_mjx_inverted_pendulum(runs):
    records = runs["inverted-pendulum"].records()
    curve = returns(records)
    assert records[-1]["env"] == "brax/inverted_pendulum"
    assert records[-1]["env_steps"] == 20_480
    # measured (seed 0): 85, 43, 1000, 1000, 1000 (seeds 1 and 2 of a 3-seed run: 63, 126,
    # 1000, 1000, 1000 and 1000, 78, 1000, 1000, 1000). On 2026-11-26 the same code (that of
    # the measurement above, and today's) gave seed 0 13 (the early evaluation), 1000, 891,
    # 1000, 1000, 354 with the same package versions (the cause, rounding on another CPU or a
    # dependency, not found): one evaluation late in a run may dip, so two of the last three
    # must reach half the maximum return (15x a fresh policy's, 85x random actions').
    assert max(curve) <= INVERTED_PENDULUM_MAX + 1e-6
    assert sorted(curve[-3:])[1] >= INVERTED_PENDULUM_MAX / 2, curve
    assert sum(curve[-3:]) / 3 > 500, curve
