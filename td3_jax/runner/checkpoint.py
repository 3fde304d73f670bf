"""Exact-resume checkpoints of the whole train state (orbax-checkpoint).

A checkpoint holds every leaf of the :class:`~td3_jax.core.training.TrainState` (parameters,
targets, optimiser states, normaliser, replay buffer, environment states, RNG keys and counters)
plus a small JSON record of host-side progress, the arrays' layout, a checksum of every array
and a SHA-256 of the record itself.
Orbax writes each checkpoint to a temporary folder and renames it when complete, so a run killed
mid-write keeps its previous checkpoint; only the newest ``keep`` are kept. A save may run in
the background (``background=True``): it returns once the arrays are copied off the device, so
the caller may reuse (donate) them, and the disk write overlaps the caller's next work.

Failures are clean: a restored array whose bytes differ from those saved (bit rot, a garbled
file), or a record whose text differs from that saved (one flipped byte of
``N/meta/metadata``), makes the checkpoint corrupt, and restoring the newest checkpoint then
falls back to the next older one with a one-line warning; damage to orbax's own files of a
checkpoint either fails its read (corrupt, the same fallback) or leaves what is restored
unchanged, which the checksums verify; a failed write (a full disk) removes what it left and
raises :class:`CheckpointWriteError` naming the last good checkpoint. Orbax's own log records,
and the errors its callbacks still raise after a failed read, are left to the program: the
CLI drops them (:func:`td3_jax.common.runtime.quiet_library_logs`).
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import math
import shutil
import sys
import time
from collections.abc import Iterator
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from td3_jax.common.runtime import in_background, root_logging_kept

__all__ = ["FORMAT", "Checkpointer", "size_text", "state_bytes"]

with root_logging_kept():  # absl, under orbax's import, would add a handler to the root logger
    import orbax.checkpoint as ocp

from td3_jax.common.errors import CheckpointError, CheckpointWriteError, CorruptCheckpointError
from td3_jax.runner.memory import larger_network_advice, size_text, state_bytes

# Orbax writes <step>.orbax-checkpoint-tmp (older versions: ...-tmp-<time>) and renames it.
_TMP_MARK = ".orbax-checkpoint-tmp"
_HASH = "mix32"
#: The record's own checksum: ``"sha256:<hex>"`` of the rest of the record (:func:`_sealed`).
_RECORD_SUM = "record_checksum"
_META_KEYS = ("layout", "checksums", "format", _RECORD_SUM)  # what save adds to the caller's meta
#: The checkpoint format; 1 (no "format" key) was written before the trainer redesign of
#: 2026-11-22 (other optimiser-state layout, no evaluation key in the state); 2 before the
#: per-environment exploration draws (``TrainState.expl_draw``) could be in the state. A run
#: without them has format 2's layout, and its format-2 checkpoints restore (the layout is
#: what is checked; the format only explains a mismatch).
FORMAT = 3
# (errno, text in a wrapped message such as tensorstore's, what the error message says)
_WRITE_CAUSES = [
    (errno.ENOSPC, "No space left", "no space left on the disk holding {}"),
    (errno.EDQUOT, "Disk quota exceeded", "the disk quota of {} is exceeded"),
    (errno.EROFS, "Read-only file system", "{} is on a read-only file system"),
    (errno.EACCES, "Permission denied", "no permission to write in {}"),
    (errno.EPERM, "Operation not permitted", "writing in {} is not permitted"),
]


class Checkpointer:
    """Saves and restores train states under ``directory`` (``directory/<chunk>/``).

    With ``create=False`` the directory is not created until the first :meth:`save`, so a reader
    (``eval``, a failed ``--resume``) leaves nothing behind; a missing directory has no steps.
    """

    def __init__(self, directory: Path, keep: int = 3, create: bool = True):
        self.directory = Path(directory).absolute()
        self._keep = keep
        self._manager: ocp.CheckpointManager | None = None
        self._pending: int | None = None  # the step of a background write not yet waited for
        self._checksum_programs: dict[tuple, Future] = {}  # layout -> compile (:meth:`prepare`)
        if create:
            self._manager = self._new_manager()

    def steps(self) -> list[int]:
        """The steps of the complete checkpoints in the directory, oldest first (after waiting
        for a background write; its failure raises :class:`CheckpointWriteError`)."""
        self.wait()
        if self._manager is None and not self.directory.is_dir():
            return []
        return sorted(self._orbax().all_steps())

    def remove_unfinished(self) -> list[Path]:
        """Removes, and returns, the folders of writes that never finished
        (``N.orbax-checkpoint-tmp``: a process ended while writing, e.g. by a second Ctrl-C).
        Only for the run that holds the directory's lock: another process's write in flight
        looks the same."""
        left = sorted(self.directory.glob(f"*{_TMP_MARK}*")) if self.directory.is_dir() else []
        for path in left:
            shutil.rmtree(path, ignore_errors=True)
        return left

    def latest_step(self) -> int | None:
        """The newest complete checkpoint's step (it may still turn out corrupt), or None."""
        steps = self.steps()
        return steps[-1] if steps else None

    def save(self, step: int, state: Any, meta: dict, *, background: bool = False) -> None:
        """Writes checkpoint ``step`` and waits until it is complete on disk; with
        ``background``, returns once ``state`` is copied to host memory and finishes the write
        while the caller goes on (the next save, :meth:`wait`, :meth:`steps` or :meth:`close`
        waits for it).

        A background write still running is finished first. Checkpoints at ``step`` or later
        (left by a run resumed from an older checkpoint) are replaced. A failed write removes
        what it left and raises :class:`CheckpointWriteError` (a background one, where it is
        waited for).
        """
        self.wait()
        leaves = _leaves_with_paths(state)
        record = {
            **meta,
            "layout": [[path, list(x.shape), str(x.dtype)] for path, x in leaves],
            "checksums": _checksums([x for _, x in leaves], self._checksum_programs),
            "format": FORMAT,
        }
        args = ocp.args.Composite(
            state=ocp.args.StandardSave(_stored_leaves(state)),
            meta=ocp.args.JsonSave(_sealed(record)),
        )
        try:
            manager = self._orbax()
            for stale in [s for s in manager.all_steps() if s >= step]:
                manager.delete(stale)
            saved = manager.save(step, args=args)
        except Exception as err:  # orbax / tensorstore wrap OS errors in many types
            raise self._write_failed(step, err) from err
        if not saved:
            raise self._write_failed(step, RuntimeError("orbax skipped the save"))
        self._pending = step
        if not background:
            self.wait()

    def prepare(self, state_specs: Any) -> Future:
        """Lowers the checksum program a :meth:`save` of the layout of ``state_specs`` (the
        state's ``ShapeDtypeStruct`` leaves, with their ``sharding``) needs, on this thread,
        and compiles it on a thread of its own (:func:`~td3_jax.common.runtime.in_background`),
        so that the first save does not compile it between two chunks (2-6 s for a robot's
        state). Returns the compile's future; saves of this layout wait for it and use its
        program (the jitted one if it failed), saves of other layouts compile theirs.
        """
        leaves = jax.tree.leaves(state_specs)
        lowered = _device_checksums.lower(leaves)
        future = in_background(lowered.compile, name="td3-jax checksums")
        self._checksum_programs[_layout(leaves)] = future
        return future

    def wait(self) -> None:
        """Waits until a background write is complete on disk (nothing to do without one); a
        failed one removes what it left and raises :class:`CheckpointWriteError`."""
        step, self._pending = self._pending, None
        if step is None or self._manager is None:
            return
        try:
            self._manager.wait_until_finished()
        except Exception as err:  # orbax / tensorstore wrap OS errors in many types
            raise self._write_failed(step, err) from err

    def check(self) -> None:
        """Raises :class:`CheckpointWriteError` if a background write has already failed,
        without waiting for one still running (a finished one is waited for: orbax raises a
        failure only there)."""
        if self._manager is not None and not self._manager.is_saving_in_progress():
            self.wait()

    @property
    def pending(self) -> int | None:
        """The step of a background write not yet waited for, or None."""
        return self._pending

    def check_space(self, state: Any) -> None:
        """Raises :class:`CheckpointWriteError` when the disk holding the directory has too
        little free space for the checkpoints of ``state`` (arrays or their shapes) to come:
        ``keep`` kept and one more being written, less those already there (replaced)."""
        size = state_bytes(state)
        existing = len(self.steps())
        need = (max(self._keep - existing, 0) + 1) * size
        probe = next(p for p in (self.directory, *self.directory.parents) if p.exists())
        free = shutil.disk_usage(probe).free
        if free >= need:
            return
        there = f", less the {existing} already there" if existing else ""
        one_kept = (max(1 - existing, 0) + 1) * size  # (offered only where it would fit)
        fixes = ["--keep-checkpoints 1"] if self._keep > 1 and free >= one_kept else []
        if existing:  # a resume: sizes and --out are the run's own
            fixes.append("free space on that disk or move the run directory to a larger one")
        else:
            fixes += [_shrink_advice(state), "an --out on a larger disk"]
        raise CheckpointWriteError(
            f"the disk holding {self.directory} has {size_text(free)} free, and this run's "
            f"checkpoints need {size_text(need)} ({self._keep} kept and one being written{there}; "
            f"{size_text(size)} each: the whole train state, replay buffer included); use "
            + ", or ".join(fixes)
        )

    def restore(
        self,
        abstract_state: Any,
        step: int | None = None,
        shardings: Any = None,
        resize: Any = None,
    ) -> tuple[Any, dict, int]:
        """Restores ``(state, meta, step)`` from checkpoint ``step`` (default: the newest good one).

        ``abstract_state`` gives the expected structure, shapes and dtypes (``jax.eval_shape`` of
        the trainer's ``init``); a checkpoint that differs raises :class:`CheckpointError`.
        ``shardings`` (a matching pytree of ``jax.sharding.Sharding``) places the restored arrays
        directly, so a checkpoint written on one device count restores onto another.

        ``resize(abstract_state, saved_layout) -> (abstract_as_saved, grow)`` restores a
        checkpoint of other shapes that the run can still use: its arrays are restored as
        ``abstract_as_saved``, checked, then ``grow(state)`` gives ``abstract_state``'s shapes
        (``grow`` ``None``: restored as ``abstract_state``); e.g. the replay ring of a run that
        ``--resume`` extends or shortens (:func:`td3_jax.core.training.ring_as_saved`).

        Without ``step``, a corrupt newest checkpoint is skipped for the next older one, with a
        one-line warning on stderr; the returned ``step`` says which was used. If all are
        corrupt, one :class:`CorruptCheckpointError` names each of them and why.
        """
        if step is not None:
            return self._restore_step(abstract_state, step, shardings, resize)
        skipped: list[CorruptCheckpointError] = []
        for candidate in reversed(self.steps()):
            try:
                result = self._restore_step(abstract_state, candidate, shardings, resize)
            except CorruptCheckpointError as err:
                skipped.append(err)
                continue
            if skipped and jax.process_index() == 0:
                used = self.directory / str(candidate)
                reasons = "; ".join(str(err) for err in skipped)
                print(f"td3-jax: warning: {reasons}; using checkpoint {used}", file=sys.stderr)
            return result
        if skipped:
            raise _all_corrupt(self.directory, skipped)
        raise CheckpointError(f"no checkpoint found in {self.directory}")

    def close(self) -> None:
        """Waits for outstanding writes (a failed one raises :class:`CheckpointWriteError`)
        and frees orbax's resources."""
        try:
            self.wait()
        finally:
            self._close_manager()

    def _close_manager(self) -> None:
        if self._manager is not None:
            self._manager.close()
            self._manager = None

    def _new_manager(self) -> ocp.CheckpointManager:
        return ocp.CheckpointManager(
            self.directory,
            options=ocp.CheckpointManagerOptions(max_to_keep=self._keep, create=True),
        )

    def _orbax(self) -> ocp.CheckpointManager:
        """The orbax manager, made on first use (it creates the directory)."""
        if self._manager is None:
            self._manager = self._new_manager()
        return self._manager

    def _restore_step(
        self, abstract_state: Any, step: int, shardings: Any, resize: Any = None
    ) -> tuple[Any, dict, int]:
        """Restores checkpoint ``step``, checking its layout and checksums (see :meth:`restore`
        for ``resize``)."""
        path = self.directory / str(step)
        if step not in self.steps():
            raise CheckpointError(f"no checkpoint {path} (steps found: {self.steps()})")
        meta = self._read(step, meta=ocp.args.JsonRestore())["meta"]
        _check_record(meta, path)
        saved, grow = abstract_state, None
        if resize is not None and isinstance(meta, dict):
            saved, grow = resize(abstract_state, meta.get("layout"))
        _check_layout(meta, saved, path)
        target = _stored_leaves(_restore_target(saved, shardings))
        stored = self._read(step, state=ocp.args.StandardRestore(target))["state"]
        state = _rebuild(saved, stored)
        _verify(state, meta.get("checksums"), path)
        if grow is not None:
            state = (
                jax.jit(grow)(state)
                if shardings is None
                else jax.jit(grow, out_shardings=shardings)(state)
            )
        return state, {k: v for k, v in meta.items() if k not in _META_KEYS}, step

    def _read(self, step: int, **items: Any) -> Any:
        """``items`` of checkpoint ``step``; any failure is a :class:`CorruptCheckpointError`."""
        try:
            return self._orbax().restore(step, args=ocp.args.Composite(**items))
        except Exception as err:  # orbax raises many types; all mean "unusable checkpoint"
            raise _unusable(self.directory / str(step), err) from err

    def read_meta(self, step: int) -> dict:
        """The record checkpoint ``step`` was saved with (the caller's ``meta`` as :meth:`save`
        got it), without its arrays; a damaged or unreadable one raises
        :class:`CorruptCheckpointError`."""
        path = self.directory / str(step)
        meta = self._read(step, meta=ocp.args.JsonRestore())["meta"]
        _check_record(meta, path)
        return {k: v for k, v in meta.items() if k not in _META_KEYS}

    def _write_failed(self, step: int, err: Exception) -> CheckpointWriteError:
        """Removes what the failed save of ``step`` left and describes the failure."""
        manager, self._manager = self._manager, None  # a fresh one re-reads the directory
        if manager is not None:
            with contextlib.suppress(Exception):  # it re-raises the failed write
                manager.close()
        if jax.process_index() == 0:
            _remove_partial(self.directory, step)
        older = sorted(int(p.name) for p in self.directory.glob("*") if p.name.isdigit())
        last = (
            f"the last good checkpoint is {self.directory / str(older[-1])}"
            if older
            else "there is no earlier checkpoint"
        )
        cause = _write_cause(err, self.directory)
        return CheckpointWriteError(
            f"could not write checkpoint {self.directory / str(step)}: {cause}; {last}"
        )


