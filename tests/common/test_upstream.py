"""Canaries for td3_jax.common.upstream: one test per private upstream name td3-jax relies on,
failing with a message naming it when a new upstream version renames or removes it; and the checks
that turn a missing name into an error instead of a silent no-op. Each test takes a few seconds on
a CPU (the cache test runs two small Python processes)."""

from __future__ import annotations

import contextlib
import dataclasses
import importlib
import inspect
import io
import subprocess
import sys
import time
from types import SimpleNamespace

import jax
import jax.extend.core as jex_core
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

from td3_jax.common import upstream
from td3_jax.envs import locomotion, physics


def _traced(fn, *args):
    """The equations of ``fn``'s top-level jaxpr."""
    return jax.make_jaxpr(fn)(*args).jaxpr.eqns


def _names(eqns) -> list[str]:
    return [e.primitive.name for e in eqns]


# tensorboardX: ending a writer whose flush failed -------------------------------------------


def test_tensorboardx_event_writers_still_have_the_parts_td3_jax_ends(tmp_path):
    from tensorboardX import SummaryWriter

    writer = SummaryWriter(str(tmp_path))
    writer.add_scalar("x", 1.0, 0)
    events = next(iter(writer.all_writers.values())).event_writer
    missing = [n for n in upstream.TENSORBOARD_EVENT_WRITER_PARTS if not hasattr(events, n)]
    assert not missing, f"tensorboardX's EventFileWriter no longer has {missing}"
    assert hasattr(events._ev_writer, "_py_recordio_writer"), "tensorboardX's record writer moved"
    upstream.abandon_tensorboard_writer(writer)
    assert events._closed and writer.all_writers is None
    writer.close()  # what its exit hook does: nothing left to flush or fail


# tyro: help text ------------------------------------------------------------------------------


def test_tyro_turns_docstrings_into_help_through_the_replaced_function():
    """tyro still has the function and calls it for a field's docstring; inside the context it
    calls ours, and afterwards its own again."""
    import tyro

    @dataclasses.dataclass
    class Flags:
        width: int = 1
        """A width
        in units."""

    def help_of(flags: type) -> str:
        with pytest.raises(SystemExit), contextlib.redirect_stdout(io.StringIO()) as out:
            tyro.cli(flags, args=["--help"])
        return out.getvalue()

    module = importlib.import_module(upstream.TYRO_UNWRAP[0])
    original = getattr(module, upstream.TYRO_UNWRAP[1])
    with upstream.tyro_help_unwrapped_by(lambda text: "REPLACED " + text):
        assert "REPLACED A width" in help_of(Flags)
    assert getattr(module, upstream.TYRO_UNWRAP[1]) is original


def test_a_tyro_without_the_function_still_parses_every_command(monkeypatch):
    """Losing the re-wrapped help must not lose the CLI: with the function renamed away, the
    context swaps nothing and tyro parses as it does on its own."""
    import tyro

    renamed = ("tyro._strings", "a_name_a_later_tyro_might_use")  # (tyro calls its new name)
    monkeypatch.setattr(upstream, "TYRO_UNWRAP", renamed)

    @dataclasses.dataclass
    class Flags:
        width: int = 1

    with upstream.tyro_help_unwrapped_by(lambda text: "never used"):
        assert not hasattr(importlib.import_module(renamed[0]), renamed[1])
        assert tyro.cli(Flags, args=["--width", "3"]) == Flags(width=3)


# XLA: the GPU matmul option -------------------------------------------------------------------


def test_cublas_matmuls_turn_triton_gemm_off_on_a_gpu_unless_xla_flags_set_it():
    off = {upstream.XLA_TRITON_GEMM: False}
    assert upstream.compile_options("gpu", "cublas", xla_flags="") == off
    assert upstream.compile_options("gpu", "cublas", xla_flags="--xla_dump_to=/tmp/x") == off
    assert upstream.compile_options("gpu", "auto", xla_flags="") == {}  # XLA's own choice
    assert upstream.compile_options("cpu", "cublas", xla_flags="") == {}
    user = f"--{upstream.XLA_TRITON_GEMM}=true"
    assert upstream.compile_options("gpu", "cublas", xla_flags=user) == {}
    other = f"--{upstream.XLA_TRITON_GEMM}_int4=false --xla_dump_to=x"  # another flag: ours
    assert upstream.compile_options("gpu", "cublas", xla_flags=other) == off


