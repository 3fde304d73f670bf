"""Tests of the exact-resume checkpoints (``td3_jax.runner.checkpoint.Checkpointer``).

A real :class:`~td3_jax.core.training.TrainState` of a tiny Pendulum run is saved and restored; to
make "bit-exact" mean something, every leaf is first overwritten with random values of its own
dtype (so no leaf is a run of zeros that a lossy or misrouted restore would reproduce by luck).
"""

from __future__ import annotations

import builtins
import dataclasses
import errno
import hashlib
import json
import logging
import os
import shutil
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from td3_jax.common.runtime import quiet_library_logs
from td3_jax.config.build import make_trainer
from td3_jax.config.schema import TrainConfig
from td3_jax.core.training import TrainState
from td3_jax.runner.checkpoint import (
    Checkpointer,
    CheckpointError,
    CheckpointWriteError,
    CorruptCheckpointError,
    _write_cause,
)

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


@pytest.fixture(autouse=True, scope="module")
def quiet_libraries():
    """What the CLI silences: orbax's log records, and the errors of tensorstore's callbacks
    after a failed read (:func:`td3_jax.common.runtime.quiet_library_logs`, for the whole
    process)."""
    quiet_library_logs()


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
        # (capped at the run's 16 steps, so a smaller --buffer-size)
        (dict(buffer_size=8), ["buffer", "[1, 16, 3]", "[1, 8, 3]"]),
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


# After a failed read, tensorstore's callbacks for orbax's closed event loop fail on background
# threads; quiet_library_logs keeps those (and only those) from reaching the hook before it.
@pytest.mark.filterwarnings("error::pytest.PytestUnraisableExceptionWarning")
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
    with pytest.raises(CorruptCheckpointError, match=r".*/3 is (unreadable or )?corrupt"):
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


# --------------------------------------------------------------------------------------------
# integrity checks, fallback to an older checkpoint, failed writes, read-only use
# --------------------------------------------------------------------------------------------


def with_big_array(state, seed: int) -> dict:
    """A scrambled train state plus a large incompressible array (its bytes lie in a data file
    as written, outside the index nodes whose own checksums the storage layer verifies)."""
    big = np.random.default_rng(seed).normal(size=(64, 300)).astype(np.float32)
    return {"train": scramble(state, seed), "big": jnp.asarray(big)}


def bit_rot(directory: Path) -> Path:
    """Inverts 64 bytes in the middle of the checkpoint's largest array file; size unchanged."""
    path = max(_files(directory / "state", _is_array_data), key=lambda p: p.stat().st_size)
    data = bytearray(path.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 64] = bytes(b ^ 0xFF for b in data[middle : middle + 64])
    size = path.stat().st_size
    path.write_bytes(bytes(data))
    assert path.stat().st_size == size
    return path


def edit_meta(directory: Path, edit, *, seal: bool = False) -> None:
    """Rewrites a checkpoint's record as ``edit`` returns it, without its own checksum (as
    versions before it wrote records) or, with ``seal``, with the checksum of the new text (an
    intact record of other contents): SHA-256 of the record as canonical JSON."""
    path = directory / "meta" / "metadata"
    record = json.loads(path.read_text())
    del record["record_checksum"]
    record = edit(record)
    if seal:
        text = json.dumps(record, sort_keys=True, separators=(",", ":"))
        record["record_checksum"] = "sha256:" + hashlib.sha256(text.encode()).hexdigest()
    path.write_text(json.dumps(record))


@pytest.fixture()
def three_steps(tmp_path, state):
    """Checkpoints 1, 2 and 3 of different values; returns (directory, {step: tree})."""
    trees = {step: with_big_array(state, seed=step) for step in (1, 2, 3)}
    ckpt = Checkpointer(tmp_path, keep=3)
    for step, tree in trees.items():
        ckpt.save(step, tree, {"step": step})
    ckpt.close()
    return tmp_path, trees


def test_bit_rot_in_an_array_fails_its_checksum(three_steps):
    directory, trees = three_steps
    bit_rot(directory / "3")
    ckpt = Checkpointer(directory)
    with pytest.raises(CorruptCheckpointError) as err:
        ckpt.restore(jax.eval_shape(lambda: trees[3]), step=3)  # an explicit step: no fallback
    assert str(err.value) == (
        f"checkpoint {directory / '3'} is corrupt (array ['big'] fails its checksum)"
    )
    ckpt.close()