def _shrink_advice(state: Any) -> str:
    """The size flag that shrinks a train state's checkpoint most: ``--buffer-size`` where the
    replay ring outweighs the networks and their optimiser states (or ``state`` is not a train
    state), else the larger network's hidden sizes."""
    buffer, agent = getattr(state, "buffer", None), getattr(state, "agent", None)
    if buffer is None or agent is None or state_bytes(buffer) >= state_bytes(agent):
        return "a smaller --buffer-size"
    return larger_network_advice(agent)


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


def _restore_target(abstract_state: Any, shardings: Any) -> Any:
    """The arrays orbax should produce: the abstract state's, placed by ``shardings`` if given."""
    if shardings is None:
        return jax.tree.map(ocp.utils.to_shape_dtype_struct, abstract_state)
    return jax.tree.map(
        lambda x, s: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=s), abstract_state, shardings
    )


def _record_checksum(record: dict) -> str:
    """``"sha256:<hex>"`` of ``record`` as canonical JSON (sorted keys, no spaces)."""
    text = json.dumps(record, sort_keys=True, separators=(",", ":"))
    return "sha256:" + hashlib.sha256(text.encode()).hexdigest()


def _sealed(record: dict) -> dict:
    """``record`` as its JSON file will hold it (tuples as lists, keys as strings), plus its
    checksum under :data:`_RECORD_SUM`."""
    plain = json.loads(json.dumps(record))
    return {**plain, _RECORD_SUM: _record_checksum(plain)}


