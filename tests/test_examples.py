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
