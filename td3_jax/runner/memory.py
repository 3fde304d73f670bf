"""Sizes of train states in memory and on disk, an estimate of the training programs' working
memory beside them, the memory available now, and the flags that shrink each."""

from __future__ import annotations

import contextlib
import math
import os
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from td3_jax.config.schema import TrainConfig

#: Copies of the environment states a physics step holds at once (its input, its output and
#: the intermediates between): an estimate, on the safe side of MJX's step.
PHYSICS_COPIES = 4
#: Float32 activations per batch row and network unit that the gradient updates hold (the
#: forward and backward passes of the actor and both critics, with the targets): 1.9 measured
#: (XLA's memory analysis of Pendulum's chunk on a CPU, batches of 256 and 4096), rounded up.
UPDATE_ACTIVATIONS = 2
#: The share of the networks and their optimiser states the updates copy (0.17 to 0.27
#: measured as above), rounded up.
UPDATE_COPY = 0.5


def state_bytes(state: Any) -> int:
    """The bytes of every array in ``state`` (arrays or ``ShapeDtypeStruct``s): what a
    checkpoint of it holds, typed PRNG keys counted as their key data."""

    def nbytes(x: Any) -> int:
        if jnp.issubdtype(x.dtype, jax.dtypes.extended):
            x = jax.eval_shape(jax.random.key_data, x)
        return int(math.prod(x.shape)) * np.dtype(x.dtype).itemsize

    return sum(nbytes(x) for x in jax.tree.leaves(state))


def size_text(size: int) -> str:
    """``size`` bytes as text: in GB from 0.1 GB up, else in MB."""
    return f"{size / 1e9:.1f} GB" if size >= 1e8 else f"{size / 1e6:.1f} MB"


def available_memory() -> int | None:
    """Bytes of this machine's memory available now without swapping (``MemAvailable`` of
    /proc/meminfo, else the free physical pages), ``None`` where neither can be read."""
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    with contextlib.suppress(OSError, ValueError, AttributeError):
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    return None


def network_units(agent: Any) -> int:
    """Units of every layer of the actor and the critics, over every member and critic (the
    sizes of their bias vectors)."""
    leaves = jax.tree_util.tree_leaves_with_path((agent.actor_params, agent.critic_params))
    return sum(int(math.prod(x.shape)) for path, x in leaves
               if jax.tree_util.keystr(path).endswith("['bias']"))  # fmt: skip


def working_bytes(abstract_state: Any, cfg: TrainConfig, devices: int = 1) -> dict[str, int]:
    """An estimate of the training programs' working memory per device beside the train
    state (``[members, ...]`` shapes), by what needs it: ``physics`` (stepping the environment
    batch: :data:`PHYSICS_COPIES` of its states, in-chunk evaluation worlds included),
    ``updates`` (the gradient updates' activations, :data:`UPDATE_ACTIVATIONS` per batch row
    and network unit), ``networks`` (the updates' copy, :data:`UPDATE_COPY` of the networks
    and their optimiser states) and ``evaluation`` (the separate evaluation's environments,
    stepped after the chunk: 0 with ``eval_in_chunk``). The chunk holds the first three at
    once, the evaluation runs on its own: the programs need :func:`working_total` of them."""
    envs = state_bytes(abstract_state.env_state)
    worlds = math.prod(jax.tree.leaves(abstract_state.env_state.obs)[0].shape[:2])
    agent = abstract_state.agent
    members = int(jax.tree.leaves(agent)[0].shape[0]) if jax.tree.leaves(agent) else 1
    activations = 4 * UPDATE_ACTIVATIONS * cfg.batch_size * network_units(agent)
    evaluated = 0 if cfg.eval_in_chunk else members * cfg.eval_envs
    return {
        "physics": PHYSICS_COPIES * envs // devices,
        "updates": activations // devices,
        "networks": int(UPDATE_COPY * state_bytes(agent)),  # (replicated on every device)
        "evaluation": PHYSICS_COPIES * envs * evaluated // max(worlds, 1),
    }


def working_total(working: dict[str, int]) -> int:
    """The most of :func:`working_bytes`' parts in use at once: the chunk's (physics, updates
    and their copy of the networks), or the evaluation after it."""
    chunk = sum(working.get(part, 0) for part in ("physics", "updates", "networks"))
    return max(chunk, working.get("evaluation", 0))


#: The flags that shrink each part of :func:`working_bytes` (``networks``: those of
#: :func:`larger_network_advice`).
WORKING_ADVICE = {
    "physics": "fewer --num-envs",
    "updates": "a smaller --batch-size",
    "evaluation": "fewer --eval-envs",
}


def larger_network_advice(agent: Any) -> str:
    """``smaller --critic-hidden-sizes`` where the critics' parameters outweigh the actor's,
    else ``smaller --actor-hidden-sizes`` (``--hidden-sizes`` sets both)."""
    critics = state_bytes(agent.critic_params) > state_bytes(agent.actor_params)
    return (f"smaller --{'critic' if critics else 'actor'}-hidden-sizes (or --hidden-sizes, "
            "which sets both)")  # fmt: skip


__all__ = [
    "PHYSICS_COPIES",
    "UPDATE_ACTIVATIONS",
    "UPDATE_COPY",
    "WORKING_ADVICE",
    "available_memory",
    "larger_network_advice",
    "network_units",
    "size_text",
    "state_bytes",
    "working_bytes",
    "working_total",
]
