"""Policy export (``td3_jax.tools.export``, ``td3_jax.tools.policy_file``, ``td3-jax export``).

The exported files are checked against the JAX policy path the run evaluates with
(normalise -> actor observation -> ``actor.apply`` -> ``to_env_action``) on random
observations, with random parameters and statistics (stronger than a freshly initialised
actor), and against hand-computed actions, for plain (mlp) and residual actors. One tiny two-seed
run (module-scoped) serves the command-line checks.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from td3_jax import envs
from td3_jax.cli import app as cli
from td3_jax.core import normalization
from td3_jax.core.networks import Actor
from td3_jax.core.training import safe_action
from td3_jax.envs.base import Environment
from td3_jax.tools import export, policy_file

onnxruntime = pytest.importorskip("onnxruntime")

TOLERANCE = 1e-5  # float32: the JAX, NumPy and ONNX Runtime matmuls sum in different orders
ROWS = 1000


def _unused(*_):
    raise AssertionError("the export never steps the environment")


def asymmetric_env() -> Environment:
    """Non-symmetric bounds, and rows [8] of which the actor sees the first 5."""
    return Environment(
        name="test/asymmetric", observation_size=5, action_size=3, episode_length=10,
        action_low=np.array([-1.0, 0.0, -3.0], np.float32),
        action_high=np.array([3.0, 0.5, -1.0], np.float32),
        reset_fn=_unused, step_fn=_unused, critic_observation_size=3, critic_offset=5,
    )  # fmt: skip


def make_actor(layer_norm: bool, max_action, residual: bool = False, dtype=None) -> Actor:
    """A plain actor of hidden sizes 32 16, or a residual one of two blocks of width 8."""
    return Actor((8, 8) if residual else (32, 16), 3, max_action, layer_norm, dtype, residual)


def random_actor(layer_norm: bool, max_action, key=0, residual=False) -> tuple[Actor, dict]:
    """An actor whose every parameter is perturbed away from its init: kernels by a random
    factor, biases and LayerNorm (and RMSNorm) scales and biases by random offsets."""
    actor = make_actor(layer_norm, max_action, residual)
    params = actor.init(jax.random.PRNGKey(key), jnp.zeros((1, 5)))
    leaves, tree = jax.tree.flatten(params)
    keys = jax.random.split(jax.random.PRNGKey(key + 1), len(leaves))
    noises = [jax.random.normal(k, x.shape) for k, x in zip(keys, leaves, strict=True)]
    leaves = [x * (1.0 + 0.5 * n) if x.ndim > 1 else x + 0.3 * n
              for x, n in zip(leaves, noises, strict=True)]  # fmt: skip
    return actor, jax.tree.unflatten(tree, leaves)


def random_stats(row_size: int) -> normalization.RunningStats:
    mean_key, var_key = jax.random.split(jax.random.PRNGKey(5))
    return normalization.RunningStats(
        mean=2.0 * jax.random.normal(mean_key, (row_size,)),
        var=jnp.exp(2.0 * jax.random.normal(var_key, (row_size,))),
        count=jnp.asarray(17.0),
    )


def jax_policy(env, actor, params, stats):
    """The evaluation's policy (td3_jax.core.training._evaluation_step) on rows [n, row_size]."""

    def act(rows):
        obs = rows if stats is None else normalization.normalize(stats, rows)
        action = safe_action(actor.apply(params, envs.actor_observation(env, obs)))
        return env.to_env_action(action)

    return jax.jit(act)