def test_xla_still_accepts_the_triton_gemm_compile_option():
    """XLA checks option names on every backend (a CPU rejects unknown ones too), so a version
    that drops it fails here rather than in a GPU run's compile."""
    lowered = jax.jit(lambda x: x @ x).lower(jnp.ones((3, 3)))
    try:
        compiled = lowered.compile(compiler_options={upstream.XLA_TRITON_GEMM: False})
    except Exception as err:  # any rejection is the canary's message
        pytest.fail(f"XLA no longer accepts the compile option {upstream.XLA_TRITON_GEMM}: {err}")
    np.testing.assert_allclose(compiled(jnp.ones((3, 3))), 3 * np.ones((3, 3)))


# JAX: the persistent compilation cache's files ----------------------------------------------

_COMPILE = """
import sys, jax, jax.numpy as jnp
jax.config.update("jax_compilation_cache_dir", sys.argv[1])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
if sys.argv[2] != "uncapped":
    jax.config.update("jax_compilation_cache_max_size", 1 << 30)
jax.jit(lambda x: x * float(sys.argv[3]) + 1.0)(jnp.ones(3)).block_until_ready()
"""


def _compile_into(cache, capped: str, factor: str) -> None:
    subprocess.run([sys.executable, "-c", _COMPILE, str(cache), capped, factor],
                   check=True, capture_output=True, timeout=120)  # fmt: skip


def test_jax_cache_entries_and_access_times_are_named_as_td3_jax_stamps_them(tmp_path):
    """JAX's ``KEY-cache`` / ``KEY-atime`` files (``jax._src.lru_cache``): an entry written
    without a size cap gets its access time from td3-jax, after which a capped cache writes
    its own entries (with their access times) beside it."""
    pytest.importorskip("filelock")  # JAX's size cap needs it (the CLI stamps only then)
    _compile_into(tmp_path, "uncapped", "3.0")
    first = upstream.jax_cache_entries(tmp_path)
    assert first, (
        f"JAX's compilation cache no longer names entries '*{upstream.JAX_CACHE_SUFFIX}' "
        f"(jax._src.lru_cache._CACHE_SUFFIX): {sorted(p.name for p in tmp_path.iterdir())}"
    )
    upstream.stamp_jax_cache_entries(tmp_path)
    _compile_into(tmp_path, "capped", "5.0")
    entries = upstream.jax_cache_entries(tmp_path)
    assert len(entries) > len(first), "a capped JAX cache wrote no entry beside stamped ones"
    for entry in entries:
        atime = upstream.jax_cache_atime(entry)
        assert atime.exists(), (
            f"JAX's capped cache no longer keeps '{atime.name}' beside '{entry.name}' "
            f"(jax._src.lru_cache._ATIME_SUFFIX {upstream.JAX_ATIME_SUFFIX!r}): "
            f"{sorted(p.name for p in tmp_path.iterdir())}"
        )
        stamp = int.from_bytes(atime.read_bytes(), "little")
        assert len(atime.read_bytes()) == 8 and abs(stamp - time.time_ns()) < 600e9, (
            "JAX's access times are no longer 8 little-endian bytes of time.time_ns() "
            "(jax._src.lru_cache.LRUCache), as upstream.jax_cache_timestamp writes them"
        )


def test_stamping_leaves_stamped_entries_and_other_files_alone(tmp_path):
    (tmp_path / "a-cache").write_bytes(b"x")
    (tmp_path / "b-cache").write_bytes(b"y")
    (tmp_path / "b-atime").write_bytes(b"kept")
    (tmp_path / "other").write_bytes(b"z")
    upstream.stamp_jax_cache_entries(tmp_path)
    assert len((tmp_path / "a-atime").read_bytes()) == 8
    assert (tmp_path / "b-atime").read_bytes() == b"kept"
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "a-atime", "a-cache", "b-atime", "b-cache", "other"]  # fmt: skip


