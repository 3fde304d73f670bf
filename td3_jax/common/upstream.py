"""Every place td3-jax relies on a private name (or a private layout) of the libraries below it.

Each touch is one small function here, named for what it does; callers use these functions and
never the private names themselves. ``tests/common/test_upstream.py`` holds one canary test per
name: it fails, naming the upstream name, when a new upstream version renames or removes it. At
run time a missing name raises :class:`UpstreamChanged` instead of being skipped: nothing here is
ever a silent no-op (an attribute swapped for domain randomisation is checked to exist first).

Checked against (``checked`` in each docstring): JAX 0.10.2 and 0.11.2; MuJoCo (``mujoco`` and
its ``mujoco.mjx``, with the MuJoCo Warp it vendors) 4.0.0; MuJoCo Playground
(``playground`` on PyPI) 0.2.0; Brax 0.14.2; tensorboardX 2.6.5; tyro 1.0.17.

One module, not ``td3_jax.envs.upstream``: JAX's compilation-cache layout is the CLI's, not an
environment's. Nothing heavy is imported here; each function imports what it touches.
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from td3_jax.common import skipped_imports
from td3_jax.common.errors import UpstreamChanged

__all__ = [
    "CALL_PRIMITIVES",
    "CONCATENATE",
    "COPY_PRIMITIVES",
    "JAX_ATIME_SUFFIX",
    "JAX_CACHE_SUFFIX",
    "JAX_DISTRIBUTED",
    "MJX_IO",
    "MJX_RESOLVER",
    "MJX_WARP_BATCH_DIM",
    "MJX_WARP_SHARED_DATA",
    "MJX_WARP_TYPES",
    "PLAYGROUND_LOCOMOTION",
    "PLAYGROUND_MENAGERIE",
    "PLAYGROUND_MJX_ENV",
    "TASK_MODEL",
    "TENSORBOARD_EVENT_WRITER_PARTS",
    "TYRO_UNWRAP",
    "XLA_TRITON_GEMM",
    "UpstreamChanged",
    "abandon_tensorboard_writer",
    "brax_env_names",
    "called_jaxpr",
    "compile_options",
    "concatenation_axis",
    "distributed_process_id",
    "distributed_store",
    "jax_cache_atime",
    "jax_cache_entries",
    "jax_cache_timestamp",
    "may_copy",
    "mjx_device_resolver",
    "playground_locomotion",
    "playground_menagerie_at",
    "playground_menagerie_path",
    "playground_module",
    "quiet_warp_overflow_warnings",
    "set_mjx_device_resolver",
    "set_task_mjx_model",
    "simulating",
    "stamp_jax_cache_entries",
    "task_mjx_model",
    "tyro_help_unwrapped_by",
    "warp_overflow_flags",
    "warp_per_world_model_fields",
    "warp_shared_data_fields",
]


def _require(owner: Any, name: str, upstream: str) -> Any:
    """``owner.name``, or :class:`UpstreamChanged` naming ``upstream`` when it is absent."""
    try:
        return getattr(owner, name)
    except AttributeError as err:
        raise UpstreamChanged(
            f"{upstream} is gone from this version of its library; td3-jax relies on it "
            "(see td3_jax/common/upstream.py for the versions checked)"
        ) from err


def _private_module(name: str) -> Any:
    """The module ``name`` of an installed library; :class:`UpstreamChanged` when the library
    is there but the module is not (``ImportError`` when the library itself is absent)."""
    importlib.import_module(name.split(".")[0])
    try:
        return importlib.import_module(name)
    except ModuleNotFoundError as err:
        if err.name is None or not (name == err.name or name.startswith(err.name + ".")):
            raise  # a dependency of the module is missing, not the module
        raise UpstreamChanged(
            f"{name} is gone from this version of its library; td3-jax relies on it "
            "(see td3_jax/common/upstream.py for the versions checked)"
        ) from err


# ---------------------------------------------------------------------------------------------
# XLA: how GPU matmuls are compiled
# ---------------------------------------------------------------------------------------------

#: XLA's compile option that sends GPU matmuls to its Triton GEMM emitter (on by default;
#: ``DebugOptions.xla_gpu_enable_triton_gemm``; checked: JAX 0.10.2 CPU, 0.11.2 H100).
XLA_TRITON_GEMM = "xla_gpu_enable_triton_gemm"


def compile_options(platform: str, matmuls: str = "auto", xla_flags: str | None = None) -> dict:
    """The compile options of a run's programs on ``platform`` (``jax.Device.platform``).

    ``matmuls="cublas"`` on a GPU turns XLA's Triton GEMM emitter off, so cuBLAS runs the
    matrix products (faster for the robot presets' C51 update, slower for the ant preset's
    loop: docs/benchmarks.md, "Playground robot presets"). ``"auto"`` leaves XLA's choice.
    Where ``xla_flags`` (default: the ``XLA_FLAGS`` environment variable) sets the option
    itself, it stands and nothing is added; on other platforms no option is given.
    """
    flags = os.environ.get("XLA_FLAGS", "") if xla_flags is None else xla_flags
    named = {flag.lstrip("-").split("=", 1)[0] for flag in flags.split()}
    if matmuls != "cublas" or platform != "gpu" or XLA_TRITON_GEMM in named:
        return {}
    return {XLA_TRITON_GEMM: False}


# ---------------------------------------------------------------------------------------------
# tensorboardX: ending a writer whose flush the disk refused
# ---------------------------------------------------------------------------------------------

#: The private parts of a tensorboardX ``EventFileWriter`` that :func:`abandon_tensorboard_writer`
#: ends (checked: tensorboardX 2.6.5).
TENSORBOARD_EVENT_WRITER_PARTS = ("_closed", "_worker", "_ev_writer", "_event_queue")


def abandon_tensorboard_writer(writer: Any) -> None:
    """Ends a tensorboardX ``SummaryWriter`` whose flush failed, giving up what it could not
    write: each event writer's thread is stopped, its file and queue closed (each on its own:
    one may fail again) and it is marked closed, so tensorboardX's exit hook and thread print
    no tracebacks."""
    for file_writer in (writer.all_writers or {}).values():
        events = file_writer.event_writer
        if getattr(events, "_closed", True):
            continue
        with contextlib.suppress(Exception):
            events._worker.stop()
        with contextlib.suppress(Exception):  # (its buffer, which the disk refused, is dropped)
            events._ev_writer._py_recordio_writer.close()
        with contextlib.suppress(Exception):
            events._event_queue.close()
        events._closed, events._event_queue, events._worker = True, None, None
    writer.file_writer = writer.all_writers = None


# ---------------------------------------------------------------------------------------------
# tyro: how help text is unwrapped
# ---------------------------------------------------------------------------------------------

#: tyro's function that joins a docstring's lines into help paragraphs
#: (``tyro._strings.remove_single_line_breaks``; checked: tyro 0.9.1 to 1.0.17). It runs before the
#: docstring is dedented, so each indented continuation line of a field's docstring stayed a
#: line break of its own in ``--help`` (ragged text at any width but the source's).
TYRO_UNWRAP = ("tyro._strings", "remove_single_line_breaks")


@contextlib.contextmanager
def tyro_help_unwrapped_by(unwrap: Callable[[str], str]) -> Iterator[None]:
    """Inside, tyro turns docstrings into help text with ``unwrap`` (text -> paragraphs).

    The one exception to this module's rule that nothing is a silent no-op: where a tyro
    version has renamed the function, nothing is swapped (help text is then only wrapped as
    tyro wraps it; every command must still parse), and the canary test fails instead."""
    try:
        module = _private_module(TYRO_UNWRAP[0])
        original = _require(module, TYRO_UNWRAP[1], ".".join(TYRO_UNWRAP))
    except UpstreamChanged:
        yield
        return
    setattr(module, TYRO_UNWRAP[1], unwrap)
    try:
        yield
    finally:
        setattr(module, TYRO_UNWRAP[1], original)


# ---------------------------------------------------------------------------------------------
# JAX: the persistent compilation cache's files
# ---------------------------------------------------------------------------------------------

#: JAX's persistent compilation cache keeps entry ``KEY`` in the file ``KEY-cache`` and, when its
#: size is capped, the entry's last use in ``KEY-atime`` (``jax._src.lru_cache._CACHE_SUFFIX``
#: and ``_ATIME_SUFFIX``; checked: JAX 0.10.2, 0.11.2).
JAX_CACHE_SUFFIX = "-cache"
JAX_ATIME_SUFFIX = "-atime"


def jax_cache_entries(path: Path) -> list[Path]:
    """The entry files of JAX's compilation cache at ``path`` (:data:`JAX_CACHE_SUFFIX`)."""
    return sorted(path.glob(f"*{JAX_CACHE_SUFFIX}"))


