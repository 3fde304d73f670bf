"""td3-jax: TD3 and DDPG on thousands of vectorised environments, in compiled JAX programs.

The public, stable API is the names of ``__all__``::

    import jax
    import td3_jax as tj

    agent = tj.td3(tj.TD3Config(), observation_size=3, action_size=1)
    state = agent.init(jax.random.key(0))
    state, metrics = agent.update(state, batch, jax.random.key(1))   # batch: a tj.Transition
    ring = tj.replay.add(tj.replay.init(10_000, example_transition), transitions)

    train = tj.make_train(tj.TrainConfig(env="gymnax/Pendulum-v1"))   # pure: jit, vmap it
    final_state, metrics = jax.jit(train)(tj.key_for_seed(0))
    records = tj.train(tj.TrainConfig(), "runs/pendulum")           # the host loop, on disk

Everything else (``td3_jax.core``, ``td3_jax.runner``, ...) is importable but may change from one
version to the next. Names load on first use, so ``import td3_jax`` is cheap and the NumPy-only
policy reader :mod:`td3_jax.tools.policy_file` works where JAX is not installed.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.2.0"

#: Public name -> (module, attribute; None for the module itself).
_PUBLIC: dict[str, tuple[str, str | None]] = {
    "td3": ("td3_jax.core.td3", "td3"),
    "ddpg": ("td3_jax.core.td3", "ddpg"),
    "TD3Config": ("td3_jax.core.td3", "TD3Config"),
    "DDPGConfig": ("td3_jax.core.td3", "DDPGConfig"),
    "Agent": ("td3_jax.core.types", "Agent"),
    "AgentState": ("td3_jax.core.types", "AgentState"),
    "Transition": ("td3_jax.core.types", "Transition"),
    "replay": ("td3_jax.core.replay", None),
    "noise": ("td3_jax.core.noise", None),
    "stats": ("td3_jax.core.stats", None),
    "envs": ("td3_jax.envs", None),
    "TrainConfig": ("td3_jax.config.schema", "TrainConfig"),
    "make_train": ("td3_jax.config.build", "make_train"),
    "key_for_seed": ("td3_jax.core.training", "key_for_seed"),
    "train": ("td3_jax.runner.run", "train"),
}

__all__ = sorted(_PUBLIC)

#: Public functions whose errors name TrainConfig's fields and their own arguments
#: (``total_steps=2000``, ``resume=True``), where the command line's name its flags.
_FIELD_NAMED = ("make_train", "train")


def __getattr__(name: str) -> Any:
    """Loads a public name on first use (PEP 562): a lazy import that keeps JAX, Flax and
    orbax out of ``import td3_jax`` until a name that needs them is asked for."""
    if name not in _PUBLIC:
        raise AttributeError(f"module 'td3_jax' has no attribute {name!r}")
    module_name, attribute = _PUBLIC[name]
    module = importlib.import_module(module_name)
    value = module if attribute is None else getattr(module, attribute)
    if name in _FIELD_NAMED:
        value = importlib.import_module("td3_jax.config.python_names").with_field_names(value)
        value.__module__, value.__qualname__ = __name__, name  # (pickled as td3_jax.NAME)
    return globals().setdefault(name, value)  # (two threads at once: both get one object)


def __dir__() -> list[str]:
    """The public names, the subpackages imported so far (``td3_jax.runner``, ...) and the
    module's own dunders; not what the package imports for itself (``Any``, ``importlib``)."""
    own = (name for name, value in globals().items()
           if name.startswith("__") or getattr(value, "__name__", "") == f"{__name__}.{name}")
    return sorted({*__all__, *own})