# JAX: primitive names in a traced program ----------------------------------------------------


def test_jit_calls_are_recognised_by_their_primitive_name():
    (eqn,) = _traced(lambda x: jax.jit(lambda y: y + 1.0)(x), 1.0)
    inner = upstream.called_jaxpr(eqn)
    assert inner is not None, (
        f"jax.jit now traces to the primitive {eqn.primitive.name!r}, not one of "
        f"upstream.CALL_PRIMITIVES {upstream.CALL_PRIMITIVES}"
    )
    assert _names(inner.eqns) == ["add"], "a jit equation's 'jaxpr' parameter moved"


def test_concatenate_is_recognised_with_its_axis():
    x = jnp.ones((2, 3))
    (eqn,) = _traced(lambda a: lax.concatenate([a, a], 1), x)
    assert upstream.concatenation_axis(eqn) == 1, (
        f"lax.concatenate now traces to {eqn.primitive.name!r} with parameters "
        f"{sorted(eqn.params)}, not {upstream.CONCATENATE!r} with 'dimension'"
    )
    assert upstream.concatenation_axis(_traced(lambda a: lax.concatenate([a, a], 0), x)[0]) == 0


@pytest.mark.parametrize(
    "fn",
    [lambda x: lax.reshape(x, (2, 3)), lambda x: lax.convert_element_type(x, jnp.int32),
     lambda x: jnp.array(x, copy=True)],
    ids=["reshape", "convert_element_type", "copy"],
)  # fmt: skip
def test_copying_primitives_are_recognised(fn):
    (eqn,) = _traced(fn, jnp.ones(6))
    assert upstream.may_copy(eqn), (
        f"{eqn.primitive.name!r} is not one of upstream.COPY_PRIMITIVES "
        f"{upstream.COPY_PRIMITIVES}: JAX renamed a primitive the prefix proof looks through"
    )


def test_the_prefix_proof_sees_through_a_jitted_hstack():
    """What Playground's tasks do (``jnp.hstack`` of the actor's observation and more) is
    still read as a prefix on this JAX; a different first piece is not."""

    def obs(a, b):
        return a, jnp.hstack([a.reshape(a.shape), b])

    closed = jax.make_jaxpr(obs)(jnp.ones(3), jnp.ones(2))
    assert locomotion._prefix_in(closed.jaxpr, closed.jaxpr.outvars), (
        f"the prefix proof no longer reads jnp.hstack on JAX {jax.__version__}: "
        f"primitives {_names(closed.jaxpr.eqns)}"
    )
    closed = jax.make_jaxpr(lambda a, b: (a, jnp.hstack([b, a])))(jnp.ones(3), jnp.ones(3))
    assert not locomotion._prefix_in(closed.jaxpr, closed.jaxpr.outvars)


# Brax ----------------------------------------------------------------------------------------


def test_brax_registry_lists_its_environments():
    pytest.importorskip("brax")
    assert {"ant", "humanoid", "hopper"} <= set(upstream.brax_env_names()), (
        "brax.envs._envs no longer holds Brax's environments by name"
    )


# MJX and MuJoCo Warp -------------------------------------------------------------------------

_XML = '<mujoco><worldbody><body><freejoint/><geom size=".1"/></body></worldbody></mujoco>'


@pytest.fixture(scope="module")
def mj_model():
    mujoco = pytest.importorskip("mujoco")
    return mujoco.MjModel.from_xml_string(_XML)


