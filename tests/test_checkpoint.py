"""Tests of the exact-resume checkpoints (``td3_jax.checkpoint.Checkpointer``).

A real :class:`~td3_jax.training.TrainState` of a tiny Pendulum run is saved and restored; to
make "bit-exact" mean something, every leaf is first overwritten with random values of its own
dtype (so no leaf is a run of zeros that a lossy or misrouted restore would reproduce by luck).
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from td3_jax.checkpoint import Checkpointer, CheckpointError
from td3_jax.config import TrainConfig
from td3_jax.training import TrainState, make_trainer

CFG = TrainConfig(
    num_envs=2,
    buffer_size=64,
    batch_size=8,
    hidden_sizes=(8,),
    eval_every=8,
    total_steps=16,
    warmup_steps=0,
)


def scramble(tree, seed: int):
    """Same structure, shapes and dtypes; every element random (floats, ints, raw keys)."""
    rng = np.random.default_rng(seed)

    def leaf(x):
        dtype = np.dtype(x.dtype)
        if np.issubdtype(dtype, np.floating):
            values = rng.normal(size=x.shape).astype(dtype) * 100
        elif dtype == np.bool_:
            values = rng.integers(0, 2, size=x.shape).astype(bool)
        else:
            info = np.iinfo(dtype)
            values = rng.integers(info.min, info.max, size=x.shape, dtype=dtype, endpoint=True)
        return jnp.asarray(values)

    return jax.tree.map(leaf, tree)


def assert_bit_exact(restored, original):
    assert jax.tree.structure(restored) == jax.tree.structure(original)
    paths = jax.tree_util.tree_leaves_with_path(original)
    for (path, want), got in zip(paths, jax.tree.leaves(restored), strict=True):
        name = jax.tree_util.keystr(path)
        got, want = np.asarray(got), np.asarray(want)
        assert got.dtype == want.dtype, name
        assert got.shape == want.shape, name
        assert got.tobytes() == want.tobytes(), name


@pytest.fixture(scope="module")
def trainer():
    return make_trainer(CFG)


@pytest.fixture(scope="module")
def abstract(trainer):
    return jax.eval_shape(trainer.init, jax.random.PRNGKey(0))


@pytest.fixture(scope="module")
def state(trainer):
    return trainer.init(jax.random.PRNGKey(1))


def step_dirs(directory: Path) -> list[int]:
    return sorted(int(p.name) for p in directory.iterdir() if p.name.isdigit())


def test_train_state_round_trips_bit_exactly(tmp_path, trainer, abstract, state):
    assert isinstance(state, TrainState)
    meta = {"wall_time_s": 12.5, "chunk": 3, "note": "x", "nested": {"a": [1, 2]}}
    ckpt = Checkpointer(tmp_path / "ck")
    ckpt.save(7, state, meta)
    restored, restored_meta, step = ckpt.restore(abstract)
    ckpt.close()
    assert step == 7
    assert restored_meta == meta
    assert isinstance(restored, TrainState)
    assert_bit_exact(restored, state)


def test_scrambled_train_state_round_trips_bit_exactly_in_a_new_checkpointer(
    tmp_path, abstract, state
):
    scrambled = scramble(state, seed=0)
    ckpt = Checkpointer(tmp_path, keep=1)
    ckpt.save(2, scrambled, {})
    ckpt.close()
    # A fresh Checkpointer (as after a restart) finds and restores it.
    fresh = Checkpointer(tmp_path, keep=1)
    assert fresh.latest_step() == 2
    restored, meta, step = fresh.restore(abstract)
    fresh.close()
    assert (meta, step) == ({}, 2)
    assert_bit_exact(restored, scrambled)
    # The restored state works with the trainer's functions (same structure and types).
    assert isinstance(restored.env_state.obs, jax.Array)


def test_any_pytree_with_zero_size_and_special_values_round_trips(tmp_path, state):
    tree = {
        "train": scramble(state, seed=1),
        "empty": jnp.zeros((0, 3), jnp.float32),
        "empty_int": jnp.zeros((4, 0), jnp.int32),
        "special": jnp.asarray([np.nan, -0.0, np.inf, -np.inf, 1e-45, -3.5], jnp.float32),
        "flags": jnp.asarray([True, False, True]),
        "scalar": jnp.asarray(-7, jnp.int32),
    }
    abstract = jax.eval_shape(lambda: tree)
    ckpt = Checkpointer(tmp_path)
    ckpt.save(0, tree, {"k": 1})
    restored, meta, step = ckpt.restore(abstract)
    ckpt.close()
    assert (meta, step) == ({"k": 1}, 0)
    assert restored["empty"].shape == (0, 3) and restored["empty"].dtype == jnp.float32
    assert restored["empty_int"].shape == (4, 0) and restored["empty_int"].dtype == jnp.int32
    assert_bit_exact(restored, tree)


def test_only_the_newest_checkpoints_are_kept(tmp_path, abstract, state):
    ckpt = Checkpointer(tmp_path, keep=2)
    for step in range(1, 6):
        ckpt.save(step, state.replace(iteration=jnp.asarray(step, jnp.int32)), {"step": step})
        assert step_dirs(tmp_path) == list(range(max(1, step - 1), step + 1))
    assert ckpt.latest_step() == 5
    restored, meta, step = ckpt.restore(abstract)
    assert (int(restored.iteration), meta, step) == (5, {"step": 5}, 5)
    restored, meta, step = ckpt.restore(abstract, step=4)
    assert (int(restored.iteration), meta, step) == (4, {"step": 4}, 4)
    # A checkpoint that was removed is an error of our type.
    with pytest.raises(CheckpointError):
        ckpt.restore(abstract, step=1)
    ckpt.close()


@pytest.mark.parametrize(
    "changes, details",
    [
        # The message names the first differing leaf with its saved and expected shapes.
        (dict(hidden_sizes=(16,)), ["actor_params", "Dense_0", "[8]", "[16]"]),
        (dict(num_envs=4), ["env_state", "[2]", "[4]"]),
        (dict(algo="ddpg"), ["critic_params", "[2, 8]", "[1, 8]"]),  # one critic, not two
        # the buffer is [replay_shards, capacity / replay_shards, ...]
        (dict(total_steps=64, eval_every=64), ["buffer", "[1, 16, 3]", "[1, 64, 3]"]),
    ],
)
def test_restore_with_a_different_config_raises(tmp_path, state, changes, details):
    ckpt = Checkpointer(tmp_path)
    ckpt.save(1, state, {})
    other = make_trainer(dataclasses.replace(CFG, **changes))
    other_abstract = jax.eval_shape(other.init, jax.random.PRNGKey(0))
    with pytest.raises(CheckpointError, match="does not match this run's configuration") as err:
        ckpt.restore(other_abstract)
    assert str(tmp_path / "1") in str(err.value)
    for detail in details:
        assert detail in str(err.value)
    ckpt.close()


def _files(folder: Path, pick) -> list[Path]:
    found = [Path(root) / f for root, _, files in os.walk(folder) for f in files]
    chosen = [p for p in found if pick(p)]
    assert chosen, f"no file to corrupt under {folder}: {found}"
    return chosen


def _garbage(path: Path) -> None:
    size = max(path.stat().st_size, 16)
    path.write_bytes(np.random.default_rng(0).bytes(size))


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _empty(path: Path) -> None:
    path.write_bytes(b"")


def _flip_byte(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))


def _is_array_data(path: Path) -> bool:
    # Array chunks live under .../state/d/ (and per-process copies under ocdbt.process_0/d/).
    return path.parent.name == "d"


# orbax/tensorstore may report the failed read again from a background thread.
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
@pytest.mark.parametrize(
    "pick, damage",
    [
        (_is_array_data, _garbage),
        (_is_array_data, _truncate),
        (_is_array_data, _empty),
        (_is_array_data, _flip_byte),
        (lambda p: p.name == "manifest.ocdbt", _garbage),
        (lambda p: p.name == "_METADATA", _garbage),
        (lambda p: p.parent.name == "meta" and p.name == "metadata", _garbage),
        (lambda p: p.parent.name == "meta" and p.name == "metadata", _empty),
        (lambda p: True, _garbage),
        (lambda p: True, _truncate),
    ],
    ids=[
        "data-garbage",
        "data-truncated",
        "data-emptied",
        "data-byte-flipped",
        "manifest-garbage",
        "array-metadata-garbage",
        "meta-garbage",
        "meta-emptied",
        "all-garbage",
        "all-truncated",
    ],
)
def test_corrupt_checkpoint_raises_checkpoint_error(tmp_path, abstract, state, pick, damage):
    ckpt = Checkpointer(tmp_path)
    ckpt.save(3, scramble(state, seed=2), {})
    ckpt.close()
    for path in _files(tmp_path / "3", pick):
        damage(path)
    fresh = Checkpointer(tmp_path)
    with pytest.raises(CheckpointError, match=r"unreadable or corrupt|does not match"):
        fresh.restore(abstract)
    fresh.close()


def test_missing_array_folder_raises_checkpoint_error(tmp_path, abstract, state):
    ckpt = Checkpointer(tmp_path)
    ckpt.save(3, state, {})
    ckpt.close()
    for path in sorted((tmp_path / "3" / "state").rglob("*"), reverse=True):
        path.rmdir() if path.is_dir() else path.unlink()
    with pytest.raises(CheckpointError):
        Checkpointer(tmp_path).restore(abstract)


def test_restore_from_an_empty_directory_raises(tmp_path, abstract):
    ckpt = Checkpointer(tmp_path / "empty")
    assert ckpt.latest_step() is None
    with pytest.raises(CheckpointError, match="no checkpoint found"):
        ckpt.restore(abstract)
    ckpt.close()


def test_checkpoint_error_is_a_runtime_error():
    assert issubclass(CheckpointError, RuntimeError)