def random_rows(size: int, stats=None, seed: int = 3) -> np.ndarray:
    """``[ROWS, size]`` observations about 2 standard deviations of ``stats`` wide (N(0, 2)
    without), the first 5% 30 wide so that the normaliser's clip at +-10 acts."""
    rng = np.random.default_rng(seed)
    mean, std = (0.0, 1.0) if stats is None else (np.asarray(stats.mean), np.sqrt(stats.var))
    width = np.where(np.arange(ROWS)[:, None] < ROWS // 20, 30.0, 2.0)
    return (mean + std * width * rng.standard_normal((ROWS, size))).astype(np.float32)


def unsaturated(actions: np.ndarray, env: Environment) -> float:
    """The fraction of action components strictly inside the bounds (not at a tanh tail)."""
    unit = (actions - env.action_low) / (env.action_high - env.action_low)
    return float(np.mean((unit > 1e-3) & (unit < 1 - 1e-3)))


def onnx_actions(path: Path, obs: np.ndarray) -> np.ndarray:
    from onnx.reference import ReferenceEvaluator  # (ONNX's own reference runtime)

    model = ReferenceEvaluator(str(path))
    return np.asarray(model.run(["action"], {"obs": obs})[0], np.float32)


def check_same(name: str, got: np.ndarray, want: np.ndarray) -> float:
    diff = float(np.max(np.abs(got - want)))
    print(f"{name}: max abs diff {diff:.3g} over {got.shape[0]} observations")
    assert got.dtype == np.float32 and got.shape == want.shape
    assert diff <= TOLERANCE, f"{name}: max abs diff {diff}"
    return diff


# --------------------------------------------------------------------------------------------
# the exported arrays against the JAX policy path
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("layer_norm", "normalized", "max_action", "residual"),
    [(False, True, 1.0, False), (True, True, 1.0, False), (True, False, (1.0, 0.5, 2.0), False),
     (False, True, (1.0, 0.5, 2.0), True), (False, False, 1.0, True)],
)  # fmt: skip
def test_exports_equal_the_jax_policy(tmp_path, layer_norm, normalized, max_action, residual):
    env = asymmetric_env()
    actor, params = random_actor(layer_norm, np.asarray(max_action, np.float32), 0, residual)
    stats = random_stats(env.row_size) if normalized else None
    policy = export.extract_policy(env, actor, params, stats)
    assert policy.layer_norm == layer_norm and policy.normalize == normalized
    assert policy.residual == residual and policy.blocks == (2 if residual else 0)
    rows = random_rows(env.row_size, stats)
    want = np.asarray(jax_policy(env, actor, params, stats)(rows))
    assert unsaturated(want, env) > 0.7  # the comparison is not of tanh tails
    obs = rows[:, : env.observation_size]
    npz = policy_file.load(export.save_npz(policy, tmp_path / "p.npz"))
    check_same(f"npz ({policy.network}, layer_norm={layer_norm})", npz(obs), want)
    onnx_path = export.save_onnx(policy, tmp_path / "p.onnx")
    check_same(f"onnx ({policy.network})", onnx_actions(onnx_path, obs), want)
    assert np.all(want >= env.action_low) and np.all(want <= env.action_high)
    assert np.all(npz(obs) >= env.action_low) and np.all(npz(obs) <= env.action_high)
    if normalized:  # the normaliser's clip acts on some observations, not on most
        z = (rows - np.asarray(stats.mean)) / np.sqrt(np.asarray(stats.var) + 1e-8)
        assert 0 < np.mean(np.abs(z[:, :5]) > 10) < 0.1


@pytest.mark.parametrize("residual", [False, True])
def test_a_bf16_actor_exports_its_float32_evaluation(residual):
    """bf16 matmuls: the export is the float32 forward pass of the same parameters, and differs
    from the bf16 one by bf16 rounding only (documented in README and td3_jax.tools.export)."""
    env = asymmetric_env()
    f32_actor, params = random_actor(not residual, 1.0, residual=residual)
    bf16_actor = make_actor(not residual, 1.0, residual, jnp.bfloat16)
    stats = random_stats(env.row_size)
    policy = export.extract_policy(env, bf16_actor, params, stats, precision="bfloat16")
    rows = random_rows(env.row_size, stats)
    got = policy_file.forward(export.npz_arrays(policy), rows[:, :5])
    check_same("npz of a bf16 actor vs float32", got, np.asarray(
        jax_policy(env, f32_actor, params, stats)(rows)))  # fmt: skip
    bf16 = np.asarray(jax_policy(env, bf16_actor, params, stats)(rows))
    diff = np.abs(got - bf16)
    print(f"npz vs the bf16 forward pass: mean {diff.mean():.2g}, max {diff.max():.2g}")
    assert 1e-4 < diff.mean() < 1e-2 and diff.max() < 0.2