def test_mjx_picks_its_device_through_resolve_impl_and_device(mj_model, monkeypatch):
    """``mujoco.mjx._src.io._resolve_impl_and_device(impl, device)`` exists, with those
    parameters, and ``put_model`` / ``make_data`` really call it (a wrapper would otherwise
    change nothing)."""
    from mujoco import mjx

    resolve = upstream.mjx_device_resolver()
    names = list(inspect.signature(resolve).parameters)
    assert names[:2] == ["impl", "device"], (
        f"{upstream.MJX_IO}.{upstream.MJX_RESOLVER} now takes {names}, not (impl, device)"
    )
    calls = []

    def spy(impl=None, device=None):
        calls.append(impl)
        return resolve(impl, device)

    monkeypatch.setattr(importlib.import_module(upstream.MJX_IO), upstream.MJX_RESOLVER, spy)
    mjx.put_model(mj_model, impl="jax")
    mjx.make_data(mj_model, impl="jax")
    assert len(calls) == 2, (
        f"mujoco.mjx.put_model / make_data no longer call {upstream.MJX_RESOLVER}: "
        "td3_jax.envs.mjx_devices would change nothing"
    )


def test_a_missing_mjx_resolver_raises_instead_of_being_skipped(monkeypatch):
    from td3_jax.envs import mjx_devices

    io = pytest.importorskip(upstream.MJX_IO)
    monkeypatch.delattr(io, upstream.MJX_RESOLVER)
    with pytest.raises(upstream.UpstreamChanged, match="_resolve_impl_and_device is gone"):
        mjx_devices.place_on_local_devices()
    with pytest.raises(upstream.UpstreamChanged, match="_resolve_impl_and_device is gone"):
        upstream.set_mjx_device_resolver(lambda impl=None, device=None: (impl, device))
    assert not hasattr(io, upstream.MJX_RESOLVER)  # not created


def test_mjx_data_and_option_keep_warp_fields_behind_impl():
    """``mujoco.mjx.Data._impl.overflow`` and ``mujoco.mjx.Option._impl.warn_overflow`` on
    the dataclasses (no Warp needed)."""
    mjx = pytest.importorskip("mujoco.mjx")
    from mujoco.mjx.warp import types as warp_types

    for owner, field in ((mjx.Data, "_impl"), (mjx.Option, "_impl"),
                         (warp_types.DataWarp, "overflow"),
                         (warp_types.OptionWarp, "warn_overflow")):  # fmt: skip
        fields = [f.name for f in dataclasses.fields(owner)]
        assert field in fields, f"{owner.__module__}.{owner.__name__}.{field} is gone"


@pytest.fixture(scope="module")
def warp_model(mj_model):
    """A tiny MJX model and data on MuJoCo Warp (its CPU kernels: nothing is compiled)."""
    pytest.importorskip("warp")
    from mujoco import mjx

    return mjx.put_model(mj_model, impl="warp"), mjx.make_data(mj_model, impl="warp")


def test_warp_overflow_flags_are_read_from_real_warp_data(warp_model):
    _, data = warp_model
    flags = upstream.warp_overflow_flags(data)
    assert np.asarray(flags).dtype.kind in "iu" and int(np.asarray(flags).max()) == 0


def test_warp_overflow_warnings_are_quieted_on_a_real_warp_model(warp_model):
    model, _ = warp_model
    task = SimpleNamespace(_mjx_model=model)
    before = int(model.opt._impl.warn_overflow)
    upstream.quiet_warp_overflow_warnings(task, 1 << 9)
    after = int(task._mjx_model.opt._impl.warn_overflow)
    assert before & (1 << 9) and after == before & ~(1 << 9)
    assert type(task._mjx_model) is type(model)


def test_warp_overflow_bits_match_what_td3_jax_counts_as_wrong_physics():
    pytest.importorskip("warp")
    from mujoco.mjx.third_party.mujoco_warp import OverflowType

    limits = OverflowType.ITERATIONS | OverflowType.LS_ITERATIONS
    assert physics._ITERATION_LIMITS == int(limits), "MuJoCo Warp moved its iteration bits"
    assert physics.WRONG_PHYSICS == int(OverflowType.ALL) & ~int(limits), (
        "MuJoCo Warp's OverflowType changed: physics.WRONG_PHYSICS must be every flag but the "
        f"iteration limits, {[f.name for f in OverflowType]}"
    )