def _check_record(meta: Any, path: Path) -> None:
    """Raises :class:`CorruptCheckpointError` where the record read back is not the one saved:
    not a JSON object, or not matching its own checksum (a record saved without one, by an
    older version, passes)."""
    if not isinstance(meta, dict):
        raise CorruptCheckpointError(f"checkpoint {path} is corrupt (its metadata is damaged)")
    if _RECORD_SUM not in meta:
        return
    rest = {k: v for k, v in meta.items() if k != _RECORD_SUM}
    if meta[_RECORD_SUM] != _record_checksum(rest):
        raise CorruptCheckpointError(
            f"checkpoint {path} is corrupt (its metadata fails its checksum)"
        )


def _check_layout(meta: Any, abstract_state: Any, path: Path) -> None:
    """Raises unless the saved layout is the abstract state's (paths, shapes and dtypes)."""
    saved = meta.get("layout") if isinstance(meta, dict) else None
    if not (isinstance(saved, list) and all(isinstance(r, list) and len(r) == 3 for r in saved)):
        raise CorruptCheckpointError(f"checkpoint {path} is corrupt (its metadata has no layout)")
    expected = [[p, list(x.shape), str(x.dtype)] for p, x in _leaves_with_paths(abstract_state)]
    if saved == expected:
        return
    diff = next(
        (
            f"{w[0]}: saved {s[1]} {s[2]}, expected {w[1]} {w[2]}"
            if s[:1] == w[:1]
            else f"saved {s[0]} {s[1]} {s[2]}, expected {w[0]} {w[1]} {w[2]}"
            for s, w in zip(saved, expected, strict=False)
            if s != w
        ),
        f"{len(saved)} saved arrays, {len(expected)} expected",
    )
    if meta.get("format", 1) != FORMAT:
        raise CheckpointError(
            f"checkpoint {path} was written by another td3-jax version (checkpoint format "
            f"{meta.get('format', 1)}, this version reads {FORMAT}; first difference: {diff}); "
            "resume it with the version that wrote it, or start a new run"
        )
    raise CheckpointError(f"checkpoint {path} does not match this run's configuration ({diff})")


