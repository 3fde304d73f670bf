"""The library's public surface: every module's ``__all__`` names what it defines, and the
README's Python quickstart uses only the top-level public names (``import td3_jax as tj``)."""

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


def python_section() -> str:
    """The README's Python quickstart: from its heading to the next one."""
    text = README.read_text()
    start = text.index("## Python")
    return text[start : text.index("\n## ", start + 1)]


def test_the_readme_python_section_uses_top_level_public_names_only():
    """The quickstart imports ``td3_jax as tj`` and nothing deeper; every ``tj.X`` it uses is in
    ``td3_jax.__all__``, and every ``tj.M.X`` of a public module ``M`` in ``M.__all__``."""
    code = "\n".join(re.findall(r"```python\n(.*?)```", python_section(), re.S))
    imports = re.findall(r"^\s*(?:from|import)\s+(td3_jax\S*)(.*)$", code, re.M)
    assert imports and all(name == "td3_jax" and rest.strip() == "as tj" for name, rest in imports)
    assert "td3_jax." not in code  # (no module below the public surface)
    used = set(re.findall(r"\btj\.([A-Za-z_]\w*)(?:\.([A-Za-z_]\w*))?", code))
    assert {first for first, _ in used} >= {"TrainConfig", "make_train", "key_for_seed", "td3"}
    for first, second in used:
        assert first in td3_jax.__all__, f"tj.{first} is not public"
        inner = getattr(td3_jax, first)
        if second and inspect_is_module(inner):
            assert second in inner.__all__, f"tj.{first}.{second} is not public"


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


def test_key_for_seed_refuses_a_seed_jax_would_wrap_and_takes_a_traced_one():
    """JAX keeps 32 bits of a seed: -1 would be 2**32 - 1's key; a vmapped seed is not
    checked (it is not known yet) and gives each seed's own key."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    assert np.array_equal(td3_jax.key_for_seed(7), jax.random.PRNGKey(7))
    for seed in (-1, 2**32, np.int64(-1), np.array(-1), jnp.array(-1)):
        with pytest.raises(ValueError, match=r"^seed -?\d+ must be in \[0, 4294967295\]"):
            td3_jax.key_for_seed(seed)
    with pytest.raises(TypeError, match=r"^seed must be a whole number, got 1\.5$"):
        td3_jax.key_for_seed(1.5)
    keys = jax.vmap(td3_jax.key_for_seed)(jnp.arange(3))
    assert np.array_equal(keys[2], jax.random.PRNGKey(2))


def test_each_agent_builder_refuses_the_other_s_config():
    with pytest.raises(TypeError, match=r"^tj\.ddpg takes a DDPGConfig, got TD3Config; tj\.td3 "):
        td3_jax.ddpg(td3_jax.TD3Config(), 3, 1)
    with pytest.raises(TypeError, match=r"^tj\.td3 takes a TD3Config, got DDPGConfig; tj\.ddpg "):
        td3_jax.td3(td3_jax.DDPGConfig(), 3, 1)
    with pytest.raises(TypeError, match=r"^tj\.td3 takes a TD3Config, got dict$"):
        td3_jax.td3({}, 3, 1)


def test_dir_shows_the_public_names_not_the_modules_helpers():
    """Tab completion on ``td3_jax.`` offers ``__all__`` (loaded or not), not ``Any`` or
    ``importlib``, which the package imports for itself."""
    import td3_jax.runner.run  # (a subpackage, once imported, is listed too)

    shown = [name for name in dir(td3_jax) if not name.startswith("_")]
    assert shown == sorted({*td3_jax.__all__, "runner"} | {
        name for name in ("cli", "common", "config", "core", "tools")
        if name in vars(td3_jax)})  # fmt: skip
    assert "__version__" in dir(td3_jax)
    assert not {"Any", "importlib", "annotations"} & set(dir(td3_jax))
