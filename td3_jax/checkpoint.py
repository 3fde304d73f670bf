"""Exact-resume checkpoints of the whole train state (orbax-checkpoint).

A checkpoint holds every leaf of the :class:`~td3_jax.training.TrainState` (parameters, targets,
optimiser states, normaliser, replay buffer, environment states, RNG keys and counters) plus a
small JSON record of host-side progress. Orbax writes each checkpoint to a temporary folder and
renames it when complete, so a run killed mid-write keeps its previous checkpoint; only the
newest ``keep`` are kept.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import orbax.checkpoint as ocp

logging.getLogger("absl").setLevel(logging.ERROR)
# After a failed read of a corrupt checkpoint, tensorstore callbacks still in flight can hit the
# closed event loop; asyncio would log each as a traceback. The CheckpointError says it all.
logging.getLogger("asyncio").setLevel(logging.CRITICAL)


class CheckpointError(RuntimeError):
    """A checkpoint that is missing, corrupt or does not match the run's configuration."""


class Checkpointer:
    """Saves and restores train states under ``directory`` (``directory/<chunk>/``)."""

    def __init__(self, directory: Path, keep: int = 3):
        self.directory = Path(directory).absolute()
        self._manager = ocp.CheckpointManager(
            self.directory,
            options=ocp.CheckpointManagerOptions(max_to_keep=keep, create=True),
        )

    def latest_step(self) -> int | None:
        return self._manager.latest_step()

    def save(self, step: int, state: Any, meta: dict) -> None:
        """Writes checkpoint ``step`` and waits until it is complete on disk."""
        leaves = _stored_leaves(state)
        layout = [[path, list(x.shape), str(x.dtype)] for path, x in _leaves_with_paths(state)]
        self._manager.save(
            step,
            args=ocp.args.Composite(
                state=ocp.args.StandardSave(leaves),
                meta=ocp.args.JsonSave({**meta, "layout": layout}),
            ),
        )
        self._manager.wait_until_finished()

    def restore(
        self, abstract_state: Any, step: int | None = None, shardings: Any = None
    ) -> tuple[Any, dict, int]:
        """Restores ``(state, meta, step)`` from checkpoint ``step`` (default: the newest).

        ``abstract_state`` gives the expected structure, shapes and dtypes (``jax.eval_shape`` of
        the trainer's ``init``); a checkpoint that differs raises :class:`CheckpointError`.
        ``shardings`` (a matching pytree of ``jax.sharding.Sharding``) places the restored arrays
        directly, so a checkpoint written on one device count restores onto another.
        """
        step = self.latest_step() if step is None else step
        if step is None:
            raise CheckpointError(f"no checkpoint found in {self.directory}")
        try:
            meta = self._manager.restore(
                step, args=ocp.args.Composite(meta=ocp.args.JsonRestore())
            )["meta"]
        except Exception as err:  # orbax raises many types; all mean "unusable checkpoint"
            raise _unusable(self.directory / str(step), err) from err
        expected = [[p, list(x.shape), str(x.dtype)] for p, x in _leaves_with_paths(abstract_state)]
        saved = meta.get("layout") if isinstance(meta, dict) else None
        if saved != expected:
            diff = next(
                (
                    f"{w[0]}: saved {s[1]} {s[2]}, expected {w[1]} {w[2]}"
                    for s, w in zip(saved or [], expected, strict=False)
                    if s != w
                ),
                f"{len(saved or [])} saved arrays, {len(expected)} expected",
            )
            raise CheckpointError(
                f"checkpoint {self.directory / str(step)} does not match this run's "
                f"configuration ({diff})"
            )
        if shardings is None:
            target = jax.tree.map(ocp.utils.to_shape_dtype_struct, abstract_state)
        else:
            target = jax.tree.map(
                lambda x, s: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=s),
                abstract_state,
                shardings,
            )
        target = _stored_leaves(target)
        try:
            restored = self._manager.restore(
                step, args=ocp.args.Composite(state=ocp.args.StandardRestore(target))
            )["state"]
        except Exception as err:
            raise _unusable(self.directory / str(step), err) from err
        state = _rebuild(abstract_state, restored)
        meta = {k: v for k, v in meta.items() if k != "layout"}
        return state, meta, step

    def close(self) -> None:
        self._manager.close()


def _leaves_with_paths(tree: Any) -> list[tuple[str, Any]]:
    return [(jax.tree_util.keystr(p), x) for p, x in jax.tree_util.tree_leaves_with_path(tree)]


def _stored_leaves(tree: Any) -> dict[str, Any]:
    """The leaves orbax stores, by position (it refuses zero-size arrays; those carry no data)."""
    return {f"{i:05d}": x for i, x in enumerate(jax.tree.leaves(tree)) if math.prod(x.shape) > 0}


def _rebuild(abstract_state: Any, stored: dict[str, Any]) -> Any:
    leaves, treedef = jax.tree.flatten(abstract_state)
    values = [
        stored[f"{i:05d}"] if math.prod(x.shape) > 0 else jnp.zeros(x.shape, x.dtype)
        for i, x in enumerate(leaves)
    ]
    return jax.tree.unflatten(treedef, values)


def _unusable(path: Path, err: Exception) -> CheckpointError:
    first_line = (str(err).splitlines() or [""])[0][:200]
    return CheckpointError(
        f"checkpoint {path} is unreadable or corrupt ({type(err).__name__}: {first_line})"
    )
