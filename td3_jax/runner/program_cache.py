"""Traced programs kept across processes, so that a repeated run skips making its environment
and tracing its programs.

MJX programs are large: tracing a run's programs (init, chunk, evaluation, and with in-chunk
evaluation the round start) takes seconds to a minute, and JAX's persistent compilation cache
(:func:`td3_jax.common.runtime.enable_compile_cache`) only helps after it, since its key is the
traced program. This module keeps the traced programs themselves: each is exported with
:mod:`jax.export` as a function of its flat list of array leaves and stored under ``DIR/<key>/``,
where the key (:func:`fingerprint`) covers what shapes the programs: the settings other than the
seed and the traced floats (:data:`td3_jax.config.schema.SWEEPABLE`), the number of members, the
devices, JAX's settings, td3-jax's own source, the versions of JAX and of the environment packages,
and the robot's asset files. It does not see code changed under an unchanged version (an editable
install of Brax or Playground being edited): use ``--compile-cache off`` or another directory then.

A later run with the same key deserialises the programs (milliseconds), compiles them (a
persistent-cache hit when that cache is on) and never makes the environment. The seed, the
learning rates and the other traced floats are arguments of the programs, so runs that differ
only in them share an entry. An entry that cannot be read or compiled is a warning and is
removed, and the run traces as usual; so is a program :mod:`jax.export` refuses (it is then
compiled as a jitted function and not stored). Entries are written whole (a temporary
directory renamed into place) and the least recently used beyond :data:`MAX_ENTRIES` are
removed. Several processes of one run (:mod:`jax.distributed`) do not use it.

This module is the store (keys, entries, flat programs); :mod:`td3_jax.runner.programs` finds a
run's programs in it, or traces and stores them, and compiles them.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import hashlib
import importlib.metadata
import json
import os
import pickle
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import Future
from pathlib import Path
from typing import Any, NamedTuple

import jax
from jax import export
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from td3_jax.common.runtime import in_background
from td3_jax.config.build import agent_config
from td3_jax.config.schema import SWEEPABLE, WANDB_SETTINGS, TrainConfig

__all__ = [
    "FORMAT",
    "MAX_ENTRIES",
    "PACKAGE_ROOT",
    "ROUND",
    "FlatProgram",
    "as_tree_function",
    "assets_digest",
    "compile_flat",
    "discard",
    "export_flat",
    "fingerprint",
    "load",
    "names",
    "save",
    "source_digest",
    "warn",
]

#: Bump when what an entry holds changes.
FORMAT = 1
#: Entries kept (the least recently used beyond this are removed when one is written).
MAX_ENTRIES = 24
#: Settings that never shape a program (host-side only; ``menagerie``: the asset digest
#: stands for it).
HOST_ONLY = ("seed", "keep_checkpoints", "checkpoint_every", "early_evaluation", "menagerie",
             *WANDB_SETTINGS)  # fmt: skip
#: Traced floats whose ``None`` means the algorithm's default value (not another program).
#: ``hidden_sizes`` is not one (it shapes the programs): its ``None`` is keyed as the
#: algorithm's widths instead, as config.json records them, so a resume from the command line
#: finds a library run's programs.
DEFAULTED = ("actor_lr", "critic_lr", "tau")
#: Packages whose code is traced into the programs.
PACKAGES = ("jax", "jaxlib", "flax", "optax", "brax", "mujoco", "mujoco-core", "mujoco-mjx",
            "warp-lang", "playground", "gymnax")  # fmt: skip
#: Parts of JAX settings' names that mark them as not changing what tracing produces (every
#: other setting is in the key).
UNTRACED_SETTINGS = ("cache", "log", "traceback", "debug", "profil", "topology", "platform",
                     "dump")  # fmt: skip
#: The td3_jax package's folder, whose Python files :func:`source_digest` reads.
PACKAGE_ROOT = Path(__file__).resolve().parents[1]
#: The program that starts a chunk's evaluation round, which runs with ``eval_in_chunk`` only.
ROUND = "round"


def names(with_init: bool = True, eval_in_chunk: bool = False) -> tuple[str, ...]:
    """The programs a run needs, in the order they are traced: the chunk, the round start's
    with ``eval_in_chunk``, the evaluation, and ``init`` unless it resumes (``with_init``
    off)."""
    return ("chunk", *((ROUND,) if eval_in_chunk else ()), "evaluate",
            *(("init",) if with_init else ()))  # fmt: skip


class FlatProgram(NamedTuple):
    """One program as a function of its flat list of input leaves.

    Attributes:
      exported: the traced program (:class:`jax.export.Exported`).
      in_specs, out_specs: each input and output leaf's :class:`PartitionSpec` on the mesh.
      donate: the positions of the inputs whose buffers the program may reuse.
    """

    exported: export.Exported
    in_specs: tuple[PartitionSpec, ...]
    out_specs: tuple[PartitionSpec, ...]
    donate: tuple[int, ...]


def fingerprint(cfg: TrainConfig, overrides: list[tuple[str, ...]], mesh: Mesh) -> str:
    """The key of the programs of ``cfg`` for members with these swept setting names on
    ``mesh`` (hex digest; see the module docstring for what it covers)."""
    settings = dataclasses.asdict(cfg)
    for name in HOST_ONLY:
        settings.pop(name)
    for name in SWEEPABLE:  # traced: only whether one is set can shape a program
        settings[name] = None if name in DEFAULTED else settings[name] is None
    # The run's length shapes a program only through a schedule's length and the replay ring
    # (capped at the run's steps): the key holds the ring's rows instead where that is all.
    settings["replay_capacity"] = cfg.replay_capacity
    settings["hidden_sizes"] = list(agent_config(cfg).hidden_sizes)  # (None: the algorithm's)
    if cfg.lr_schedule == "constant":
        settings.pop("total_steps")
    device = mesh.devices.flat[0]
    described = {
        "format": FORMAT,
        "settings": settings,
        "members": [list(names) for names in overrides],
        "devices": [device.platform, device.device_kind, mesh.size, jax.process_count()],
        "jax": _jax_settings(),
        "versions": {name: _version(name) for name in PACKAGES},
        "source": source_digest(),
        "assets": assets_digest(cfg),
        "python": sys.version_info[:2],
    }
    text = json.dumps(described, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def _jax_settings() -> dict[str, str]:
    """JAX's settings that may change a trace (all but :data:`UNTRACED_SETTINGS`)."""
    values = jax.config.values.items()
    return {k: str(v) for k, v in values if not any(part in k for part in UNTRACED_SETTINGS)}


