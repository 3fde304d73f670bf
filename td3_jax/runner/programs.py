"""A run's compiled programs: init, chunk and evaluate for a device mesh, traced in this process
or read back from the program store (:mod:`td3_jax.runner.program_cache`), one type whatever their
origin.

Two steps, so that a run checks its directory between them: :func:`find` looks the programs up
in the store and makes the population's program (its environment included) only when none is
stored; :func:`compiled` compiles them side by side and returns :class:`Programs`. The host
loop (:mod:`td3_jax.runner.run`) never asks where they came from.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from td3_jax.common import upstream
from td3_jax.common.errors import ConfigError
from td3_jax.common.runtime import StopToken, in_background, result
from td3_jax.config.build import make_population, member_hyperparams
from td3_jax.config.schema import TrainConfig
from td3_jax.core.population import Member, Population, member_keys
from td3_jax.core.training import Hyperparams, TrainState
from td3_jax.envs import Environment, is_custom, warp_kernels
from td3_jax.runner import program_cache
from td3_jax.runner.program_cache import FlatProgram
from td3_jax.runner.sharding import check_program_memory, replicate, state_shardings

__all__ = [
    "Programs",
    "Source",
    "abstract_state",
    "chunk_argument_specs",
    "compile_ahead",
    "compile_options",
    "compiled",
    "find",
    "jitted",
    "options_on",
    "run_compiled",
    "with_sharding",
]


class Programs(NamedTuple):
    """A population's programs compiled (or jitted) for a device mesh
    (:mod:`td3_jax.runner.sharding`).

    Attributes:
      abstract_state: shapes and dtypes of the train state (every leaf ``[members, ...]``).
      shardings: the state's shardings on the mesh (a tree like the state).
      hyperparams: the members' float settings replicated on the mesh (leaves ``[members]``;
        the ``hp`` to pass to ``chunk``).
      init: ``init() -> state`` (``None`` where compiled without it: a resumed run).
      chunk: ``chunk(hp, state, iterations) -> (state, metrics[members])``, the chunk's
        iterations (``Population.iterate`` of :class:`td3_jax.core.population.Population`),
        after ``start_round`` where there is one (:meth:`train_chunk` runs both);
        ``iterations`` is an int32 scalar; donates its state.
      evaluate: ``evaluate(state) -> returns[members, eval_envs]`` with the run's key
        schedule (with ``eval_in_chunk``: the returns of the chunk's evaluation round).
      start_round: ``start_round(state) -> state``, with ``eval_in_chunk``: starts the
        chunk's evaluation round (a program of its own, compiled beside the chunk); donates
        its state. ``None`` without.
    Metrics and returns come back replicated.
    """

    abstract_state: Any
    shardings: Any
    hyperparams: Hyperparams
    init: Callable[[], TrainState] | None
    chunk: Callable[..., tuple[TrainState, dict[str, jax.Array]]]
    evaluate: Callable[[TrainState], jax.Array]
    start_round: Callable[[TrainState], TrainState] | None = None

    def train_chunk(self, state: TrainState, iterations: Any) -> tuple[TrainState, dict]:
        """One chunk of ``iterations`` (an int32 scalar): its evaluation round started where
        there is one (``start_round``), then its iterations (``chunk``)."""
        if self.start_round is not None:
            state = self.start_round(state)
        return self.chunk(self.hyperparams, state, iterations)


@dataclasses.dataclass
class Source:
    """Where a run's programs come from, before they are compiled: ``stored`` (read back from
    the store, their pytree structures ``trees`` loading in a thread) or ``program`` (the
    population traced in this process, stored under ``directory/key`` once exported)."""

    cfg: TrainConfig
    population: list[Member]
    mesh: Mesh
    names: tuple[str, ...]
    directory: Path | None = None
    key: str | None = None
    stored: dict[str, FlatProgram] | None = None
    trees: Future | None = None
    program: Population | None = None

    @property
    def env(self) -> Environment | None:
        """The environment, where this process made it (stored programs need none)."""
        return None if self.program is None else self.program.spec.env


# --------------------------------------------------------------------------------------------
# the seam: find, then compile
# --------------------------------------------------------------------------------------------


def find(cfg: TrainConfig, population: list[Member], mesh: Mesh, directory: Path | None,
         with_init: bool = True, env: Any = None) -> Source:  # fmt: skip
    """Looks the run's programs up in ``directory`` (``None``, several processes, MuJoCo Warp
    physics, whose FFI calls ``jax.export`` refuses, or an environment of your own, whose code
    the key cannot see: never) and makes the population's program, environment included
    (``env`` when given: :func:`td3_jax.config.build.make_env`), only when none is stored; nothing
    is compiled."""
    names = program_cache.names(with_init, cfg.eval_in_chunk)
    source = Source(cfg, population, mesh, names)
    if cfg.impl == "warp" or env is not None or is_custom(cfg.env):
        directory = None  # XLA's persistent compilation cache still applies
    if directory is not None and jax.process_count() == 1:
        overrides = [tuple(name for name, _ in m.overrides) for m in population]
        source.key = program_cache.fingerprint(cfg, overrides, mesh)
        source.directory = Path(directory)
        source.stored, source.trees = program_cache.load(source.directory, source.key, names)
    if source.stored is None:
        source.program = make_population(cfg, population, devices=mesh.size, env=env,
                                         mesh=mesh)
    return source


def abstract_state(source: Source) -> Any:
    """Shapes and dtypes of the run's train state (every leaf ``[members, ...]``; for
    restoring a checkpoint); stored programs whose structure cannot be read are given up for
    the population's program (:func:`_give_up_stored`)."""
    if source.stored is not None:
        try:
            return source.trees.result()["state"]
        except Exception as err:  # e.g. a class it names no longer exists
            _give_up_stored(source, err)
    return source.program.abstract_state