def jax_cache_atime(entry: Path) -> Path:
    """The access-time file of a cache entry file (:data:`JAX_ATIME_SUFFIX`)."""
    return entry.with_name(entry.name.removesuffix(JAX_CACHE_SUFFIX) + JAX_ATIME_SUFFIX)


def jax_cache_timestamp() -> bytes:
    """Now, as JAX's size-capped cache writes an access time: nanoseconds since the epoch in 8
    little-endian bytes (``jax._src.lru_cache.LRUCache``; checked: JAX 0.10.2, 0.11.2)."""
    import time

    return time.time_ns().to_bytes(8, "little")


def stamp_jax_cache_entries(path: Path) -> None:
    """Gives every entry of the compilation cache at ``path`` the access-time file that JAX's
    size-capped cache reads when it evicts (entries written without a cap, e.g. by an earlier
    td3-jax, have none, and JAX would then fail to write any new entry)."""
    stamp = jax_cache_timestamp()
    for entry in jax_cache_entries(path):
        atime = jax_cache_atime(entry)
        if not atime.exists():
            try:
                atime.write_bytes(stamp)
            except OSError:  # a read-only cache: JAX reports its own write errors
                return


# ---------------------------------------------------------------------------------------------
# JAX: primitive names in a traced program (read to prove an observation prefix)
# ---------------------------------------------------------------------------------------------