def _words(x: jax.Array) -> jax.Array:
    """The array's bits as flat ``uint32`` words (typed PRNG keys as their key data)."""
    if jnp.issubdtype(x.dtype, jax.dtypes.extended):
        x = jax.random.key_data(x)
    if x.dtype == jnp.bool_:
        x = x.astype(jnp.uint8)
    size = jnp.dtype(x.dtype).itemsize
    if size in (4, 8):  # an 8-byte element becomes two words
        return jax.lax.bitcast_convert_type(x, jnp.uint32).reshape(-1)
    unsigned = {1: jnp.uint8, 2: jnp.uint16}[size]
    return jax.lax.bitcast_convert_type(x, unsigned).astype(jnp.uint32).reshape(-1)


def _mix(x: jax.Array) -> jax.Array:
    """Two position-weighted ``uint32`` sums of the array's words (``[2]``, wrapping).

    Every weight is odd, so changing any one word always changes the first sum; changes that
    cancel in both sums at once are vanishingly unlikely for real corruption.
    """
    words = _words(x)
    i = jnp.arange(words.shape[0], dtype=jnp.uint32)
    w1 = (i * jnp.uint32(2654435761) + jnp.uint32(0x9E3779B9)) | jnp.uint32(1)
    w2 = ((i ^ jnp.uint32(0x85EBCA6B)) * jnp.uint32(0xC2B2AE35)) | jnp.uint32(1)
    return jnp.stack([jnp.sum(words * w1, dtype=jnp.uint32),
                      jnp.sum((words ^ (i >> 3)) * w2, dtype=jnp.uint32)])  # fmt: skip