def compiled(source: Source, stop: StopToken | None = None,
             check: Callable[[Any], None] | None = None,
             traced: Callable[[Any], None] | None = None) -> Programs:  # fmt: skip
    """The run's :class:`Programs`, compiled side by side: stored ones read back, otherwise
    each is traced, handed to a thread to compile while the next is traced, then stored.

    ``check(abstract_state)``, if given, runs once the state's shapes are known and before any
    compile is waited for (before tracing; for stored programs, while they compile): e.g. that
    the state fits in memory and its checkpoints on the disk. ``traced(abstract_state)``, if
    given, runs once, as soon as every program is traced and handed to a thread to compile (for
    stored programs, after ``check``, and not again where they are given up and traced
    instead), before any compile is waited for: the caller's own work that would otherwise
    delay the tracing (e.g. lowering a checkpoint's program); where it raises, the compiles
    already handed over run to their end unused. Without a directory (or when exporting fails)
    the programs are compiled as jitted functions (:func:`compile_ahead`), the same programs,
    stored nowhere. Stored programs that fail to compile are given up and the programs traced
    instead. Once ``stop`` is set, nothing more is traced or waited for (KeyboardInterrupt).
    """
    stop = stop if stop is not None else StopToken()
    stop.raise_if_set()  # a Ctrl-C Python discarded while tracing
    futures = _compile_stored(source)  # compiling while the state's structure is read back
    shapes = abstract_state(source)
    if check is not None:
        check(shapes)
    traced = _at_most_once(None if traced is None else functools.partial(traced, shapes))
    if source.stored is not None and traced is not None:
        traced()
    if source.stored is not None:
        try:
            return _stored_programs(source, futures, stop)
        except Exception as err:  # e.g. a program that reads back but does not compile
            _give_up_stored(source, err)
    if source.directory is None:
        return _compile_plain(source, stop, traced)
    try:
        return _compile_traced(source, stop, traced)
    except _ExportFailed as err:
        program_cache.warn(f"the traced programs cannot be kept ({err.__cause__}); compiling "
                           "them as usual")  # fmt: skip
        return _compile_plain(source, stop, traced)