def test_a_wrong_recorded_checksum_names_the_array(three_steps):
    directory, trees = three_steps
    paths = [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_leaves_with_path(trees[2])]
    victim = next(i for i, p in enumerate(paths) if "actor_params" in p and "kernel" in p)

    def replace_checksum(meta):
        kind = meta["checksums"][victim].split(":")[0]
        meta["checksums"][victim] = f"{kind}:0:0"  # the right kind of checksum, a wrong value
        return meta

    edit_meta(directory / "2", replace_checksum, seal=True)
    with pytest.raises(CorruptCheckpointError) as err:
        Checkpointer(directory).restore(jax.eval_shape(lambda: trees[2]), step=2)
    assert str(err.value) == (
        f"checkpoint {directory / '2'} is corrupt (array {paths[victim]} fails its checksum)"
    )


def test_a_checkpoint_saved_without_checksums_still_restores(three_steps):
    directory, trees = three_steps
    edit_meta(directory / "3", lambda meta: {k: v for k, v in meta.items() if k != "checksums"})
    restored, meta, step = Checkpointer(directory).restore(jax.eval_shape(lambda: trees[3]))
    assert (meta, step) == ({"step": 3}, 3)
    assert_bit_exact(restored, trees[3])


@pytest.mark.filterwarnings("error::pytest.PytestUnraisableExceptionWarning")
def test_a_corrupt_newest_checkpoint_falls_back_to_the_previous_one(three_steps, capsys):
    directory, trees = three_steps
    bit_rot(directory / "3")
    ckpt = Checkpointer(directory)
    restored, meta, step = ckpt.restore(jax.eval_shape(lambda: trees[3]))
    assert (meta, step) == ({"step": 2}, 2)
    assert_bit_exact(restored, trees[2])
    assert capsys.readouterr().err.splitlines() == [
        f"td3-jax: warning: checkpoint {directory / '3'} is corrupt (array ['big'] fails its "
        f"checksum); using checkpoint {directory / '2'}"
    ]
    assert ckpt.latest_step() == 3  # still there; the next save of step 3 replaces it
    ckpt.save(3, trees[1], {"step": "3 again"})
    restored, meta, step = ckpt.restore(jax.eval_shape(lambda: trees[3]))
    assert (meta, step) == ({"step": "3 again"}, 3)
    assert_bit_exact(restored, trees[1])
    assert step_dirs(directory) == [1, 2, 3] and capsys.readouterr().err == ""
    ckpt.close()


@pytest.mark.filterwarnings("error::pytest.PytestUnraisableExceptionWarning")
def test_fallback_skips_every_corrupt_checkpoint_in_one_line(three_steps, capsys):
    directory, trees = three_steps
    bit_rot(directory / "3")
    (directory / "2" / "meta" / "metadata").write_text("{not json")
    restored, meta, step = Checkpointer(directory).restore(jax.eval_shape(lambda: trees[3]))
    assert (meta, step) == ({"step": 1}, 1)
    assert_bit_exact(restored, trees[1])
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith(f"td3-jax: warning: checkpoint {directory / '3'} is corrupt (array")
    assert f"; checkpoint {directory / '2'} is unreadable or corrupt (" in line
    assert line.endswith(f"; using checkpoint {directory / '1'}")


@pytest.mark.filterwarnings("error::pytest.PytestUnraisableExceptionWarning")
def test_when_every_checkpoint_is_corrupt_the_error_names_each_of_them(three_steps, capsys):
    directory, trees = three_steps
    for step in (1, 2, 3):
        bit_rot(directory / str(step))
    with pytest.raises(CorruptCheckpointError) as err:
        Checkpointer(directory).restore(jax.eval_shape(lambda: trees[3]))
    fix = (f"; none can be restored: start the run again with another --out (or remove "
           f"{directory.parent}), or put back an intact copy of the checkpoints")  # fmt: skip
    assert (
        str(err.value)
        == f"no usable checkpoint in {directory}: "
        + "; ".join(
            f"checkpoint {directory / str(step)} is corrupt (array ['big'] fails its checksum)"
            for step in (3, 2, 1)
        )
        + fix
    )
    assert capsys.readouterr().err == ""
    # With one checkpoint, its own error is the message, and what to do.
    for step in (1, 2):
        shutil.rmtree(directory / str(step))
    only = Checkpointer(directory, keep=3)
    with pytest.raises(CorruptCheckpointError) as err:
        only.restore(jax.eval_shape(lambda: trees[3]))
    assert str(err.value) == (
        f"checkpoint {directory / '3'} is corrupt (array ['big'] fails its checksum)" + fix
    )
    only.close()