def test_warp_precompile_finds_mujoco_warp_and_warps_module_load(warp_model):
    """What :mod:`td3_jax.envs.warp_kernels` relies on: MJX's MuJoCo Warp with the functions
    it runs, Warp's ``Module.load(device, block_dim)``, and MJX's Warp options."""
    import inspect

    import warp

    mjwarp = upstream.mjx_mujoco_warp()
    for name in ("put_model", "put_data", "forward", "step"):
        assert callable(getattr(mjwarp, name, None)), f"{upstream.MJX_MUJOCO_WARP}.{name} is gone"
    load = upstream.warp_module_class().load
    assert list(inspect.signature(load).parameters)[:3] == ["self", "device", "block_dim"]
    for name in ("force_load", "capture_while", "capture_if", "get_suggested_block_size"):
        assert callable(getattr(warp, name, None)), f"warp.{name} is gone"
    model, _ = warp_model
    assert isinstance(upstream.mjx_warp_options(model).warn_overflow, int)


def test_missing_warp_fields_raise_naming_them():
    with pytest.raises(upstream.UpstreamChanged, match=r"mujoco\.mjx\.Data\._impl is gone"):
        upstream.warp_overflow_flags(SimpleNamespace(qpos=0))
    with pytest.raises(upstream.UpstreamChanged, match=r"DataWarp\.overflow is gone"):
        upstream.warp_overflow_flags(SimpleNamespace(_impl=SimpleNamespace()))
    task = SimpleNamespace(_mjx_model=SimpleNamespace(opt=SimpleNamespace(_impl=object())))
    with pytest.raises(upstream.UpstreamChanged, match=r"OptionWarp\.warn_overflow is gone"):
        upstream.quiet_warp_overflow_warnings(task, 1)


# MuJoCo Playground ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cartpole():
    """A cheap Playground task (DM Control's CartpoleBalance on MJX's JAX physics)."""
    playground = pytest.importorskip("mujoco_playground")
    return playground.dm_control_suite.load("CartpoleBalance", config_overrides={"impl": "jax"})


def test_playground_locomotion_registry():
    pytest.importorskip("mujoco_playground")
    registry = upstream.playground_locomotion()
    for name in ("ALL_ENVS", "get_default_config", "load", "get_domain_randomizer"):
        assert hasattr(registry, name), f"{upstream.PLAYGROUND_LOCOMOTION}.{name} is gone"
    assert "T1JoystickFlatTerrain" in registry.ALL_ENVS


def test_a_missing_private_module_raises_instead_of_listing_nothing():
    with pytest.raises(upstream.UpstreamChanged, match=r"mujoco_playground\._src\.nowhere"):
        upstream._private_module("mujoco_playground._src.nowhere")
    with pytest.raises(ImportError):  # a library not installed stays an ImportError
        upstream._private_module("no_such_library_td3._src.x")


def test_playgrounds_own_menagerie_is_where_playground_reads_it():
    mjx_env = pytest.importorskip(upstream.PLAYGROUND_MJX_ENV)
    assert str(upstream.playground_menagerie_path()) == str(mjx_env.MENAGERIE_PATH), (
        f"{upstream.PLAYGROUND_MJX_ENV}.MENAGERIE_PATH moved"
    )


def test_playground_builds_a_robot_from_the_menagerie_td3_jax_points_it_at(monkeypatch):
    """``mjx_env.MENAGERIE_PATH`` and ``ensure_menagerie_exists`` are what Playground's
    locomotion loader reads at load time: pointed elsewhere, it builds T1 from there without
    cloning (it cannot clone here: the clone is made to fail)."""
    from td3_jax.envs import menagerie

    mjx_env = pytest.importorskip(upstream.PLAYGROUND_MJX_ENV)
    try:
        root = menagerie.find_root("T1JoystickFlatTerrain")
    except menagerie.MissingAssetsError:
        pytest.skip("no booster_t1 robot folder installed")

    def clone(*args):
        raise AssertionError("Playground tried to git clone the Menagerie")

    monkeypatch.setattr(mjx_env, "_clone_with_progress", clone, raising=False)
    monkeypatch.setattr(mjx_env, "MENAGERIE_PATH", mjx_env.MENAGERIE_PATH / "td3-jax-absent")
    with upstream.playground_menagerie_at(root):
        assert mjx_env.ensure_menagerie_exists is upstream._no_clone
        task = upstream.playground_locomotion().load("T1JoystickFlatTerrain")
    assert task.mj_model.nbody > 10
    assert str(mjx_env.MENAGERIE_PATH).endswith("td3-jax-absent")  # put back