#: Primitives that call an inner jaxpr: ``jax.jit``'s (``pjit`` before JAX 0.7, ``jit`` since;
#: checked: 0.10.2, 0.11.2) and ``closed_call``.
CALL_PRIMITIVES = ("pjit", "jit", "closed_call")
#: Primitives that return their input unchanged when its shape and dtype are kept (``copy_p``:
#: ``copy``'s name in older JAX).
COPY_PRIMITIVES = ("reshape", "copy", "copy_p", "convert_element_type")
#: ``lax.concatenate``'s primitive; its axis is the parameter ``dimension``.
CONCATENATE = "concatenate"


def called_jaxpr(eqn: Any) -> Any:
    """The jaxpr a ``jit``-like equation calls (its ``jaxpr`` or ``call_jaxpr`` parameter,
    unwrapped from a closed jaxpr), or ``None`` for any other equation."""
    if eqn.primitive.name not in CALL_PRIMITIVES:
        return None
    inner = eqn.params.get("jaxpr") or eqn.params.get("call_jaxpr")
    return getattr(inner, "jaxpr", inner)


def may_copy(eqn: Any) -> bool:
    """Whether ``eqn`` is a primitive that returns its input unchanged when the input's shape
    and dtype are kept (:data:`COPY_PRIMITIVES`)."""
    return eqn.primitive.name in COPY_PRIMITIVES


def concatenation_axis(eqn: Any) -> int | None:
    """The axis ``eqn`` concatenates along, or ``None`` when it is no concatenation."""
    return eqn.params["dimension"] if eqn.primitive.name == CONCATENATE else None


# ---------------------------------------------------------------------------------------------
# Brax
# ---------------------------------------------------------------------------------------------


def brax_env_names() -> list[str]:
    """Brax's environment names, from its registry ``brax.envs._envs`` (Brax has no public
    listing; checked: Brax 0.14.2)."""
    from brax import envs

    return sorted(_require(envs, "_envs", "brax.envs._envs"))


# ---------------------------------------------------------------------------------------------
# MJX (mujoco.mjx) and the MuJoCo Warp it steps with
# ---------------------------------------------------------------------------------------------