def replace_once(path: Path, old: bytes, new: bytes) -> None:
    """Replaces the first ``old`` in ``path`` by ``new`` of its length (the size kept)."""
    data = path.read_bytes()
    assert len(old) == len(new) and old in data
    path.write_bytes(data.replace(old, new, 1))


@pytest.mark.filterwarnings("error::pytest.PytestUnraisableExceptionWarning")
@pytest.mark.parametrize(
    ("old", "new"),
    [(b'"float32"', b'"float22"'), (b'"step": 3', b'"step": 7')],
    ids=["layout-dtype", "progress-value"],
)
def test_a_damaged_metadata_byte_falls_back_to_the_previous_checkpoint(
    three_steps, capsys, old, new
):
    """One byte of checkpoint 3's record changed, the JSON still valid: a dtype of its layout
    (once reported as "does not match this run's configuration", and for a run's settings as
    an edited config.json) or a value of the caller's record (once restored as if saved). Its
    checksum fails, so the restore uses checkpoint 2, saying so once."""
    directory, trees = three_steps
    replace_once(directory / "3" / "meta" / "metadata", old, new)
    ckpt = Checkpointer(directory)
    restored, meta, step = ckpt.restore(jax.eval_shape(lambda: trees[3]))
    assert (meta, step) == ({"step": 2}, 2)
    assert_bit_exact(restored, trees[2])
    assert capsys.readouterr().err.splitlines() == [
        f"td3-jax: warning: checkpoint {directory / '3'} is corrupt (its metadata fails its "
        f"checksum); using checkpoint {directory / '2'}"
    ]
    with pytest.raises(CorruptCheckpointError, match="its metadata fails its checksum"):
        ckpt.restore(jax.eval_shape(lambda: trees[3]), step=3)  # an explicit step: no fallback
    with pytest.raises(CorruptCheckpointError, match="its metadata fails its checksum"):
        ckpt.read_meta(3)
    assert ckpt.read_meta(2) == {"step": 2}
    ckpt.close()


def _flipped_at(path: Path, fraction: float) -> bytes:
    """``path``'s bytes with the lowest bit of the byte at ``fraction`` of its length flipped."""
    data = bytearray(path.read_bytes())
    data[min(int(len(data) * fraction), len(data) - 1)] ^= 0x01
    return bytes(data)


@pytest.mark.filterwarnings("error::pytest.PytestUnraisableExceptionWarning")
def test_one_flipped_bit_in_any_file_restores_checkpoint_3_exactly_or_falls_back(
    three_steps, capsys
):
    """Every file of a checkpoint, one bit flipped at a quarter, half and three quarters of
    it: the restore gives either checkpoint 3 bit for bit with its record (the flip was in a
    byte nothing restored depends on) or checkpoint 2 with one warning naming 3; never an
    error, never other values. The record and the array data always fall back."""
    directory, trees = three_steps
    abstract = jax.eval_shape(lambda: trees[3])
    outcomes = {}
    for path in sorted(p for p in (directory / "3").rglob("*") if p.is_file()):
        intact = path.read_bytes()
        for fraction in (0.25, 0.5, 0.75):
            path.write_bytes(_flipped_at(path, fraction))
            restored, meta, step = Checkpointer(directory).restore(abstract)
            path.write_bytes(intact)
            warning = capsys.readouterr().err
            assert (meta, step) == ({"step": step}, step) and step in (2, 3), path
            assert_bit_exact(restored, trees[step])
            if step == 2:
                assert warning.startswith(f"td3-jax: warning: checkpoint {directory / '3'} is ")
                assert warning.endswith(f"; using checkpoint {directory / '2'}\n")
            else:
                assert warning == ""
            outcomes.setdefault(path.relative_to(directory / "3").as_posix(), set()).add(step)
    assert outcomes["meta/metadata"] == {2}
    data = [name for name in outcomes if _is_array_data(directory / "3" / name)]
    assert any(outcomes[name] == {2} for name in data)