def test_a_missing_menagerie_path_raises_instead_of_being_created(monkeypatch, tmp_path):
    mjx_env = pytest.importorskip(upstream.PLAYGROUND_MJX_ENV)
    monkeypatch.delattr(mjx_env, "MENAGERIE_PATH")
    with pytest.raises(upstream.UpstreamChanged, match="MENAGERIE_PATH is gone"):
        with upstream.playground_menagerie_at(tmp_path):
            pass
    assert not hasattr(mjx_env, "MENAGERIE_PATH")


def test_a_task_simulates_the_model_swapped_into_it(cartpole):
    """``MjxEnv._mjx_model`` is on the task itself, its ``mjx_model`` reads it, and ``step``
    traced while another model is swapped in simulates that one (domain randomisation)."""
    assert upstream.TASK_MODEL in vars(cartpole), (
        f"Playground's MjxEnv.{upstream.TASK_MODEL} is gone: domain randomisation cannot swap it"
    )
    model = upstream.task_mjx_model(cartpole)
    state = jax.eval_shape(cartpole.reset, jax.random.PRNGKey(0))
    action = jax.ShapeDtypeStruct((cartpole.action_size,), jnp.float32)

    def step(swapped, s, a):
        with upstream.simulating(cartpole, swapped):
            assert cartpole.mjx_model is swapped, (
                f"MjxEnv.mjx_model no longer reads {upstream.TASK_MODEL}"
            )
            return cartpole.step(s, a)

    jaxpr = jax.make_jaxpr(step)(model, state, action).jaxpr
    model_inputs = set(jaxpr.invars[: len(jax.tree.leaves(model))])
    used = {v for e in jaxpr.eqns for v in e.invars if isinstance(v, jex_core.Var)}
    assert model_inputs & used, f"Playground's step no longer simulates {upstream.TASK_MODEL}"
    assert upstream.task_mjx_model(cartpole) is model  # put back


def test_swapping_a_model_into_a_task_without_one_raises_and_creates_nothing():
    """Domain randomisation must never set a new attribute Playground does not read."""
    task = SimpleNamespace(mjx_model="the task's")
    with pytest.raises(upstream.UpstreamChanged, match="holds no attribute _mjx_model"):
        with upstream.simulating(task, "randomised"):
            pass
    with pytest.raises(upstream.UpstreamChanged, match="holds no attribute _mjx_model"):
        upstream.set_task_mjx_model(task, "adjusted")
    assert not hasattr(task, "_mjx_model")


def test_a_model_found_only_through_a_wrapper_is_not_swapped():
    class Wrapper:
        def __init__(self, env):
            self.env = env

        def __getattr__(self, name):
            return getattr(self.env, name)

    wrapper = Wrapper(SimpleNamespace(_mjx_model="the task's"))
    with pytest.raises(upstream.UpstreamChanged, match="Wrapper holds no attribute"):
        upstream.set_task_mjx_model(wrapper, "randomised")


def test_jax_keeps_its_distributed_client_with_the_key_value_calls_td3_jax_uses():
    """The distributed runtime's client (``None`` before ``jax.distributed.initialize``) and
    the two calls of its class that the settings check uses."""
    from jax._src.lib import _jax

    assert upstream.distributed_store() is None  # (this process started no runtime)
    for name in ("key_value_set", "blocking_key_value_get"):
        assert callable(getattr(_jax.DistributedRuntimeClient, name))


def test_a_jax_without_the_distributed_client_raises_naming_it(monkeypatch):
    from jax._src import distributed

    monkeypatch.delattr(distributed, "global_state")
    with pytest.raises(upstream.UpstreamChanged, match=r"jax\._src\.distributed\.global_state"):
        upstream.distributed_store()