def test_statistics_that_saw_nothing_are_the_identity():
    env = asymmetric_env()
    actor, params = random_actor(False, 1.0)
    fresh = normalization.init(env.row_size)
    policy = export.extract_policy(env, actor, params, fresh)
    assert not policy.normalize
    rows = random_rows(env.row_size)
    want = np.asarray(jax_policy(env, actor, params, fresh)(rows))
    got = policy_file.forward(export.npz_arrays(policy), rows[:, :5])
    check_same("npz (count 0)", got, want)


def hand_policy(normalize: bool) -> export.PolicyArrays:
    """obs [2] -> action [2], one Dense layer: kernel I, bias 0; bounds [-1, 3] and [0, 0.5]."""
    return export.PolicyArrays(
        kernels=(np.eye(2, dtype=np.float32),), biases=(np.zeros(2, np.float32),),
        ln_scales=(), ln_biases=(), ln_epsilon=1e-6, normalize=normalize,
        obs_mean=np.array([1.0, 0.0], np.float32), obs_std=np.array([2.0, 0.1], np.float32),
        obs_clip=10.0, max_action=np.ones(2, np.float32),
        action_low=np.array([-1.0, 0.0], np.float32),
        action_high=np.array([3.0, 0.5], np.float32), env="test/hand",
    )  # fmt: skip


def test_bounds_by_hand(tmp_path):
    """tanh(atanh(0.5)) = 0.5 -> -1 + (0.5 + 1) / 2 * 4 = 2; tanh(-20) = -1 -> 0 + 0 = 0;
    normalised: (1 + 2 atanh(0.5) - 1) / 2 = atanh(0.5) -> 2, and (-5 - 0) / 0.1 = -50,
    clipped to -10, tanh(-10) = -1 -> 0."""
    half = np.arctanh(np.float32(0.5))
    cases = [(False, [half, -20.0]), (True, [1.0 + 2.0 * half, -5.0])]
    for normalize, obs in cases:
        policy = hand_policy(normalize)
        obs = np.array([obs], np.float32)
        npz = policy_file.load(export.save_npz(policy, tmp_path / "hand.npz"))
        onnx_path = export.save_onnx(policy, tmp_path / "hand.onnx")
        for got in (npz(obs), onnx_actions(onnx_path, obs)):
            np.testing.assert_allclose(got, [[2.0, 0.0]], atol=1e-6)


def test_onnx_model_interface(tmp_path):
    onnx = pytest.importorskip("onnx")
    env = asymmetric_env()
    actor, params = random_actor(True, 1.0)
    policy = export.extract_policy(env, actor, params, random_stats(env.row_size))
    model = onnx.load(str(export.save_onnx(policy, tmp_path / "p.onnx")))
    assert [o.version for o in model.opset_import if o.domain == ""] == [export.ONNX_OPSET]
    (obs,), (action,) = model.graph.input, model.graph.output
    assert (obs.name, action.name) == ("obs", "action")
    dims = [d.dim_param or d.dim_value for d in obs.type.tensor_type.shape.dim]
    assert dims == ["batch", 5]
    meta = {p.key: p.value for p in model.metadata_props}
    assert meta["opset"] == "17" and meta["env"] == "test/asymmetric"
    assert meta["action_low"] == "[-1.0, 0.0, -3.0]"
    assert (meta["network"], meta["format_version"], meta["layer_norm"]) == ("mlp", "1", "true")
    batch = random_rows(5)[:7]  # the batch dimension is dynamic
    assert onnx_actions(tmp_path / "p.onnx", batch).shape == (7, 3)