@jax.jit
def _device_checksums(leaves: list[jax.Array]) -> list[jax.Array]:
    """:func:`_mix` of every leaf, on the device: one small compiled program per state layout,
    so a save costs no host copy or host hashing of the (large) replay buffer."""
    return [_mix(x) for x in leaves]


def _layout(leaves: list[Any]) -> tuple:
    """What a compiled checksum program needs its arguments to match: each leaf's shape, dtype,
    weak type (typed PRNG keys have none: not weak) and placement."""
    return tuple((x.shape, x.dtype, getattr(x, "weak_type", False), x.sharding) for x in leaves)


def _checksums(leaves: list[Any], compiled: dict[tuple, Future] | None = None) -> list[str]:
    """``"mix32:<a>:<b>"`` per array (computed where the arrays live, also when they are split
    over several processes), by the program ``compiled`` holds for their layout
    (:meth:`Checkpointer.prepare`; waited for), else one compiled now."""
    arrays = [jnp.asarray(x) if not isinstance(x, jax.Array) else x for x in leaves]
    program = _prepared((compiled or {}).get(_layout(arrays)))
    sums = program(arrays)
    values = [np.asarray(s.addressable_data(0)) for s in sums]
    return [f"{_HASH}:{int(v[0])}:{int(v[1])}" for v in values]


def _prepared(future: Future | None) -> Any:
    """The program ``future`` compiled, or the jitted one (no future, or its compile failed:
    the run said so once, :func:`td3_jax.runner.run._wait_for_save_warmup`)."""
    if future is None:
        return _device_checksums
    try:
        return future.result()
    except Exception:  # (compiled at its first use instead, as without prepare)
        return _device_checksums