def _at_most_once(function: Callable[[], None] | None) -> Callable[[], None] | None:
    """``function`` that runs on its first call only (``None`` stays ``None``)."""
    if function is None:
        return None
    calls = []

    def once() -> None:
        if not calls:
            calls.append(None)
            function()

    return once


def _give_up_stored(source: Source, err: BaseException) -> None:
    """Discards the source's unusable stored programs and makes the population's program
    instead (its environment included), so the run traces as if nothing had been stored."""
    program_cache.discard(source.directory / source.key, err)
    source.stored = source.trees = None
    source.program = make_population(source.cfg, source.population, devices=source.mesh.size,
                                     mesh=source.mesh)


class _ExportFailed(RuntimeError):
    """jax.export refused a program (the run compiles it the usual way instead)."""


# --------------------------------------------------------------------------------------------
# each origin
# --------------------------------------------------------------------------------------------


def compile_options(source: Source) -> dict:
    """The XLA compile options of the run's programs: ``--matmuls`` on its devices
    (:func:`td3_jax.common.upstream.compile_options`)."""
    return options_on(source.cfg, source.mesh.devices.flat[0])


def options_on(cfg: TrainConfig, device: jax.Device) -> dict:
    """The XLA compile options of the programs of the run of ``cfg`` on ``device``."""
    return upstream.compile_options(device.platform, cfg.matmuls)


def run_compiled(
    cfg: TrainConfig, function: Callable, *args: Any, doing: str = "the program",
    advice: str = "fewer --episodes",
) -> Any:  # fmt: skip
    """``function(*args)``, jitted and compiled with the compile options of the run of ``cfg``
    on the default device (as its training programs were, :func:`compile_options`): how a
    finished run's programs (``td3-jax eval``, ``render``) run, waited for. A program too big
    for the device's memory raises :class:`ConfigError` (``doing``, ``advice``: its message)
    before it runs (:func:`td3_jax.runner.sharding.check_program_memory`), as does an allocation
    that XLA refuses while compiling or running it."""
    device = jax.devices()[0]
    with out_of_memory_as_config_error(device, doing, advice):
        # (a GPU compile may run out first: its autotuner allocates the program's operands)
        compiled = jax.jit(function).lower(*args).compile(compiler_options=options_on(cfg, device))
        check_program_memory(compiled, device, doing, advice)
        return jax.block_until_ready(compiled(*args))


@contextlib.contextmanager
def out_of_memory_as_config_error(device: Any, doing: str, advice: str) -> Iterator[None]:
    """An allocation XLA refuses in the block (``RESOURCE_EXHAUSTED``) becomes one line, a
    :class:`ConfigError`: ``doing`` does not fit in ``device``'s memory, XLA's words (cut
    before its buffer dump), then ``use {advice}``; other errors pass as they are."""
    try:
        yield
    except jax.errors.JaxRuntimeError as err:
        if "RESOURCE_EXHAUSTED" not in str(err) and "Out of memory" not in str(err):
            raise
        said = " ".join(str(err).split("BufferAssignment")[0].split())[:300]  # (not its dump)
        raise ConfigError(f"{doing} does not fit in {device.device_kind}'s memory ({said}); "
                          f"use {advice}") from None  # fmt: skip


def _compile_plain(source: Source, stop: StopToken, traced: Callable[[], None] | None = None
                   ) -> Programs:  # fmt: skip
    """The traced population jitted for the mesh and compiled now (stored nowhere);
    ``traced()`` once all are handed to their compiles."""
    programs = jitted(source.program, source.mesh)
    return compile_ahead(programs, source.program, with_init="init" in source.names, stop=stop,
                         options=compile_options(source), traced=traced)  # fmt: skip