def test_a_newest_checkpoint_of_another_configuration_does_not_fall_back(tmp_path, capsys):
    ckpt = Checkpointer(tmp_path)
    ckpt.save(1, {"w": jnp.ones(3)}, {})
    ckpt.save(2, {"w": jnp.ones(4)}, {})
    with pytest.raises(CheckpointError, match="does not match this run's configuration") as err:
        ckpt.restore(jax.eval_shape(lambda: {"w": jnp.ones(3)}))
    assert not isinstance(err.value, CorruptCheckpointError)
    assert str(err.value) == (
        f"checkpoint {tmp_path / '2'} does not match this run's configuration "
        "(['w']: saved [4] float32, expected [3] float32)"
    )
    assert capsys.readouterr().err == ""
    ckpt.close()


def fail_writes_under(monkeypatch, directory: Path, error: OSError) -> None:
    """Every Python-level open for writing below ``directory`` raises ``error`` (as a full disk
    would; orbax writes its metadata, JSON items and commit markers that way)."""
    real_open = builtins.open

    def open_(file, mode="r", *args, **kwargs):
        if isinstance(file, str | os.PathLike) and str(file).startswith(str(directory)):
            if any(flag in mode for flag in "wax+"):
                raise error
        return real_open(file, mode, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", open_)


def leftovers(directory: Path) -> list[str]:
    return [str(p) for p in directory.rglob("*") if "tmp" in p.name]


@pytest.mark.filterwarnings("error::pytest.PytestUnraisableExceptionWarning")
def test_a_full_disk_fails_the_save_cleanly_and_keeps_the_last_checkpoint(
    tmp_path, abstract, state, monkeypatch, caplog
):
    ckpt = Checkpointer(tmp_path, keep=3)
    ckpt.save(4, state, {"step": 4})
    with monkeypatch.context() as patch:
        fail_writes_under(patch, tmp_path, OSError(errno.ENOSPC, os.strerror(errno.ENOSPC)))
        with pytest.raises(CheckpointWriteError) as err:
            ckpt.save(5, scramble(state, seed=5), {"step": 5})
    assert str(err.value) == (
        f"could not write checkpoint {tmp_path / '5'}: no space left on the disk holding "
        f"{tmp_path}; the last good checkpoint is {tmp_path / '4'}"
    )
    assert isinstance(err.value, CheckpointError)
    assert leftovers(tmp_path) == [] and step_dirs(tmp_path) == [4]
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR] == []
    assert ckpt.latest_step() == 4
    restored, meta, step = ckpt.restore(abstract)
    assert (meta, step) == ({"step": 4}, 4)
    assert_bit_exact(restored, state)
    # Once there is room again, the same Checkpointer saves.
    ckpt.save(5, scramble(state, seed=5), {"step": 5})
    assert step_dirs(tmp_path) == [4, 5]
    ckpt.close()


def test_a_failed_first_save_says_there_is_no_earlier_checkpoint(tmp_path, state, monkeypatch):
    ckpt = Checkpointer(tmp_path)
    fail_writes_under(monkeypatch, tmp_path, OSError(errno.EIO, os.strerror(errno.EIO)))
    with pytest.raises(CheckpointWriteError) as err:
        ckpt.save(1, state, {})
    monkeypatch.undo()
    assert str(err.value) == (
        f"could not write checkpoint {tmp_path / '1'}: OSError: [Errno {errno.EIO}] "
        f"{os.strerror(errno.EIO)}; there is no earlier checkpoint"
    )
    assert leftovers(tmp_path) == [] and step_dirs(tmp_path) == []
    ckpt.close()


def test_a_read_only_checkpointer_creates_nothing(tmp_path, abstract, state):
    missing = tmp_path / "run" / "checkpoints"
    ckpt = Checkpointer(missing, create=False)
    assert ckpt.latest_step() is None and ckpt.steps() == []
    with pytest.raises(CheckpointError, match=r"no checkpoint found in .*checkpoints"):
        ckpt.restore(abstract)
    ckpt.close()
    assert not (tmp_path / "run").exists()
    # It reads an existing directory, and a save creates the directory.
    ckpt = Checkpointer(missing, create=False)
    ckpt.save(1, state, {})
    ckpt.close()
    reader = Checkpointer(missing, create=False)
    assert reader.steps() == [1]
    assert_bit_exact(reader.restore(abstract)[0], state)
    reader.close()