def test_a_residual_actors_layout_and_onnx_model(tmp_path):
    """The residual actor's parameters are what the export reads (every one used: the
    comparisons above perturb each); its ONNX model builds the RMSNorm of opset-17 nodes and
    says the network in its metadata; its summary says it too."""
    onnx = pytest.importorskip("onnx")
    env = asymmetric_env()
    actor, params = random_actor(False, 1.0, residual=True)
    layers = params["params"]["ResidualMLP_0"]
    assert {k: [v.shape for v in layer.values()] for k, layer in layers.items()} == {
        "Dense_0": [(8,), (5, 8)], "Dense_1": [(32,), (8, 32)], "LayerNorm_0": [(32,), (32,)],
        "Dense_2": [(8,), (32, 8)], "LayerNorm_1": [(8,), (8,)], "Dense_3": [(32,), (8, 32)],
        "LayerNorm_2": [(32,), (32,)], "Dense_4": [(8,), (32, 8)], "LayerNorm_3": [(8,), (8,)],
        "RMSNorm_0": [(8,)], "Dense_5": [(3,), (8, 3)],
    }  # fmt: skip
    policy = export.extract_policy(env, actor, params)
    np.testing.assert_array_equal(policy.rms_scale, layers["RMSNorm_0"]["scale"])
    assert export.summary(policy) == ("test/asymmetric member 0 at 0 env steps: obs 5 -> action "
                                      "3 in [[-1.0, 0.0, -3.0], [3.0, 0.5, -1.0]], residual "
                                      "actor (2 blocks of 8)")  # fmt: skip
    model = onnx.load(str(export.save_onnx(policy, tmp_path / "p.onnx")))
    ops = {node.op_type for node in model.graph.node}
    assert {"ReduceMean", "Sqrt", "LayerNormalization"} <= ops
    meta = {p.key: p.value for p in model.metadata_props}
    assert (meta["network"], meta["blocks"], meta["format_version"]) == ("residual", "2", "2")
    assert onnx_actions(tmp_path / "p.onnx", random_rows(5)[:7]).shape == (7, 3)


# --------------------------------------------------------------------------------------------
# the NumPy-only loader
# --------------------------------------------------------------------------------------------

BLOCKED_IMPORT = """
import sys
for name in ("jax", "jaxlib", "flax", "optax", "onnx", "onnxruntime"):
    sys.modules[name] = None  # importing any of them now raises ImportError
{load}
import numpy as np
policy = load(sys.argv[1])
obs = np.load(sys.argv[2])
np.save(sys.argv[3], policy(obs))
imported = sorted(m for m in sys.modules if m.startswith("td3_jax"))
print(imported)
"""