def _compile_stored(source: Source) -> dict[str, Future]:
    """The stored programs handed to threads that compile them (read back from the
    compilation cache); ``{}`` where none are stored."""
    if source.stored is None:
        return {}
    options = compile_options(source)
    return {name: in_background(program_cache.compile_flat, source.stored[name], source.mesh,
                                options)
            for name in source.names}  # fmt: skip


def _stored_programs(source: Source, futures: dict[str, Future], stop: StopToken) -> Programs:
    """The stored programs, once compiled."""
    inputs = _placed_inputs(source)
    trees = result(source.trees, stop)
    executables = {name: result(future, stop) for name, future in futures.items()}
    return _flat_programs(source, executables, trees, *inputs)


def _compile_traced(source: Source, stop: StopToken, traced: Callable[[], None] | None = None
                    ) -> Programs:  # fmt: skip
    """The programs traced and exported (all of them, so the stored entry is complete), the
    run's compiled side by side (``traced()`` once all are handed over), then stored."""
    futures, flat, trees = _export_each(source, stop)
    if traced is not None:
        traced()
    program_cache.save(source.directory, source.key, flat, trees)
    inputs = _placed_inputs(source)
    executables = {name: result(future, stop) for name, future in futures.items()}
    return _flat_programs(source, executables, trees, *inputs)


def _placed_inputs(source: Source) -> tuple[Any, Any]:
    """The members' hyperparameters and start keys, replicated on the mesh."""
    hp = member_hyperparams(source.cfg, source.population)
    place = lambda x: replicate(x, source.mesh)
    return jax.tree.map(place, hp), place(member_keys(source.population))


def _export_each(source: Source, stop: StopToken) -> tuple[dict, dict, dict]:
    """Traces and exports each program, submitting the compile of each the run needs before
    tracing the next."""
    program, mesh = source.program, source.mesh
    replicated = NamedSharding(mesh, PartitionSpec())
    shardings = state_shardings(program.abstract_state, mesh)
    everywhere = lambda tree: jax.tree.map(lambda _: replicated, tree)
    hp, state, scalar = chunk_argument_specs(program, shardings)
    keys = jax.ShapeDtypeStruct(program.keys.shape, program.keys.dtype, sharding=replicated)
    plans = {
        "chunk": (program.iterate, (hp, state, scalar),
                  lambda out: (shardings, everywhere(out[1])), (1,)),
        program_cache.ROUND: (program.start_round, (state,), lambda out: shardings, (0,)),
        "evaluate": (program.scheduled_evaluate, (state,), everywhere, ()),
        "init": (program.init_from_keys, (keys,), lambda out: shardings, ()),
    }  # fmt: skip
    executables, flat, trees = {}, {}, {"state": program.abstract_state}
    for name in program_cache.names(True, program.start_round is not None):
        stop.raise_if_set()
        try:
            flat[name], trees[name] = program_cache.export_flat(*plans[name])
        except Exception as err:  # e.g. a custom call jax.export does not take
            raise _ExportFailed(name) from err
        if name in source.names:  # a resume needs no init, but the entry keeps it
            executables[name] = in_background(program_cache.compile_flat, flat[name], mesh,
                                              compile_options(source))  # fmt: skip
    warp_kernels.programs_traced()
    return executables, flat, trees


def _flat_programs(source: Source, executables: dict, trees: dict, hp: Any, keys: Any) -> Programs:
    """The run's :class:`Programs` over the flat executables."""
    calls = {name: program_cache.as_tree_function(executables[name], trees[name])
             for name in executables}  # fmt: skip
    init = calls.get("init")
    return Programs(
        abstract_state=trees["state"],
        shardings=state_shardings(trees["state"], source.mesh),
        hyperparams=hp,
        init=(lambda: init(keys)) if init else None,
        chunk=calls["chunk"],
        evaluate=calls["evaluate"],
        start_round=calls.get(program_cache.ROUND),
    )


# --------------------------------------------------------------------------------------------
# a population jitted for a mesh
# --------------------------------------------------------------------------------------------


