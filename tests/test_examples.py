"""The examples run as a user runs them: ``examples/custom_loop.py``, a TD3 loop written from
the public pieces only, learns Pendulum."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from examples import custom_loop

EXAMPLE = Path(custom_loop.__file__)


def _names_td3_jax(node: ast.Import | ast.ImportFrom) -> bool:
    if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("td3_jax"):
        return True
    return any(alias.name.startswith("td3_jax") for alias in node.names)


def test_the_custom_loop_uses_only_the_public_api():
    """Its only td3_jax import is ``import td3_jax as tj``, and every ``tj.X`` it names is in
    ``td3_jax.__all__``."""
    import td3_jax

    tree = ast.parse(EXAMPLE.read_text())
    imports = [node for node in ast.walk(tree) if isinstance(node, ast.Import | ast.ImportFrom)]
    ours = [node for node in imports if _names_td3_jax(node)]
    assert [(n.names[0].name, n.names[0].asname) for n in ours] == [("td3_jax", "tj")]
    used = {node.attr for node in ast.walk(tree)
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
            and node.value.id == "tj"}  # fmt: skip
    assert used and used <= set(td3_jax.__all__), used - set(td3_jax.__all__)


@pytest.mark.slow
def test_the_custom_loop_learns_pendulum():
    """A random policy scores about -1,200 to -1,500 on Pendulum and a swing-up about -150; the
    loop's policy passes -400 within 16k env steps (about a minute on 2 cores)."""
    returns = custom_loop.train(total_steps=16_000, seed=0)
    assert returns[0] < -900  # the untrained actor does not swing up
    assert max(returns[-2:]) > -400, returns


@pytest.mark.timeout(600)
@pytest.mark.processes
def test_the_two_process_example_trains_one_run_in_both_processes(tmp_path):
    """``examples/two_processes.py`` started twice on CPUs, as its docstring says: both
    processes end with the same records (one run, its evaluation averaged over both)."""
    import os

    from td3_jax.cli.local_processes import free_port

    example = Path(custom_loop.__file__).with_name("two_processes.py")
    flags = ["--coordinator", f"localhost:{free_port()}", "--out", str(tmp_path / "run"),
             "--total-steps", "4000"]  # fmt: skip
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    procs, outs = _both_processes(example, flags, env)
    assert [proc.returncode for proc in procs] == [0, 0], [err[-2000:] for _, err in outs]
    said = [out.strip().splitlines()[-1] for out, _ in outs]
    assert said[0].startswith("process 0: eval return ") and said[1].startswith("process 1: ")
    assert said[0].split(": ", 1)[1] == said[1].split(": ", 1)[1]
    records = (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()
    assert '"env_steps": 4000,' in records[-1]  # (the whole run, written once)
    flags[1] = f"localhost:{free_port()}"  # (again into the same folder: refused in one line)
    procs, outs = _both_processes(example, flags, env)
    assert [proc.returncode for proc in procs] == [1, 1]
    for i, (_, err) in enumerate(outs):
        assert err.strip().splitlines()[-1].startswith(f"process {i}: {tmp_path / 'run'} "
                                                       "already holds a run"), err[-2000:]
        assert "Traceback" not in err


def _both_processes(example: Path, flags: list[str], env: dict) -> tuple[list, list]:
    """Both processes of the example run to their end: ``(processes, [(stdout, stderr)])``."""
    import subprocess
    import sys

    procs = [subprocess.Popen([sys.executable, str(example), "--process-id", str(i), *flags],
                              env=env, text=True, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE) for i in (0, 1)]  # fmt: skip
    try:
        return procs, [proc.communicate(timeout=500) for proc in procs]
    finally:
        for proc in procs:
            proc.kill()