def test_a_checkpoint_of_an_older_format_says_so(tmp_path, state, abstract):
    """A layout mismatch in a checkpoint without the current format is named as a version
    difference, not as a configuration the user changed."""
    ckpt = Checkpointer(tmp_path)
    ckpt.save(1, state, {})
    ckpt.close()

    def as_format_one(meta):
        del meta["format"]
        meta["layout"][0][1] = [*meta["layout"][0][1], 1]  # as if the layout had changed
        return meta

    edit_meta(tmp_path / "1", as_format_one)
    with pytest.raises(CheckpointError, match=r"another td3-jax version .*format 1, this version"):
        Checkpointer(tmp_path).restore(abstract, step=1)


def test_a_background_save_survives_the_caller_donating_the_state(tmp_path, abstract, state):
    """A background save returns before the disk write; the caller may then hand the arrays to a
    program that donates (overwrites) them, as the training loop's next chunk does."""
    original = scramble(state, seed=11)
    expected = jax.tree.map(np.array, original)  # host copies, taken before anything is donated
    ckpt = Checkpointer(tmp_path)
    ckpt.save(1, original, {"step": 1}, background=True)
    zero = lambda x: jnp.logical_xor(x, x) if x.dtype == jnp.bool_ else x - x
    overwrite = jax.jit(lambda tree: jax.tree.map(zero, tree), donate_argnums=0)
    zeros = jax.block_until_ready(overwrite(original))
    assert all(not np.asarray(x).any() for x in jax.tree.leaves(zeros))
    # The arrays are either donated (deleted, their memory reused) or, on the CPU, pinned by the
    # pending write's zero-copy host views, when XLA silently declines the donation (seen in 1
    # run of 6 under load, and always when saves follow each other): both are safe, and the
    # checkpoint must hold the values of the moment of the save either way.
    deleted = {x.is_deleted() for x in jax.tree.leaves(original)}
    assert len(deleted) == 1  # all or none
    ckpt.wait()
    assert step_dirs(tmp_path) == [1]
    restored, meta, step = ckpt.restore(abstract)
    assert (meta, step) == ({"step": 1}, 1)
    assert_bit_exact(restored, expected)
    ckpt.close()


@pytest.mark.parametrize("keep", [1, 3])
def test_a_background_write_that_fails_raises_where_it_is_waited_for(
    tmp_path, abstract, state, monkeypatch, keep
):
    ckpt = Checkpointer(tmp_path, keep=keep)
    ckpt.save(4, state, {"step": 4}, background=True)
    assert ckpt.pending == 4
    assert ckpt.steps() == [4] and ckpt.pending is None  # steps() waits for the write
    with monkeypatch.context() as patch:
        fail_writes_under(patch, tmp_path, OSError(errno.ENOSPC, os.strerror(errno.ENOSPC)))
        ckpt.save(5, scramble(state, seed=5), {"step": 5}, background=True)  # returns
        with pytest.raises(CheckpointWriteError) as err:
            ckpt.wait()
    assert str(err.value).startswith(f"could not write checkpoint {tmp_path / '5'}: no space left")
    assert str(err.value).endswith(f"the last good checkpoint is {tmp_path / '4'}")
    assert leftovers(tmp_path) == [] and ckpt.steps() == [4]
    assert_bit_exact(ckpt.restore(abstract)[0], state)  # also with keep=1: 4 is not deleted
    ckpt.close()


def test_check_raises_a_failed_background_write_without_waiting(tmp_path, state, monkeypatch):
    import time

    ckpt = Checkpointer(tmp_path)
    ckpt.check()  # nothing pending: nothing to say
    with monkeypatch.context() as patch:
        fail_writes_under(patch, tmp_path, OSError(errno.EIO, os.strerror(errno.EIO)))
        ckpt.save(1, state, {}, background=True)
        raised = None
        for _ in range(400):  # until the write has failed
            try:
                ckpt.check()
            except CheckpointWriteError as err:
                raised = err
                break
            time.sleep(0.025)
    assert raised is not None
    assert str(raised).startswith(f"could not write checkpoint {tmp_path / '1'}")
    assert ckpt.pending is None and ckpt.steps() == []
    ckpt.close()