#: MJX's module whose ``_resolve_impl_and_device(impl, device) -> (impl, device)`` picks the
#: device of ``put_model``/``make_data``/``put_data`` (checked: MuJoCo 4.0.0).
MJX_IO = "mujoco.mjx._src.io"
MJX_RESOLVER = "_resolve_impl_and_device"


#: JAX's distributed runtime state, whose ``client`` holds the key-value store every process
#: of a ``jax.distributed`` run shares (``key_value_set(key, value)``,
#: ``blocking_key_value_get(key, timeout_in_ms)``; checked: JAX 0.10.2 CPU; tested by
#: tests/common/test_upstream.py).
JAX_DISTRIBUTED = "jax._src.distributed"


def distributed_store() -> Any:
    """The key-value store shared by the processes of this ``jax.distributed`` run (its
    client; ``None`` before ``jax.distributed.initialize``)."""
    module = _private_module(JAX_DISTRIBUTED)
    state = _require(module, "global_state", f"{JAX_DISTRIBUTED}.global_state")
    return _require(state, "client", f"{JAX_DISTRIBUTED}.global_state.client")


def distributed_process_id() -> int:
    """This process's id in its ``jax.distributed`` run, as it joined (0 before
    ``jax.distributed.initialize``), read without starting JAX's backend (which
    ``jax.process_index()`` does, and which may fail or wait for a process that is gone)."""
    module = _private_module(JAX_DISTRIBUTED)
    state = _require(module, "global_state", f"{JAX_DISTRIBUTED}.global_state")
    return _require(state, "process_id", f"{JAX_DISTRIBUTED}.global_state.process_id")


def mjx_device_resolver() -> Callable[..., tuple[Any, Any]] | None:
    """MJX's ``mujoco.mjx._src.io._resolve_impl_and_device`` (``None`` without MJX;
    :class:`UpstreamChanged` when MJX is there without it)."""
    try:
        import mujoco.mjx  # noqa: F401
    except ImportError:  # MJX not installed: gymnax environments only
        return None
    return _require(_private_module(MJX_IO), MJX_RESOLVER, f"{MJX_IO}.{MJX_RESOLVER}")


def set_mjx_device_resolver(resolve: Callable[..., tuple[Any, Any]]) -> None:
    """Makes ``resolve`` MJX's ``_resolve_impl_and_device`` (which must already exist)."""
    module = _private_module(MJX_IO)
    _require(module, MJX_RESOLVER, f"{MJX_IO}.{MJX_RESOLVER}")
    setattr(module, MJX_RESOLVER, resolve)


#: MJX's Warp bridge and its table of the fields that carry a per-world axis
#: (``_BATCH_DIM["Model"]``: field name -> whether MuJoCo Warp simulates it per world when it is
#: batched under ``jax.vmap``; checked: MuJoCo 4.0.0).
MJX_WARP_TYPES = "mujoco.mjx.warp.types"
MJX_WARP_BATCH_DIM = "_BATCH_DIM"


def warp_per_world_model_fields() -> frozenset[str]:
    """The ``mujoco.mjx.Model`` fields that MuJoCo Warp simulates per world (one value per
    environment) when they carry a batch axis: the True entries of MJX's Warp bridge's
    ``mujoco.mjx.warp.types._BATCH_DIM["Model"]``."""
    table = _require(_private_module(MJX_WARP_TYPES), MJX_WARP_BATCH_DIM,
                     f"{MJX_WARP_TYPES}.{MJX_WARP_BATCH_DIM}")  # fmt: skip
    return frozenset(name for name, per_world in table["Model"].items() if per_world is True)


#: ``mujoco.mjx.warp.types.DATA_NON_VMAP``: the ``Data._impl`` fields MuJoCo Warp keeps once for
#: all the worlds stepped together, without a batch axis (its contact buffer, its counters;
#: checked: MuJoCo 4.0.0).
MJX_WARP_SHARED_DATA = "DATA_NON_VMAP"