def _verify(state: Any, checksums: Any, path: Path) -> None:
    """Raises :class:`CorruptCheckpointError` for the first array that fails its checksum.

    Checkpoints saved without checksums (or with another kind of checksum) pass.
    """
    if checksums is None:
        return
    leaves = _leaves_with_paths(state)
    if not isinstance(checksums, list) or len(checksums) != len(leaves):
        raise CorruptCheckpointError(f"checkpoint {path} is corrupt (its checksum list is damaged)")
    got = _checksums([x for _, x in leaves])
    for (name, _), want, have in zip(leaves, checksums, got, strict=True):
        if isinstance(want, str) and want.startswith(f"{_HASH}:") and have != want:
            raise CorruptCheckpointError(
                f"checkpoint {path} is corrupt (array {name} fails its checksum)"
            )


def _all_corrupt(directory: Path, errors: list[CorruptCheckpointError]) -> CorruptCheckpointError:
    """One error naming every checkpoint of ``directory`` (newest first), what is wrong with
    each, and what to do: where each is damaged, none can be restored, so the run starts again
    elsewhere; where one failed for another cause (no memory, no permission), that is fixed."""
    reasons = "; ".join(str(err) for err in errors)
    run = directory.parent
    fix = (f"none can be restored: start the run again with another --out (or remove {run}), "
           "or put back an intact copy of the checkpoints")  # fmt: skip
    if not all(getattr(err, "damaged", True) for err in errors):
        fix = "fix what keeps them from being read, then try again"
    if len(errors) == 1:
        return CorruptCheckpointError(f"{reasons}; {fix}")
    return CorruptCheckpointError(f"no usable checkpoint in {directory}: {reasons}; {fix}")


def _unusable(path: Path, err: Exception) -> CorruptCheckpointError:
    """A read of checkpoint ``path`` failed with ``err``: what is wrong, in words (the
    storage library's own message names its drivers and byte ranges)."""
    cause = _cause(err)
    error = CorruptCheckpointError(f"checkpoint {path} is unreadable or corrupt ({cause})")
    error.damaged = not cause.startswith(_UNKNOWN)  # (else not known to be damaged)
    return error


def _cause(err: Exception) -> str:
    """Why a checkpoint could not be read: its metadata damaged, files missing or damaged."""
    text = str(err)
    if isinstance(err, ValueError | TypeError | KeyError) and "JSON" in type(err).__name__ + text:
        return "its metadata is damaged"
    chain = list(_exception_chain(err))  # (the storage library's cause is often beneath)
    text = " ".join(str(e) for e in chain)
    if any(isinstance(e, FileNotFoundError) for e in chain) or "NOT_FOUND" in text:
        return "files of it are missing"
    if "OUT_OF_RANGE" in text and "byte range" in text:
        return "its array files are cut short"
    if any(code in text for code in ("DATA_LOSS", "OUT_OF_RANGE", "corrupt", "checksum")):
        return "its array files are damaged"
    return f"{_UNKNOWN}: {_first_line(err, 120)}"


#: :func:`_cause` for a failure that says nothing of damage (out of memory, no permission).
_UNKNOWN = "it cannot be read"


def _first_line(err: BaseException, limit: int = 200) -> str:
    """``Type: first line of the message`` (cut to ``limit`` characters)."""
    line = (str(err).splitlines() or [""])[0]
    return f"{type(err).__name__}: {line[:limit]}{'...' if len(line) > limit else ''}"


def _exception_chain(err: BaseException) -> Iterator[BaseException]:
    """``err`` and the exceptions it was raised from or while handling."""
    seen: set[int] = set()
    current: BaseException | None = err
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        yield current
        current = current.__cause__ or current.__context__


def _write_cause(err: Exception, directory: Path) -> str:
    """Why a write failed, in words: a known OS cause anywhere in the chain, else the error."""
    chain = list(_exception_chain(err))
    for code, text, cause in _WRITE_CAUSES:
        if any(getattr(e, "errno", None) == code or text in str(e) for e in chain):
            return cause.format(directory)
    return _first_line(err)


def _remove_partial(
    directory: Path, step: int, settle_s: float = 0.25, timeout_s: float = 120.0
) -> None:
    """Removes the temporary and final folders of a failed save of ``step``.

    Orbax raises at the first failed write while tensorstore may still be writing other files
    (re-creating their folders), so the removal repeats until nothing reappears for ``settle_s``.
    """
    deadline = time.monotonic() + timeout_s
    while True:
        for path in [*directory.glob(f"{step}{_TMP_MARK}*"), directory / str(step)]:
            shutil.rmtree(path, ignore_errors=True)
        time.sleep(settle_s)
        left = [*directory.glob(f"{step}{_TMP_MARK}*"), *directory.glob(str(step))]
        if not left or time.monotonic() > deadline:
            return
