"""The library's public surface: every module's ``__all__`` names what it defines, and every
``td3_jax`` name the README's library section uses is public."""

from __future__ import annotations

import importlib
import pkgutil
import re
from pathlib import Path

import pytest

import td3_jax

README = Path(__file__).parents[1] / "README.md"
MODULES = sorted(
    m.name
    for m in pkgutil.walk_packages(td3_jax.__path__, "td3_jax.")
    if m.name != "td3_jax.__main__"  # runs the CLI when imported
)


@pytest.mark.parametrize("name", MODULES)
def test_every_module_has_an_all_naming_what_exists(name):
    module = importlib.import_module(name)
    assert hasattr(module, "__all__"), f"{name} says nothing of what is public (no __all__)"
    exported = module.__all__
    assert len(set(exported)) == len(exported), f"{name}.__all__ repeats a name"
    missing = [n for n in exported if not hasattr(module, n)]
    assert not missing, f"{name}.__all__ names what it does not define: {missing}"


def library_section() -> str:
    text = README.read_text()
    return text[text.index("## The library") : text.index("### Details that matter")]


def test_the_readme_library_section_uses_public_names_only():
    """``tj.X``, ``tj.M.X``, ``training.X`` and ``build.X`` in the section are in their module's
    __all__."""
    code = "\n".join(re.findall(r"```python\n(.*?)```", library_section(), re.S))
    used = set(re.findall(r"\b(tj|training|build)\.([A-Za-z_]\w*)(?:\.([A-Za-z_]\w*))?", code))
    assert len(used) > 10  # the section's two examples were read
    assert {("build", "make_spec", ""), ("build", "hyperparams", "")} <= used
    for prefix, first, second in used:
        module = td3_jax if prefix == "tj" else importlib.import_module(f"td3_jax.{prefix}")
        assert first in module.__all__, f"{prefix}.{first} is not public"
        inner = getattr(module, first)
        if second and inspect_is_module(inner):
            assert second in inner.__all__, f"{prefix}.{first}.{second} is not public"


def inspect_is_module(value) -> bool:
    return type(value).__name__ == "module"


def test_every_error_is_one_class_of_the_errors_module_with_its_exit_code():
    """The modules that raise an error re-export errors' class (one class, not a copy); bad
    input exits 2, a run stopped by what it computed exits 3."""
    from td3_jax import envs
    from td3_jax.common import errors, upstream
    from td3_jax.config import schema as config
    from td3_jax.runner import checkpoint, run
    from td3_jax.tools import export, render

    for module, name in [(config, "ConfigError"), (checkpoint, "CorruptCheckpointError"),
                         (envs, "UnknownEnvironmentError"), (envs, "MissingAssetsError"),
                         (envs, "EnvironmentOptionError"), (export, "ExportError"),
                         (run, "OutputWriteError"), (render, "GLUnavailableError"),
                         (run, "NonFiniteError"), (run, "PhysicsOverflowError"),
                         (upstream, "UpstreamChanged")]:  # fmt: skip
        assert getattr(module, name) is getattr(errors, name), name
        assert issubclass(getattr(errors, name), errors.Td3JaxError)
    assert errors.ExportError("x").exit_code == errors.CheckpointWriteError("x").exit_code == 2
    assert errors.NonFiniteError("x").exit_code == errors.PhysicsOverflowError("x").exit_code == 3
    assert isinstance(errors.UnknownEnvironmentError("x"), ValueError)  # as before the move