def warp_shared_data_fields() -> frozenset[str]:
    """The fields of an MJX ``Data`` stepped by Warp (``data._impl.NAME``) that have no batch
    axis: one buffer for all the environments of a batched call
    (``mujoco.mjx.warp.types.DATA_NON_VMAP``)."""
    names = _require(_private_module(MJX_WARP_TYPES), MJX_WARP_SHARED_DATA,
                     f"{MJX_WARP_TYPES}.{MJX_WARP_SHARED_DATA}")  # fmt: skip
    return frozenset(names)


def warp_overflow_flags(data: Any) -> Any:
    """MuJoCo Warp's per-environment overflow flags (its ``OverflowType`` bits) of an MJX
    ``Data`` stepped by Warp: ``data._impl.overflow`` (``mujoco.mjx.Data._impl``, a
    ``mujoco.mjx.warp.types.DataWarp``; checked: MuJoCo 4.0.0)."""
    impl = _require(data, "_impl", "mujoco.mjx.Data._impl")
    return _require(impl, "overflow", "mujoco.mjx.warp.types.DataWarp.overflow")


#: MJX's copy of MuJoCo Warp (``put_model``, ``put_data``, ``forward``, ``step``) and Warp's
#: module class, whose ``load(device, block_dim)`` compiles or loads a module (checked: MuJoCo
#: 4.0.0, warp-lang 1.19.0).
MJX_MUJOCO_WARP = "mujoco.mjx.third_party.mujoco_warp"
WARP_CONTEXT = "warp._src.context"


def mjx_mujoco_warp() -> Any:
    """The MuJoCo Warp package that MJX steps (:data:`MJX_MUJOCO_WARP`)."""
    return _private_module(MJX_MUJOCO_WARP)


def warp_module_class() -> Any:
    """Warp's ``Module`` class (:data:`WARP_CONTEXT`), whose ``load`` method every kernel
    launch calls before it runs the kernel."""
    return _require(_private_module(WARP_CONTEXT), "Module", f"{WARP_CONTEXT}.Module")


def mjx_warp_options(model: Any) -> Any:
    """MuJoCo Warp's own options of an MJX model made on Warp: ``model.opt._impl``
    (``mujoco.mjx.Option._impl``, a ``mujoco.mjx.warp.types.OptionWarp``; checked: MuJoCo
    4.0.0)."""
    return _require(model.opt, "_impl", "mujoco.mjx.Option._impl")


def quiet_warp_overflow_warnings(task: Any, bits: int) -> None:
    """Clears ``bits`` from MuJoCo Warp's ``warn_overflow`` option of the Playground ``task``'s
    model: ``model.opt._impl.warn_overflow`` (``mujoco.mjx.Option._impl``, a
    ``mujoco.mjx.warp.types.OptionWarp``; checked: MuJoCo 4.0.0)."""
    model = task_mjx_model(task)
    option = mjx_warp_options(model)
    warn = _require(option, "warn_overflow", "mujoco.mjx.warp.types.OptionWarp.warn_overflow")
    quieter = option.replace(warn_overflow=int(warn) & ~bits)
    set_task_mjx_model(task, model.replace(opt=model.opt.replace(_impl=quieter)))


# ---------------------------------------------------------------------------------------------
# MuJoCo Playground
# ---------------------------------------------------------------------------------------------

#: Playground's module holding the locomotion registry (``ALL_ENVS``, ``get_default_config``,
#: ``load``, ``get_domain_randomizer``) and the one holding ``MENAGERIE_PATH`` and
#: ``ensure_menagerie_exists`` (checked: Playground 0.2.0).
PLAYGROUND_LOCOMOTION = "mujoco_playground._src.locomotion"
PLAYGROUND_MJX_ENV = "mujoco_playground._src.mjx_env"
#: The attribute of a Playground task (``mjx_env.MjxEnv``) holding the MJX model its ``reset``
#: and ``step`` simulate; Playground's own ``wrapper.BraxDomainRandomizationVmapWrapper`` swaps
#: it the same way (checked: Playground 0.2.0).
TASK_MODEL = "_mjx_model"
#: Where Playground's ``mjx_env.MENAGERIE_PATH`` lies inside its package, the folder its
#: ``ensure_menagerie_exists`` clones the Menagerie into (checked: Playground 0.2.0).
PLAYGROUND_MENAGERIE = "mujoco_playground/external_deps/mujoco_menagerie"