@pytest.mark.parametrize(("how", "residual"), [("package", False), ("copied file", True)])
def test_policy_file_runs_without_jax(tmp_path, how, residual):
    env = asymmetric_env()
    actor, params = random_actor(not residual, 1.0, residual=residual)
    policy = export.extract_policy(env, actor, params, random_stats(env.row_size))
    path = export.save_npz(policy, tmp_path / "p.npz")
    obs = random_rows(5)
    np.save(tmp_path / "obs.npy", obs)
    if how == "package":
        load = "from td3_jax.tools.policy_file import load"
        pythonpath = str(Path(policy_file.__file__).parents[2])
    else:  # the module copied onto a machine without td3-jax
        shutil.copy(policy_file.__file__, tmp_path / "policy_file.py")
        load, pythonpath = "from policy_file import load", str(tmp_path)
    script = textwrap.dedent(BLOCKED_IMPORT).format(load=load)
    done = subprocess.run(
        [sys.executable, "-c", script, str(path), str(tmp_path / "obs.npy"),
         str(tmp_path / "out.npy")],
        capture_output=True, text=True, timeout=60, env={"PYTHONPATH": pythonpath},
        cwd=tmp_path,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    if how == "package":
        # (td3_jax.tools is the loader's package: its __init__ imports nothing)
        assert done.stdout.strip() == "['td3_jax', 'td3_jax.tools', 'td3_jax.tools.policy_file']"
    # Equal to float32 rounding: BLAS may pick another kernel (threads, alignment) per process.
    np.testing.assert_allclose(
        np.load(tmp_path / "out.npy"), policy_file.load(path)(obs), rtol=1e-5, atol=1e-6
    )


def test_policy_file_refuses_bad_input(tmp_path):
    env = asymmetric_env()
    actor, params = random_actor(False, 1.0)
    path = export.save_npz(export.extract_policy(env, actor, params), tmp_path / "p.npz")
    policy = policy_file.load(path)
    assert policy(np.zeros(5)).shape == (3,)  # one observation, no batch axis
    with pytest.raises(policy_file.PolicyFileError, match=r"takes observations \[\.\.\., 5\]"):
        policy(np.zeros((2, 8)))
    (tmp_path / "junk.npz").write_bytes(b"not a zip")  # e.g. an ONNX model misnamed
    with pytest.raises(policy_file.PolicyFileError, match="is not a policy file"):
        policy_file.load(tmp_path / "junk.npz")
    with pytest.raises(policy_file.PolicyFileError, match="cannot read"):
        policy_file.load(tmp_path / "missing.npz")
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(policy_file.PolicyFileError):
        policy_file.load(truncated)
    arrays = dict(np.load(path))
    arrays["format_version"] = np.array(99)
    np.savez(tmp_path / "future.npz", **arrays)
    with pytest.raises(policy_file.PolicyFileError, match="format version 99"):
        policy_file.load(tmp_path / "future.npz")
    arrays.update(format_version=np.array(2), network=np.array("transformer"))
    np.savez(tmp_path / "unknown.npz", **arrays)
    with pytest.raises(policy_file.PolicyFileError, match="holds a 'transformer' actor"):
        policy_file.load(tmp_path / "unknown.npz")
    # A damaged file: a layer missing (a KeyError when run, once), a residual layer count off.
    arrays = dict(np.load(path))
    del arrays[f"bias_{int(arrays['num_layers']) - 1}"]
    np.savez(tmp_path / "no_bias.npz", **arrays)
    with pytest.raises(policy_file.PolicyFileError, match=r"not a td3-jax policy file \(no "
                       r"'bias_2' array\)"):  # fmt: skip
        policy_file.load(tmp_path / "no_bias.npz")
    residual, params = random_actor(False, 1.0, residual=True)
    arrays = export.npz_arrays(export.extract_policy(env, residual, params))
    arrays["blocks"] = np.array(3)
    np.savez(tmp_path / "blocks.npz", **arrays)
    with pytest.raises(policy_file.PolicyFileError, match="damaged: a residual actor of 3 "
                       "blocks has 8 layers, not 6"):  # fmt: skip
        policy_file.load(tmp_path / "blocks.npz")


#: The arrays of a version-1 file (a plain actor of two layers, one hidden, with layer norm),
#: as td3-jax wrote them before residual actors.
VERSION_1_ARRAYS = (
    "format_version", "env", "observation_size", "action_size", "layer_norm", "num_layers",
    "member", "env_steps", "precision", "normalize", "obs_mean", "obs_std", "obs_clip",
    "max_action", "action_low", "action_high", "ln_epsilon", "kernel_0", "bias_0", "kernel_1",
    "bias_1", "ln_scale_0", "ln_bias_0",
)  # fmt: skip


def test_a_plain_actor_is_still_written_and_read_as_version_1(tmp_path):
    """A plain actor's file is the version-1 file it was (the same arrays), which this loader
    reads; a residual actor's is version 2, which a version-1 loader refuses in one line."""
    env = asymmetric_env()
    rng = np.random.default_rng(0)
    policy = dataclasses.replace(
        hand_policy(True), kernels=(np.eye(2, dtype=np.float32),
                 rng.standard_normal((2, 2)).astype(np.float32)),
        biases=(np.zeros(2, np.float32), np.ones(2, np.float32)),
        ln_scales=(np.full(2, 2.0, np.float32),), ln_biases=(np.ones(2, np.float32),),
    )  # fmt: skip
    arrays = export.npz_arrays(policy)
    assert tuple(arrays) == VERSION_1_ARRAYS and int(arrays["format_version"]) == 1
    path = tmp_path / "v1.npz"
    np.savez(path, **arrays)
    loaded = policy_file.load(path)
    assert loaded.network == "mlp"
    obs = np.array([[0.3, -0.2], [3.0, 1.0]], np.float32)
    z = np.clip((obs - policy.obs_mean) / policy.obs_std, -10, 10)
    h = np.maximum(hand_layer_norm(z) * 2.0 + 1.0, 0.0) @ policy.kernels[1] + 1.0
    want = policy.action_low + (np.tanh(h) + 1) / 2 * (policy.action_high - policy.action_low)
    np.testing.assert_allclose(loaded(obs), want, atol=1e-5)
    actor, params = random_actor(False, 1.0, residual=True)
    residual = export.save_npz(export.extract_policy(env, actor, params), tmp_path / "r.npz")
    assert int(policy_file.read(residual)["format_version"]) == 2
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(policy_file, "FORMAT_VERSION", policy_file.MLP_VERSION)
        assert policy_file.load(path).network == "mlp"
        with pytest.raises(policy_file.PolicyFileError, match="has format version 2; this "
                           "loader reads up to 1"):  # fmt: skip
            policy_file.load(residual)


def hand_layer_norm(z: np.ndarray) -> np.ndarray:
    """LayerNorm without scale or bias over ``z [n, features]``."""
    centred = z - z.mean(-1, keepdims=True)
    return centred / np.sqrt(np.square(centred).mean(-1, keepdims=True) + 1e-6)


# --------------------------------------------------------------------------------------------
# which member
# --------------------------------------------------------------------------------------------


def _record(env_steps, returns):
    return {"env_steps": env_steps, "per_member": [{"eval_return_mean": r} for r in returns]}


def test_best_member_is_the_checkpoints_best():
    records = [_record(64, [-5.0, -1.0, -3.0]), _record(128, [-2.0, None, -4.0])]
    assert export.best_member(records, 128) == 0  # a diverged member (None) is never best
    assert export.best_member(records, 64) == 1  # the evaluation of the checkpoint's step
    assert export.best_member(records, 999) == 0  # no record at that step: the last one
    assert export.best_member([{"env_steps": 64, "eval_return_mean": 1.0}], 64) is None
    assert export.choose_member(None, 3, records, 64) == 1
    assert export.choose_member(None, 1, [], 64) == 0
    assert export.choose_member(2, 3, records, 64) == 2
    for bad in (3, -1):
        with pytest.raises(export.ExportError, match=r"out of range: the run has 3 members"):
            export.choose_member(bad, 3, records, 64)


def test_a_diverged_member_is_refused():
    env = asymmetric_env()
    actor, params = random_actor(False, 1.0)
    params = jax.tree.map(lambda x: x * jnp.nan, params)
    with pytest.raises(export.ExportError, match="member 2 has non-finite"):
        export.check_finite(export.extract_policy(env, actor, params, member=2))


# --------------------------------------------------------------------------------------------
# the command line, on one tiny trained run of two seeds
# --------------------------------------------------------------------------------------------

TINY_FLAGS = [
    "--env", "gymnax/Pendulum-v1", "--num-envs", "4", "--total-steps", "64",
    "--eval-every", "64", "--warmup-steps", "16", "--batch-size", "16",
    "--updates-per-iter", "1", "--hidden-sizes", "16", "16", "--eval-envs", "2",
    "--episode-length", "16", "--seed", "3", "--seeds", "2", "--buffer-size", "128",
    "--normalize-obs", "--quiet", "--compile-cache", "off",
]  # fmt: skip


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("export") / "run"
    cli.main(["train", *TINY_FLAGS, "--out", str(out)])
    return out


def cli_error(capsys, *args: str) -> tuple[int, str]:
    """``td3-jax ARGS`` in-process: ``(exit code, stderr)``."""
    with pytest.raises(SystemExit) as exit_:
        cli.main(list(args))
    return exit_.value.code, capsys.readouterr().err


def test_cli_exports_the_best_member(tiny_run, tmp_path, capsys):
    records = [json.loads(line) for line in (tiny_run / "metrics.jsonl").read_text().splitlines()]
    returns = [m["eval_return_mean"] for m in records[-1]["per_member"]]
    best = int(np.argmax(returns))
    cli.main(["export", "--run", str(tiny_run), "--format", "onnx"])
    cli.main(
        ["export", "--run", str(tiny_run), "--format", "npz", "--out", str(tmp_path / "x.npz")]
    )
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == str(tiny_run / "policy.onnx") and lines[2] == str(tmp_path / "x.npz")
    assert lines[1] == (f"gymnax/Pendulum-v1 member {best} (seed={3 + best}) at 64 env steps: "
                        "obs 3 -> action 1 in [-2, 2], normalised observations")  # fmt: skip
    _, program, state, _ = export.restore_checkpoint(tiny_run)
    stats = jax.tree.map(lambda x: x[best], state.obs_stats)
    assert float(stats.count) > 0 and not np.allclose(stats.mean, 0.0)
    params = jax.tree.map(lambda x: x[best], state.agent.actor_params)
    obs = random_rows(3, stats)
    want = np.asarray(jax_policy(program.env, program.spec.agent.actor, params, stats)(obs))
    check_same("cli npz", policy_file.load(tmp_path / "x.npz")(obs), want)
    check_same("cli onnx", onnx_actions(tiny_run / "policy.onnx", obs), want)
    assert np.all(np.abs(want) <= 2.0)


def test_cli_member_flag(tiny_run, tmp_path, capsys):
    out = tmp_path / "m1.npz"
    cli.main(["export", "--run", str(tiny_run), "--format", "npz", "--member", "1", "--out",
              str(out)])  # fmt: skip
    assert "member 1 (seed=4) at 64 env steps" in capsys.readouterr().out
    assert int(policy_file.load(out).arrays["member"]) == 1
    # With --member the records are not read: a damaged metrics.jsonl does not stop it (it
    # does where they choose the best member).
    damaged = tmp_path / "damaged"
    shutil.copytree(tiny_run, damaged)
    lines = (damaged / "metrics.jsonl").read_text().splitlines()
    (damaged / "metrics.jsonl").write_text("\n".join([lines[0][:20], *lines]) + "\n")
    cli.main(["export", "--run", str(damaged), "--format", "npz", "--member", "1", "--out",
              str(tmp_path / "m1-again.npz")])  # fmt: skip
    assert "member 1 (seed=4) at 64 env steps" in capsys.readouterr().out
    code, err = cli_error(capsys, "export", "--run", str(damaged), "--format", "npz")
    assert code == 2 and "metrics.jsonl is not a JSON record" in err, err


def test_cli_errors_exit_2(tiny_run, tmp_path, capsys):
    no_checkpoint = tmp_path / "no_checkpoint"
    no_checkpoint.mkdir()
    shutil.copy(tiny_run / "config.json", no_checkpoint / "config.json")
    notes, other = tmp_path / "notes.md", tmp_path / "someone_elses.npz"
    text_npz = tmp_path / "notes.npz"
    for text in (notes, text_npz):
        text.write_text("# not a policy\n")
    np.savez(other, weights=np.zeros(3))
    cases = {
        ("--run", str(tmp_path), "--format", "npz"): "not a td3-jax run directory",
        ("--run", str(no_checkpoint), "--format", "npz"): "holds no checkpoint (its run stopped",
        ("--run", str(tiny_run), "--format", "tflite"): "--format 'tflite' is not one of onnx",
        ("--run", str(tiny_run), "--format", "npz", "--member", "2"): "out of range",
        ("--run", str(tiny_run), "--format", "npz", "--out", str(tmp_path / "a" / "b.npz")):
            f"its folder {tmp_path / 'a'} does not exist",
        ("--run", str(tiny_run), "--format", "npz", "--out", str(notes / "b.npz")):
            f"its folder {notes} is a file",
        ("--run", str(tiny_run), "--format", "npz", "--out", str(tmp_path / "p.onnx")):
            "names an .onnx file but --format is npz",
        ("--run", str(tiny_run), "--format", "onnx", "--out", str(tmp_path / "p.NPZ")):
            "names an .npz file but --format is onnx",
        ("--run", str(tiny_run), "--format", "npz", "--out", str(notes)):
            f"--out {notes}: a --format npz policy file ends in .npz (as notes.md.npz)",
        ("--run", str(tiny_run), "--format", "npz", "--out", str(tmp_path)):
            f"--out {tmp_path} is a directory: name a file in it, as {tmp_path}/policy.npz",
        ("--run", str(tiny_run), "--format", "onnx", "--out", "."):
            "--out . is a directory: name a file in it, as policy.onnx",
        ("--run", str(tiny_run), "--format", "onnx", "--out", "/"):
            "--out / is a directory: name a file in it, as /policy.onnx",
        ("--run", str(tiny_run), "--format", "npz", "--out", str(text_npz)):
            "exists and is not a policy td3-jax exported",
        ("--run", str(tiny_run), "--format", "npz", "--out", str(other)):
            "exists and is not a policy td3-jax exported: remove it or choose another name",
        ("--run", str(tiny_run), "--format", "npz", "--out", "/proc/td3-jax-policy.npz"):
            "--out /proc/td3-jax-policy.npz: cannot write it (",  # (before the checkpoint)
    }  # fmt: skip
    for args, message in cases.items():
        code, stderr = cli_error(capsys, "export", *args)
        assert code == 2, stderr
        assert stderr.startswith("td3-jax: error: ") and message in stderr, stderr
        assert len(stderr.strip().splitlines()) == 1
    assert notes.read_text() == text_npz.read_text() == "# not a policy\n"
    assert list(np.load(other)) == ["weights"]
    for fmt in ("npz", "onnx"):  # (a second export of a run replaces its own file)
        again = tmp_path / f"p.{fmt}"
        for _ in range(2):
            cli.main(["export", "--run", str(tiny_run), "--format", fmt, "--out", str(again)])
            assert capsys.readouterr().out.splitlines()[0] == str(again)
    script = tmp_path / "train_t1.onnx"  # (a text naming td3-jax: still not a policy)
    script.write_text("td3-jax train --preset t1\n")
    code, stderr = cli_error(capsys, "export", "--run", str(tiny_run), "--format", "onnx",
                             "--out", str(script))  # fmt: skip
    assert code == 2 and "exists and is not a policy td3-jax exported" in stderr
    code, stderr = cli_error(capsys, "export", "--run", str(tiny_run), "--format", "onnx",
                             "--out", str(tmp_path / "policy"))  # fmt: skip
    assert code == 2 and "ends in .onnx (as policy.onnx)" in stderr
    assert script.read_text() == "td3-jax train --preset t1\n"
    # and in a real process: exit status 2, one line, no traceback
    done = subprocess.run(
        [sys.executable, "-m", "td3_jax", "export", "--run", str(tmp_path), "--format", "npz"],
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert done.stderr.strip().splitlines() == [
        f"td3-jax: error: {tmp_path} holds no config.json: not a td3-jax run directory"
    ]


def test_missing_onnx_says_how_to_install(tiny_run, monkeypatch):
    monkeypatch.setitem(sys.modules, "onnx", None)
    with pytest.raises(export.ExportError, match=r"pip install 'td3-jax\[export\]'"):
        export.export_run(tiny_run, "onnx")