def _version(package: str) -> str | None:
    try:
        return importlib.metadata.version(package)
    except importlib.metadata.PackageNotFoundError:
        return None


def source_digest(root: Path = PACKAGE_ROOT) -> str:
    """A digest of td3-jax's own Python files, those of every subpackage (a changed file
    changes every key)."""
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(str(path.relative_to(root)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def assets_digest(cfg: TrainConfig) -> str | None:
    """For a Playground locomotion task, a digest of its robot folder's files (names, sizes,
    modification times) and where it was found; ``None`` for other environments (their files
    ship in the versioned packages). Raises as making the environment would when none is found.
    """
    from td3_jax.envs import menagerie

    source, _, task = cfg.env.partition("/")
    if source != "playground" or not any(task.startswith(p) for p in menagerie.ROBOTS):
        return None
    folder, _ = menagerie.robot(task)
    root = menagerie.find_root(task, cfg.menagerie)
    digest = hashlib.sha256(str(root.resolve()).encode())
    for path in sorted((root / folder).rglob("*")):
        if path.is_file():
            stat = path.stat()
            digest.update(f"{path.relative_to(root)} {stat.st_size} {stat.st_mtime_ns}".encode())
    return digest.hexdigest()


def export_flat(
    fn: Callable,
    args: tuple,
    out_shardings: Callable[[Any], Any],
    donate: tuple[int, ...] = (),
) -> tuple[FlatProgram, tuple[Any, Any]]:
    """Traces ``fn(*args)`` (``args``: ``jax.ShapeDtypeStruct`` leaves with shardings) and
    exports it as a function of the flat input leaves: ``(program, (in_tree, out_tree))``.

    ``out_shardings(out)``: the output's shardings (a tree like ``out``). ``donate``: the
    positions in ``args`` whose leaves the program may reuse.
    """
    leaves, in_tree = jax.tree.flatten(args)
    traced: dict[str, Any] = {}

    def flat(*xs: jax.Array) -> list[jax.Array]:
        out = fn(*jax.tree.unflatten(in_tree, list(xs)))
        shardings = out_shardings(out)
        out = jax.lax.with_sharding_constraint(out, shardings)
        traced["tree"] = jax.tree.structure(out)
        traced["specs"] = tuple(s.spec for s in jax.tree.leaves(shardings))
        return jax.tree.leaves(out)

    in_specs = tuple(x.sharding.spec for x in leaves)
    exported = export.export(jax.jit(flat, in_shardings=[x.sharding for x in leaves]))(*leaves)
    positions = _leaf_positions(args)
    donated = tuple(i for arg in donate for i in positions[arg])
    program = FlatProgram(exported, in_specs, traced["specs"], donated)
    return program, (in_tree, traced["tree"])


def _leaf_positions(args: tuple) -> list[range]:
    """The flat leaf positions of each argument in ``args``."""
    positions, start = [], 0
    for arg in args:
        count = len(jax.tree.leaves(arg))
        positions.append(range(start, start + count))
        start += count
    return positions


def compile_flat(program: FlatProgram, mesh: Mesh, options: dict | None = None) -> Any:
    """``program`` compiled for ``mesh`` with XLA compile ``options``
    (:func:`td3_jax.common.upstream.compile_options`): called with the flat input leaves, returns
    the flat output leaves (other shapes or placements raise instead of recompiling)."""
    place = lambda specs: [NamedSharding(mesh, spec) for spec in specs]
    in_shardings = place(program.in_specs)
    out_shardings = place(program.out_specs)
    jitted = jax.jit(program.exported.call, in_shardings=in_shardings,
                     out_shardings=out_shardings, donate_argnums=program.donate)  # fmt: skip
    avals = [jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=s)
             for a, s in zip(program.exported.in_avals, in_shardings, strict=True)]  # fmt: skip
    return jitted.lower(*avals).compile(compiler_options=options)


def as_tree_function(executable: Any, trees: tuple[Any, Any]) -> Callable:
    """The flat ``executable`` called with and returning pytrees of ``trees``' structure."""
    in_tree, out_tree = trees

    def call(*args: Any) -> Any:
        leaves, tree = jax.tree.flatten(args)
        if tree != in_tree:
            raise ValueError(f"expected arguments structured as {in_tree}, got {tree}")
        return jax.tree.unflatten(out_tree, executable(*leaves))

    return call


def save(directory: Path, key: str, programs: dict[str, FlatProgram], trees: dict) -> None:
    """Writes an entry under ``directory/key`` whole (replacing an incomplete one), or warns
    and writes nothing; another process's entry of the same key, written meanwhile, is kept."""
    target = directory / key
    tmp = None
    try:
        directory.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{key}-", dir=directory))
        _write_entry(tmp, programs, trees)
        shutil.rmtree(target, ignore_errors=True)  # an incomplete entry (see load)
        try:
            os.replace(tmp, target)
        except OSError as err:
            if err.errno not in (errno.ENOTEMPTY, errno.EEXIST):
                raise
        else:
            tmp = None
        _evict(directory)
    except Exception as err:  # a full disk, a read-only cache, an unpicklable structure
        warn(f"could not keep the traced programs in {directory} ({type(err).__name__}: {err})")
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


def _write_entry(path: Path, programs: dict[str, FlatProgram], trees: dict) -> None:
    """The files of an entry, readable by whoever may read ``path``'s parent."""
    for name, program in programs.items():
        (path / f"{name}.bin").write_bytes(program.exported.serialize())
    layout = {name: (p.in_specs, p.out_specs, p.donate) for name, p in programs.items()}
    (path / "layout.pkl").write_bytes(pickle.dumps({"programs": layout}))
    (path / "trees.pkl").write_bytes(pickle.dumps(trees))
    umask = os.umask(0)
    os.umask(umask)
    path.chmod(0o777 & ~umask)  # mkdtemp made it private


def load(directory: Path, key: str, names: tuple[str, ...]) -> tuple[dict | None, Future | None]:
    """``(programs, trees)`` of the entry ``directory/key``: ``{name: FlatProgram}`` of these
    programs, and their pytree structures (``{name: (input treedef, output treedef)}``, plus
    ``"state"``: the abstract train state) loading in a thread, since unpickling them imports
    the environment's packages (MJX), which overlaps with compiling. ``(None, None)`` when
    there is none, when it lacks one of them (the run then traces and replaces it), or when it
    is unreadable (it is removed with a warning)."""
    path = directory / key
    try:
        if not (path / "trees.pkl").is_file():
            return None, None
        layout = pickle.loads((path / "layout.pkl").read_bytes())
        if not set(names) <= set(layout["programs"]):
            return None, None
        programs = {name: FlatProgram(export.deserialize(bytearray((path / f"{name}.bin")
                                                                   .read_bytes())),
                                      *layout["programs"][name])
                    for name in names}  # fmt: skip
    except Exception as err:  # a partial or foreign directory: trace as usual
        discard(path, err)
        return None, None
    with contextlib.suppress(OSError):  # recently used (a read-only cache stays as it is)
        os.utime(path)
    return programs, in_background(lambda: pickle.loads((path / "trees.pkl").read_bytes()))


def discard(path: Path, err: BaseException) -> None:
    """Removes the unusable entry ``path``, with a warning naming the cause."""
    warn(f"ignored the unusable traced programs in {path} ({type(err).__name__}: {err}); "
          "tracing them again")  # fmt: skip
    shutil.rmtree(path, ignore_errors=True)


def _evict(directory: Path) -> None:
    """Removes the least recently used entries beyond :data:`MAX_ENTRIES`, and temporary
    folders older than an hour (left by processes that were killed while writing)."""
    stamped = []
    for path in directory.iterdir():
        with contextlib.suppress(OSError):  # removed meanwhile by another process
            stamped.append((path.stat().st_mtime, path))
    stale = time.time() - 3600
    temporary = [p for t, p in stamped if p.name.startswith(".") and t < stale]
    entries = sorted((item for item in stamped if not item[1].name.startswith(".")), reverse=True)
    for old in temporary + [p for _, p in entries[MAX_ENTRIES:]]:
        shutil.rmtree(old, ignore_errors=True)


def warn(message: str) -> None:
    """``td3-jax: warning: message`` on stderr, by the first process only."""
    if jax.process_index() == 0:
        print(f"td3-jax: warning: {message}", file=sys.stderr)