def playground_module(name: str) -> Any:
    """Playground's module ``name``, Playground imported without the packages it imports but
    td3-jax never uses (:mod:`td3_jax.common.skipped_imports`: PyTorch)."""
    with skipped_imports.skipping_unused_imports() as skipped:
        try:
            return _private_module(name)
        except ModuleNotFoundError as err:
            if (err.name or "").partition(".")[0] not in skipped:
                raise
            raise UpstreamChanged(
                f"{name} now needs {err.name} to be imported; td3-jax imports MuJoCo Playground "
                "without it (td3_jax/common/skipped_imports.py; checked: Playground 0.2.0)"
            ) from err


def playground_locomotion() -> Any:
    """Playground's locomotion registry module (``ImportError`` without Playground)."""
    return playground_module(PLAYGROUND_LOCOMOTION)


def playground_menagerie_path() -> Path | None:
    """Where Playground reads the Menagerie by default, its ``mjx_env.MENAGERIE_PATH``
    (``<package>/external_deps/mujoco_menagerie``), found without importing Playground
    (``None`` without it; checked: Playground 0.2.0)."""
    package, inside = PLAYGROUND_MENAGERIE.split("/", 1)
    spec = importlib.util.find_spec(package)
    if spec is None or spec.origin is None:
        return None
    return Path(spec.origin).parent / inside


def _no_clone() -> None:
    """Stands in for Playground's ``ensure_menagerie_exists`` (which would ``git clone``)."""


@contextlib.contextmanager
def playground_menagerie_at(root: Path) -> Iterator[None]:
    """Points Playground at ``root`` (``mjx_env.MENAGERIE_PATH``) and disables its clone
    (``mjx_env.ensure_menagerie_exists``) while a task is built."""
    from etils import epath

    mjx_env = playground_module(PLAYGROUND_MJX_ENV)
    for name in ("MENAGERIE_PATH", "ensure_menagerie_exists"):
        _require(mjx_env, name, f"{PLAYGROUND_MJX_ENV}.{name}")
    saved = mjx_env.MENAGERIE_PATH, mjx_env.ensure_menagerie_exists
    mjx_env.MENAGERIE_PATH, mjx_env.ensure_menagerie_exists = epath.Path(root), _no_clone
    try:
        yield
    finally:
        mjx_env.MENAGERIE_PATH, mjx_env.ensure_menagerie_exists = saved


def _check_task(task: Any) -> None:
    """:class:`UpstreamChanged` unless ``task`` itself holds :data:`TASK_MODEL` (an attribute
    only found through a wrapper, or none at all, would be set without effect)."""
    if TASK_MODEL not in getattr(task, "__dict__", {}):
        raise UpstreamChanged(
            f"the Playground task {type(task).__name__} holds no attribute {TASK_MODEL} "
            f"(mujoco_playground's MjxEnv.{TASK_MODEL}): td3-jax swaps it to simulate a "
            "randomised or adjusted model and will not set it where Playground does not read "
            "it (see td3_jax/common/upstream.py for the versions checked)"
        )


def task_mjx_model(task: Any) -> Any:
    """The MJX model a Playground task simulates (its :data:`TASK_MODEL`)."""
    _check_task(task)
    return getattr(task, TASK_MODEL)


def set_task_mjx_model(task: Any, model: Any) -> None:
    """Makes the Playground task simulate ``model`` (its :data:`TASK_MODEL`, which must
    exist: never a new attribute)."""
    _check_task(task)
    setattr(task, TASK_MODEL, model)


@contextlib.contextmanager
def simulating(task: Any, model: Any) -> Iterator[None]:
    """The Playground task simulating ``model`` meanwhile (its own model back after), as
    Playground's own domain-randomisation wrapper does while tracing."""
    saved = task_mjx_model(task)
    set_task_mjx_model(task, model)
    try:
        yield
    finally:
        set_task_mjx_model(task, saved)