@pytest.mark.parametrize(
    ("keep", "existing", "free_checkpoints", "fits"),
    [(3, 0, 4, True), (3, 0, 3.9, False), (1, 0, 2, True), (1, 0, 1.9, False),
     (3, 2, 2, True), (3, 2, 1.9, False), (2, 3, 1, True), (2, 3, 0.9, False),
     (3, 0, 1.5, False)],
)  # fmt: skip
def test_check_space_asks_for_the_kept_checkpoints_and_one_being_written(
    tmp_path, state, monkeypatch, keep, existing, free_checkpoints, fits
):
    """Free space needed: (keep - checkpoints already there, at least 0, + 1) checkpoints;
    --keep-checkpoints 1 is suggested only where it would fit (1.5 checkpoints free for 2)."""
    import shutil

    from td3_jax.runner import checkpoint

    size = sum(np.asarray(x).nbytes for x in jax.tree.leaves(state))
    assert checkpoint.state_bytes(state) == size
    ckpt = Checkpointer(tmp_path / "ckpt", keep=max(keep, existing))
    for step in range(1, existing + 1):
        ckpt.save(step, state, {})
    ckpt.close()
    free = int(free_checkpoints * size)
    usage = shutil.disk_usage(tmp_path)._replace(free=free)
    monkeypatch.setattr(checkpoint.shutil, "disk_usage", lambda path: usage)
    ckpt = Checkpointer(tmp_path / "ckpt", keep=keep)
    if fits:
        ckpt.check_space(state)
    else:
        with pytest.raises(CheckpointWriteError, match="checkpoints need") as err:
            ckpt.check_space(state)
        message = str(err.value)
        # offered where one kept checkpoint (and one being written) would fit
        one_kept_fits = free_checkpoints >= max(1 - existing, 0) + 1
        assert ("--keep-checkpoints 1" in message) == (keep > 1 and one_kept_fits)
        # On resume (checkpoints already there) the sizes and --out are the run's own.
        assert (f"less the {existing} already there" in message) == (existing > 0)
        assert ("smaller --critic-hidden-sizes" in message) == (existing == 0)  # (see below)
        assert ("free space on that disk" in message) == (existing > 0)
    ckpt.close()


def test_check_space_names_the_larger_part_of_the_train_state_to_shrink(tmp_path, monkeypatch):
    """A fresh run short of disk is told to shrink what outweighs the rest of a checkpoint:
    the replay ring (--buffer-size) or the networks with their optimiser states (the larger
    network's hidden sizes), not a ring that is a sliver of it."""
    import shutil

    from td3_jax.runner import checkpoint

    usage = shutil.disk_usage(tmp_path)._replace(free=0)
    monkeypatch.setattr(checkpoint.shutil, "disk_usage", lambda path: usage)
    ckpt = Checkpointer(tmp_path / "ckpt", keep=1)
    for cfg, part, advice in (
        (CFG, "agent", "smaller --critic-hidden-sizes"),
        (
            dataclasses.replace(CFG, buffer_size=4096, total_steps=4096),
            "buffer",
            "a smaller --buffer-size",
        ),
    ):
        abstract = jax.eval_shape(make_trainer(cfg).init, jax.random.PRNGKey(0))
        other = "buffer" if part == "agent" else "agent"
        sizes = {name: checkpoint.state_bytes(getattr(abstract, name)) for name in (part, other)}
        assert sizes[part] > sizes[other]
        with pytest.raises(CheckpointWriteError, match="checkpoints need") as err:
            ckpt.check_space(abstract)
        assert advice in str(err.value) and str(err.value).count("smaller") == 1
    ckpt.close()


@pytest.mark.parametrize(
    ("code", "words"),
    [
        (errno.ENOSPC, "no space left on the disk holding {}"),
        (errno.EDQUOT, "the disk quota of {} is exceeded"),
        (errno.EROFS, "{} is on a read-only file system"),
        (errno.EACCES, "no permission to write in {}"),
        (errno.EPERM, "writing in {} is not permitted"),  # (an immutable file: a traceback once)
    ],
)
def test_a_refused_write_is_said_in_words_raised_or_wrapped(code, words, tmp_path):
    """The OS's reason, whether the OSError comes itself, as the cause of another error, or
    only as text inside one (tensorstore's wrapped messages)."""
    expected = words.format(tmp_path)
    raised = OSError(code, os.strerror(code))
    caused = ValueError("the save failed")
    caused.__cause__ = raised
    wrapped = RuntimeError(f"Error writing local file: {os.strerror(code)} [source locations]")
    for err in (raised, caused, wrapped):
        assert _write_cause(err, tmp_path) == expected, err
    assert _write_cause(OSError(errno.EIO, "I/O error"), tmp_path).startswith("OSError: ")