def jitted(program: Population, mesh: Mesh) -> Programs:
    """``program`` jitted with the state split over ``mesh`` (envs, replay), the rest
    replicated; each function compiles at its first call (:func:`compile_ahead`: now)."""
    shardings = state_shardings(program.abstract_state, mesh)
    replicated = NamedSharding(mesh, PartitionSpec())
    start_round = program.start_round
    if start_round is not None:
        start_round = jax.jit(start_round, in_shardings=(shardings,), out_shardings=shardings,
                              donate_argnums=0)  # fmt: skip
    return Programs(
        abstract_state=program.abstract_state,
        shardings=shardings,
        hyperparams=jax.tree.map(lambda x: replicate(x, mesh), program.hyperparams),
        init=jax.jit(program.init, out_shardings=shardings),
        chunk=jax.jit(
            program.iterate,
            in_shardings=(replicated, shardings, replicated),
            out_shardings=(shardings, replicated),
            donate_argnums=1,
        ),
        evaluate=jax.jit(program.scheduled_evaluate, out_shardings=replicated),
        start_round=start_round,
    )


def with_sharding(abstract: Any, shardings: Any) -> Any:
    """``abstract``'s leaves as ``ShapeDtypeStruct`` placed by ``shardings`` (same tree)."""
    return jax.tree.map(
        lambda a, s: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=s, weak_type=a.weak_type),
        abstract,
        shardings,
    )


def chunk_argument_specs(program: Population, shardings: Any) -> tuple[Any, Any, Any]:
    """The chunk's abstract arguments ``(hp, state, iterations)`` placed on a mesh: the state
    by ``shardings`` (:func:`td3_jax.runner.sharding.state_shardings`), the others replicated."""
    mesh = jax.tree.leaves(shardings)[0].mesh
    replicated = NamedSharding(mesh, PartitionSpec())
    hp = jax.eval_shape(lambda: program.hyperparams)
    hp_spec = with_sharding(hp, jax.tree.map(lambda _: replicated, hp))
    iterations = jax.ShapeDtypeStruct((), jnp.int32, sharding=replicated)
    return hp_spec, with_sharding(program.abstract_state, shardings), iterations


def compile_ahead(programs: Programs, program: Population, with_init: bool = True,
                  stop: StopToken | None = None, options: dict | None = None,
                  traced: Callable[[], None] | None = None) -> Programs:  # fmt: skip
    """``programs`` (:func:`jitted`) with their functions compiled now, side by side, instead
    of at their first call.

    Each program is traced (Python, one at a time) and handed to a thread that compiles it
    while the next is traced: the chunk first, as it takes longest. (Compiling the evaluation
    during the first chunk instead gained nothing on G1: its autotuning waits for the GPU,
    which the chunk holds.) The returned functions are the compiled executables: calling them
    with other shapes or shardings raises instead of recompiling. Once ``stop`` is set, the
    compiles are no longer waited for (KeyboardInterrupt). ``options``: XLA compile options
    (:func:`compile_options`). ``traced()``, if given, runs once every program is handed to
    its thread, before any is waited for.
    """
    stop = stop if stop is not None else StopToken()
    hp_spec, state_spec, iterations = chunk_argument_specs(program, programs.shardings)
    lowerings = {"chunk": lambda: programs.chunk.lower(hp_spec, state_spec, iterations)}
    if programs.start_round is not None:
        lowerings["start_round"] = lambda: programs.start_round.lower(state_spec)
    lowerings["evaluate"] = lambda: programs.evaluate.lower(state_spec)
    if with_init:
        lowerings["init"] = programs.init.lower
    futures = {}
    for name, lower in lowerings.items():
        futures[name] = in_background(functools.partial(lower().compile, compiler_options=options))
        stop.raise_if_set()
    warp_kernels.programs_traced()  # (Warp's kernels compile beside XLA's from here)
    if traced is not None:
        traced()
    return programs._replace(**{name: result(f, stop) for name, f in futures.items()})
