"""Export a trained deterministic actor as plain float32 arrays: a ``.npz`` or an ONNX model.

What is exported is the policy the run evaluates (:func:`td3_jax.core.training.evaluate`), for one
member of a run's newest checkpoint:

1. the observation normalisation, when the run's ``normalize_obs`` is on and its statistics
   have seen data: ``clip((obs - mean) / sqrt(var + 1e-8), -10, 10)`` per feature, with the
   statistics sliced to the actor's observation (``row[:observation_size]``);
2. the actor's network, then ``max_action * tanh``. A plain (``--actor-network mlp``) actor:
   Dense kernels ``[in, out]`` and biases, LayerNorm scales and biases after each hidden Dense
   with ``--layer-norm`` (epsilon: flax's default, 1e-6), ReLU. A residual one
   (:class:`~td3_jax.core.networks.ResidualMLP`): ``h = Dense_0(x)``; per block ``b``,
   ``y = relu(LN_2b(Dense_2b+1(h)))``, ``h = h + relu(LN_2b+1(Dense_2b+2(y)))``; then
   ``Dense_2B+1(RMSNorm(h))`` (``h / sqrt(mean(h^2) + 1e-6) * scale``);
3. the agent's action mapped to the environment's own bounds,
   ``low + (clip(a, -1, 1) + 1) / 2 * (high - low)`` (:meth:`Environment.to_env_action`).

Both formats compute in float32. A ``--precision bfloat16`` run keeps float32 parameters but
runs its matmuls in bf16; the export computes those in float32, so its actions differ from the
bf16 forward pass by bf16 rounding (a few 1e-3), and are the more exact ones.

The ``.npz`` runs with :mod:`td3_jax.tools.policy_file` (NumPy only). The ONNX model (opset
:data:`ONNX_OPSET`, which LayerNormalization needs) is built node by node from the same arrays
with ``onnx.helper``: input ``obs`` float32 ``[batch, observation_size]`` (dynamic batch),
output ``action`` float32 ``[batch, action_size]``; opset 17 has no RMSNorm, so the residual
actor's is built of Mul, ReduceMean, Add, Sqrt and Div.

A plain actor's ``.npz`` is of format version 1, as before residual actors (a loader of
version 1 reads it); a residual actor's is of version 2 (:func:`file_version`), which older
loaders refuse with a clear error rather than run it as an MLP.
"""

from __future__ import annotations

import dataclasses
import importlib
import math
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from td3_jax.common.errors import ConfigError, ExportError
from td3_jax.core import normalization
from td3_jax.runner.logger import probe_write
from td3_jax.tools.policy_file import FORMAT_VERSION, MLP_VERSION

#: The export formats (``td3-jax export --format``).
FORMATS = ("onnx", "npz")
#: The ONNX opset of exported models (LayerNormalization is in the default domain from 17).
ONNX_OPSET = 17


@dataclasses.dataclass(frozen=True)
class PolicyArrays:
    """One deterministic actor as float32 NumPy arrays (see the module docstring).

    Attributes:
      kernels, biases: the Dense layers, ``[in, out]`` and ``[out]``, input layer first (of a
        residual actor: ``Dense_0`` to ``Dense_2B+1``, ``2B + 2`` layers of ``B`` blocks).
      ln_scales, ln_biases: ``[features]`` LayerNorm parameters: of each hidden layer (empty
        without layer norm), or of a residual actor's blocks (``LayerNorm_0`` to
        ``LayerNorm_2B-1``); ``ln_epsilon`` their epsilon.
      normalize: whether observations are normalised; ``obs_mean``, ``obs_std``
        ``[observation_size]`` (``std = sqrt(var + 1e-8)``; 0 and 1 when not) and ``obs_clip``.
      max_action: ``[action_size]`` scale of the tanh output.
      action_low, action_high: ``[action_size]`` bounds of the environment's actions.
      env, member, env_steps, precision: where the policy comes from.
      residual: whether the actor is a :class:`~td3_jax.core.networks.ResidualMLP`; ``rms_scale``
        ``[width]`` its RMSNorm's scale (``None`` for a plain actor), ``rms_epsilon`` its
        epsilon.
    """

    kernels: tuple[np.ndarray, ...]
    biases: tuple[np.ndarray, ...]
    ln_scales: tuple[np.ndarray, ...]
    ln_biases: tuple[np.ndarray, ...]
    ln_epsilon: float
    normalize: bool
    obs_mean: np.ndarray
    obs_std: np.ndarray
    obs_clip: float
    max_action: np.ndarray
    action_low: np.ndarray
    action_high: np.ndarray
    env: str
    member: int = 0
    env_steps: int = 0
    precision: str = "float32"
    residual: bool = False
    rms_scale: np.ndarray | None = None
    rms_epsilon: float = 1e-6

    @property
    def observation_size(self) -> int:
        return int(self.kernels[0].shape[0])

    @property
    def action_size(self) -> int:
        return int(self.kernels[-1].shape[1])

    @property
    def layer_norm(self) -> bool:
        """A plain actor's ``--layer-norm`` (a residual actor's blocks always normalise)."""
        return bool(self.ln_scales) and not self.residual

    @property
    def network(self) -> str:
        """``"residual"`` or ``"mlp"`` (``--actor-network``)."""
        return "residual" if self.residual else "mlp"

    @property
    def blocks(self) -> int:
        """The residual blocks (0 for a plain actor)."""
        return (len(self.kernels) - 2) // 2 if self.residual else 0


# --------------------------------------------------------------------------------------------
# extracting the arrays
# --------------------------------------------------------------------------------------------


def _f32(x: Any) -> np.ndarray:
    return np.array(x, dtype=np.float32)


def _numbered(params: dict, prefix: str) -> list[dict]:
    """``params[prefix_0], params[prefix_1], ...`` in index order (flax's auto-names)."""
    names = [k for k in params if k.startswith(prefix + "_")]
    return [params[n] for n in sorted(names, key=lambda n: int(n.rsplit("_", 1)[1]))]


def _layers(body: dict, layer_norm: bool) -> tuple[list, list, list, list]:
    """``(kernels, biases, ln_scales, ln_biases)`` of a network's ``Dense_i`` and (with
    ``layer_norm``) ``LayerNorm_i`` parameters, in index order, float32."""
    dense = _numbered(body, "Dense")
    norms = _numbered(body, "LayerNorm") if layer_norm else []
    kernels = [_f32(d["kernel"]) for d in dense]
    biases = [_f32(d["bias"]) for d in dense]
    return kernels, biases, [_f32(n["scale"]) for n in norms], [_f32(n["bias"]) for n in norms]


def mlp_arrays(actor_params: Any, layer_norm: bool) -> tuple[list, list, list, list]:
    """``(kernels, biases, ln_scales, ln_biases)`` of an :class:`~td3_jax.core.networks.Actor`'s
    parameters (``{"params": {"MLP_0": {"Dense_i": ..., "LayerNorm_i": ...}}}``), float32."""
    layers = _layers(actor_params["params"]["MLP_0"], layer_norm)
    dense, norms = len(layers[0]), len(layers[2])
    if layer_norm and norms != dense - 1:
        raise ExportError(f"the actor has {dense} Dense layers but {norms} LayerNorms")
    return layers


def residual_arrays(actor_params: Any) -> tuple[list, list, list, list, np.ndarray]:
    """``(kernels, biases, ln_scales, ln_biases, rms_scale)`` of a residual actor's parameters
    (``{"params": {"ResidualMLP_0": {"Dense_i", "LayerNorm_i", "RMSNorm_0"}}}``): ``2B + 2``
    Dense layers and ``2B`` LayerNorms of ``B >= 1`` blocks, the RMSNorm's scale ``[width]``."""
    body = actor_params["params"]["ResidualMLP_0"]
    kernels, biases, scales, shifts = _layers(body, True)
    dense, norms = len(kernels), len(scales)
    if dense < 4 or dense % 2 or norms != dense - 2:
        raise ExportError(f"the residual actor has {dense} Dense layers and {norms} "
                          "LayerNorms, not 2B + 2 and 2B of B blocks")  # fmt: skip
    return kernels, biases, scales, shifts, _f32(body["RMSNorm_0"]["scale"])


def normalization_arrays(stats: Any, observation_size: int) -> tuple[bool, np.ndarray, np.ndarray]:
    """``(normalize, mean, std)`` ``[observation_size]`` of running statistics (per feature,
    sliced to the actor's part of the row); ``(False, 0, 1)`` for ``None`` (the run does not
    normalise) or statistics that have seen nothing (the normaliser is then the identity)."""
    if stats is None or float(np.asarray(stats.count)) <= 0:
        size = observation_size
        return False, np.zeros(size, np.float32), np.ones(size, np.float32)
    mean = _f32(stats.mean)[:observation_size]
    var = _f32(stats.var)[:observation_size]
    return True, mean, np.sqrt(var + np.float32(normalization.EPSILON))


def extract_policy(
    env: Any, actor: Any, actor_params: Any, obs_stats: Any = None, **origin: Any
) -> PolicyArrays:
    """The :class:`PolicyArrays` of one member's actor.

    Args:
      env: the :class:`~td3_jax.envs.Environment` (sizes and action bounds).
      actor: the :class:`~td3_jax.core.networks.Actor` module (layer norm, ``max_action``,
        ``residual``).
      actor_params: its parameters (one member's: no leading member axis).
      obs_stats: the member's :class:`~td3_jax.core.normalization.RunningStats` over rows
        ``[row_size]``, or ``None`` when the run does not normalise observations.
      origin: ``member``, ``env_steps``, ``precision`` recorded with the arrays.
    """
    import flax.linen as nn

    residual = bool(actor.residual)
    if residual:
        kernels, biases, scales, shifts, rms_scale = residual_arrays(actor_params)
    else:
        kernels, biases, scales, shifts = mlp_arrays(actor_params, actor.layer_norm)
        rms_scale = None
    if kernels[0].shape[0] != env.observation_size or kernels[-1].shape[1] != env.action_size:
        raise ExportError(
            f"the actor's sizes {kernels[0].shape[0]} -> {kernels[-1].shape[1]} "
            f"differ from {env.name}'s {env.observation_size} -> {env.action_size}"
        )
    normalize, mean, std = normalization_arrays(obs_stats, env.observation_size)
    max_action = np.broadcast_to(_f32(actor.max_action), (env.action_size,)).copy()
    return PolicyArrays(
        tuple(kernels), tuple(biases), tuple(scales), tuple(shifts),
        float(nn.LayerNorm.epsilon), normalize, mean, std, normalization.CLIP, max_action,
        _f32(env.action_low), _f32(env.action_high), env.name, **origin, residual=residual,
        rms_scale=rms_scale, rms_epsilon=float(nn.RMSNorm.epsilon),
    )  # fmt: skip


def check_finite(policy: PolicyArrays) -> None:
    """Raises :class:`ExportError` when a parameter or statistic is NaN or infinite."""
    arrays = [*policy.kernels, *policy.biases, *policy.ln_scales, *policy.ln_biases,
              policy.obs_mean, policy.obs_std,
              *([] if policy.rms_scale is None else [policy.rms_scale])]  # fmt: skip
    if not all(np.isfinite(a).all() for a in arrays):
        raise ExportError(
            f"member {policy.member} has non-finite parameters or statistics (it diverged); "
            "choose another with --member"
        )


# --------------------------------------------------------------------------------------------
# which member, from a run directory
# --------------------------------------------------------------------------------------------


def _record_return(record: dict, k: int) -> float:
    value = record["per_member"][k].get("eval_return_mean")
    return -math.inf if value is None or not math.isfinite(value) else float(value)


def best_member(records: list[dict], env_steps: int | None) -> int | None:
    """The member with the highest ``eval_return_mean`` in the evaluation at ``env_steps``
    (the checkpoint's; else the last one), or ``None`` without per-member records."""
    with_members = [r for r in records if r.get("per_member")]
    if not with_members:
        return None
    at = [r for r in with_members if r.get("env_steps") == env_steps]
    record = (at or with_members)[-1]
    count = len(record["per_member"])
    returns = [_record_return(record, k) for k in range(count)]
    return max(range(count), key=lambda k: (returns[k], -k))  # ties: the lower index


def member_out_of_range(requested: int, count: int) -> str:
    """The one line ``export`` and ``render`` give for a ``--member`` a run of ``count``
    members does not have (a negative one included)."""
    members = "1 member (0)" if count == 1 else f"{count} members (0 to {count - 1})"
    return f"--member {requested} is out of range: the run has {members}"


def choose_member(
    requested: int | None,
    count: int,
    records: list[dict],
    env_steps: int | None,
    error: type[ConfigError] = ExportError,
) -> int:
    """``requested`` checked against ``count`` members (else ``error``, the calling
    command's, saying :func:`member_out_of_range`), else :func:`best_member`, else 0."""
    if requested is None:
        best = best_member(records, env_steps)
        return best if best is not None and best < count else 0
    if not 0 <= requested < count:
        raise error(member_out_of_range(requested, count))
    return requested


def _member(tree: Any, k: int) -> Any:
    import jax

    return jax.tree.map(lambda x: np.asarray(x[k]), tree)


def restore_checkpoint(run_dir: Path, env: Any = None) -> tuple[Any, Any, Any, dict]:
    """``(config, population program, state, meta)`` of a run's newest good checkpoint,
    restored onto one device (as :func:`td3_jax.runner.finished.evaluate_run` does; ``env``: the
    environment object of a run trained on one)."""
    from td3_jax.runner import finished, rundir

    rundir.load_config(run_dir)  # one line for a directory without config.json
    if not rundir.checkpoint_steps(run_dir):  # (before the environment is made)
        raise rundir.no_checkpoint_error(run_dir)
    cfg, _, program = finished.run_program(Path(run_dir), env=env)
    state, meta = finished.restore_on_one_device(program, run_dir)
    return cfg, program, state, meta


def load_run_policy(run_dir: Path, member: int | None = None, env: Any = None) -> PolicyArrays:
    """The :class:`PolicyArrays` of member ``member`` of the run in ``run_dir`` (default: the
    best by the checkpoint's evaluation in metrics.jsonl, else member 0; ``env``: the
    environment object of a run trained on one)."""
    from td3_jax.runner import rundir
    from td3_jax.runner.logger import read_metrics

    if member is not None:  # a bad --member fails before the (slower) restore
        cfg = rundir.load_config(run_dir)
        choose_member(member, len(rundir.load_members(run_dir, cfg)), [], 0)
    cfg, program, state, meta = restore_checkpoint(run_dir, env)
    env_steps = int(meta.get("env_steps", 0))
    count = len(program.members)  # (the records only choose among several members)
    records = read_metrics(Path(run_dir) / "metrics.jsonl") if member is None and count > 1 else []
    k = choose_member(member, count, records, env_steps)
    spec = program.spec
    stats = _member(state.obs_stats, k) if spec.normalize_obs else None
    policy = extract_policy(
        spec.env, spec.agent.actor, _member(state.agent.actor_params, k), stats,
        member=k, env_steps=env_steps, precision=cfg.precision,
    )  # fmt: skip
    check_finite(policy)
    return policy


# --------------------------------------------------------------------------------------------
# the .npz file
# --------------------------------------------------------------------------------------------


def file_version(policy: PolicyArrays) -> int:
    """The policy file's format version: a plain actor's is version 1 (what loaders from before
    residual actors read), a residual one's :data:`FORMAT_VERSION` (2)."""
    return FORMAT_VERSION if policy.residual else MLP_VERSION


def npz_arrays(policy: PolicyArrays) -> dict[str, np.ndarray]:
    """The arrays of the policy file (read by :mod:`td3_jax.tools.policy_file`; no array needs
    pickle): version 1's for a plain actor, and of a residual one also ``network``,
    ``blocks``, ``rms_scale`` ``[width]`` and ``rms_epsilon`` (version 2)."""
    arrays = {
        "format_version": np.array(file_version(policy)), "env": np.array(policy.env),
        "observation_size": np.array(policy.observation_size),
        "action_size": np.array(policy.action_size), "layer_norm": np.array(policy.layer_norm),
        "num_layers": np.array(len(policy.kernels)), "member": np.array(policy.member),
        "env_steps": np.array(policy.env_steps), "precision": np.array(policy.precision),
        "normalize": np.array(policy.normalize), "obs_mean": policy.obs_mean,
        "obs_std": policy.obs_std, "obs_clip": np.float32(policy.obs_clip),
        "max_action": policy.max_action, "action_low": policy.action_low,
        "action_high": policy.action_high, "ln_epsilon": np.float32(policy.ln_epsilon),
    }  # fmt: skip
    for i, (kernel, bias) in enumerate(zip(policy.kernels, policy.biases, strict=True)):
        arrays[f"kernel_{i}"], arrays[f"bias_{i}"] = kernel, bias
    for i, (scale, bias) in enumerate(zip(policy.ln_scales, policy.ln_biases, strict=True)):
        arrays[f"ln_scale_{i}"], arrays[f"ln_bias_{i}"] = scale, bias
    if policy.residual:
        arrays.update(network=np.array(policy.network), blocks=np.array(policy.blocks),
                      rms_scale=policy.rms_scale,
                      rms_epsilon=np.float32(policy.rms_epsilon))  # fmt: skip
    return arrays


def save_npz(policy: PolicyArrays, path: Path) -> Path:
    """Writes the policy file ``path`` (``np.savez``; the name is kept as given)."""
    path = Path(path)
    with open(path, "wb") as file:  # (a file object: savez would append .npz to the name)
        np.savez(file, **npz_arrays(policy))
    return path


# --------------------------------------------------------------------------------------------
# the ONNX model
# --------------------------------------------------------------------------------------------


def require_onnx() -> Any:
    """The ``onnx`` module, or :class:`ExportError` saying how to install it."""
    try:
        return importlib.import_module("onnx")
    except ImportError:
        raise ExportError(
            "--format onnx needs the onnx package: pip install 'td3-jax[export]' "
            "(or use --format npz, which needs only NumPy to run)"
        ) from None


class _Graph:
    """Nodes and constants of an ONNX graph under construction (names made unique here)."""

    def __init__(self, onnx: Any):
        self.onnx, self.nodes, self.constants = onnx, [], []

    def constant(self, name: str, value: np.ndarray) -> str:
        self.constants.append(self.onnx.numpy_helper.from_array(_f32(value), name))
        return name

    def node(self, op: str, inputs: list[str], name: str, **attributes: Any) -> str:
        self.nodes.append(self.onnx.helper.make_node(op, inputs, [name], name=name, **attributes))
        return name


def _onnx_normalize(graph: _Graph, policy: PolicyArrays, x: str) -> str:
    """``clip((x - mean) / std, -clip, clip)``, or ``x`` without normalisation."""
    if not policy.normalize:
        return x
    x = graph.node("Sub", [x, graph.constant("obs_mean", policy.obs_mean)], "obs_centred")
    x = graph.node("Div", [x, graph.constant("obs_std", policy.obs_std)], "obs_scaled")
    low = graph.constant("obs_clip_low", np.float32(-policy.obs_clip))
    high = graph.constant("obs_clip_high", np.float32(policy.obs_clip))
    return graph.node("Clip", [x, low, high], "obs_normalized")


def _onnx_dense(graph: _Graph, policy: PolicyArrays, i: int, x: str) -> str:
    """Dense layer ``i``: ``x @ kernel_i + bias_i`` (MatMul, Add), ``[batch, out]``."""
    x = graph.node("MatMul", [x, graph.constant(f"kernel_{i}", policy.kernels[i])], f"matmul_{i}")
    return graph.node("Add", [x, graph.constant(f"bias_{i}", policy.biases[i])], f"dense_{i}")


def _onnx_layer_norm(graph: _Graph, policy: PolicyArrays, i: int, x: str) -> str:
    """LayerNorm ``i`` over the last axis of ``x [batch, features]`` (LayerNormalization)."""
    scale = graph.constant(f"ln_scale_{i}", policy.ln_scales[i])
    shift = graph.constant(f"ln_bias_{i}", policy.ln_biases[i])
    return graph.node("LayerNormalization", [x, scale, shift], f"layer_norm_{i}",
                      axis=-1, epsilon=policy.ln_epsilon)  # fmt: skip


def _onnx_mlp(graph: _Graph, policy: PolicyArrays, x: str) -> str:
    """The Dense layers (MatMul, Add), LayerNorm and ReLU after each hidden one."""
    last = len(policy.kernels) - 1
    for i in range(last):
        x = _onnx_dense(graph, policy, i, x)
        if policy.layer_norm:
            x = _onnx_layer_norm(graph, policy, i, x)
        x = graph.node("Relu", [x], f"relu_{i}")
    return _onnx_dense(graph, policy, last, x)


def _onnx_rms_norm(graph: _Graph, policy: PolicyArrays, x: str) -> str:
    """``x / sqrt(mean(x^2) + eps) * scale`` over the last axis of ``x [batch, width]`` (opset
    17 has no RMSNormalization; its ReduceMean takes ``axes`` as an attribute)."""
    square = graph.node("Mul", [x, x], "rms_square")
    mean = graph.node("ReduceMean", [square], "rms_mean", axes=[-1], keepdims=1)
    eps = graph.constant("rms_epsilon", np.float32(policy.rms_epsilon))
    rms = graph.node("Sqrt", [graph.node("Add", [mean, eps], "rms_variance")], "rms")
    x = graph.node("Div", [x, rms], "rms_normalized")
    return graph.node("Mul", [x, graph.constant("rms_scale", policy.rms_scale)], "rms_norm")


def _onnx_residual(graph: _Graph, policy: PolicyArrays, x: str) -> str:
    """The residual network: ``Dense_0``, per block ``h + relu(LN(Dense(relu(LN(Dense(h))))))``
    (names indexed as the parameters), then RMSNorm and the output Dense layer."""
    h = _onnx_dense(graph, policy, 0, x)
    for b in range(policy.blocks):
        y = _onnx_layer_norm(graph, policy, 2 * b, _onnx_dense(graph, policy, 2 * b + 1, h))
        y = graph.node("Relu", [y], f"relu_{2 * b}")
        y = _onnx_layer_norm(graph, policy, 2 * b + 1, _onnx_dense(graph, policy, 2 * b + 2, y))
        y = graph.node("Relu", [y], f"relu_{2 * b + 1}")
        h = graph.node("Add", [h, y], f"block_{b}")
    return _onnx_dense(graph, policy, 2 * policy.blocks + 1, _onnx_rms_norm(graph, policy, h))


def _onnx_action(graph: _Graph, policy: PolicyArrays, x: str) -> None:
    """``max_action * tanh(x)`` mapped to ``[low, high]``, as the graph's output ``action``."""
    x = graph.node("Tanh", [x], "tanh")
    x = graph.node("Mul", [x, graph.constant("max_action", policy.max_action)], "agent_action")
    one = graph.constant("one", np.float32(1.0))
    x = graph.node("Clip", [x, graph.constant("minus_one", np.float32(-1.0)), one], "clipped")
    x = graph.node("Add", [x, one], "shifted")
    x = graph.node("Mul", [x, graph.constant("half", np.float32(0.5))], "unit_action")
    span = graph.constant("action_span", policy.action_high - policy.action_low)
    x = graph.node("Mul", [x, span], "scaled_action")
    graph.node("Add", [graph.constant("action_low", policy.action_low), x], "action")


def onnx_metadata(policy: PolicyArrays) -> dict[str, str]:
    """The model's ``metadata_props``: where it comes from, the network (``mlp`` or
    ``residual``, its blocks), sizes, bounds, opset."""
    return {
        "producer": "td3-jax", "format_version": str(file_version(policy)), "env": policy.env,
        "network": policy.network, "blocks": str(policy.blocks),
        "observation_size": str(policy.observation_size),
        "action_size": str(policy.action_size), "layer_norm": str(policy.layer_norm).lower(),
        "normalize_obs": str(policy.normalize).lower(), "member": str(policy.member),
        "env_steps": str(policy.env_steps), "precision": policy.precision,
        "action_low": repr(policy.action_low.tolist()),
        "action_high": repr(policy.action_high.tolist()), "opset": str(ONNX_OPSET),
    }  # fmt: skip


def onnx_model(policy: PolicyArrays) -> Any:
    """The policy as a checked ``onnx.ModelProto`` (opset :data:`ONNX_OPSET`): input ``obs``
    float32 ``[batch, observation_size]``, output ``action`` float32 ``[batch, action_size]``."""
    onnx = require_onnx()
    helper, floats = onnx.helper, onnx.TensorProto.FLOAT
    graph = _Graph(onnx)
    network = _onnx_residual if policy.residual else _onnx_mlp
    _onnx_action(graph, policy, network(graph, policy, _onnx_normalize(graph, policy, "obs")))
    inputs = [helper.make_tensor_value_info("obs", floats, ["batch", policy.observation_size])]
    outputs = [helper.make_tensor_value_info("action", floats, ["batch", policy.action_size])]
    body = helper.make_graph(graph.nodes, "td3_jax_policy", inputs, outputs, graph.constants)
    model = helper.make_model(body, opset_imports=[helper.make_opsetid("", ONNX_OPSET)],
                              producer_name="td3-jax")  # fmt: skip
    helper.set_model_props(model, onnx_metadata(policy))
    onnx.checker.check_model(model, full_check=True)
    return model


def save_onnx(policy: PolicyArrays, path: Path) -> Path:
    """Writes the ONNX model of ``policy`` to ``path``."""
    path = Path(path)
    path.write_bytes(onnx_model(policy).SerializeToString())
    return path


# --------------------------------------------------------------------------------------------
# the command
# --------------------------------------------------------------------------------------------


def default_output(run_dir: Path, fmt: str) -> Path:
    """``run_dir/policy.onnx`` or ``run_dir/policy.npz``."""
    return Path(run_dir) / f"policy.{fmt}"


def _bounds(values: np.ndarray) -> str:
    return f"{values[0]:g}" if np.all(values == values[0]) else f"[{', '.join(map(str, values))}]"


def _network_summary(policy: PolicyArrays) -> str:
    if policy.residual:
        return f", residual actor ({policy.blocks} blocks of {policy.kernels[0].shape[1]})"
    return ", layer norm" if policy.layer_norm else ""


def summary(policy: PolicyArrays, label: str = "") -> str:
    """One line: environment, member (and its ``label``: seed and swept values), sizes, action
    bounds and what is not the default (layer norm, a residual actor, normalised
    observations)."""
    member = f"{policy.member} ({label})" if label else f"{policy.member}"
    return (
        f"{policy.env} member {member} at {policy.env_steps} env steps: "
        f"obs {policy.observation_size} -> action {policy.action_size} in "
        f"[{_bounds(policy.action_low)}, {_bounds(policy.action_high)}]"
        f"{_network_summary(policy)}"
        f"{', normalised observations' if policy.normalize else ''}"
    )


def check_output(out: Path, fmt: str) -> None:
    """Raises :class:`ExportError` where ``out`` cannot take a ``fmt`` policy: a suffix that is
    not ``.fmt`` (the other format's or none of them), a directory, a missing folder, an
    existing file that td3-jax did not export (replacing a policy file of its own is fine: a
    second export of a run), or a place this process may not write
    (:func:`~td3_jax.runner.logger.probe_write`)."""
    if out.is_dir():
        raise ExportError(f"--out {out} is a directory: name a file in it, as "
                          f"{out / default_output(Path(), fmt)}")  # fmt: skip
    other = {".onnx": "onnx", ".npz": "npz"}.get(out.suffix.lower())
    if other is None:
        raise ExportError(f"--out {out}: a --format {fmt} policy file ends in .{fmt} (as "
                          f"{out.name or 'policy'}.{fmt})")  # fmt: skip
    if other != fmt:
        raise ExportError(f"--out {out} names an .{other} file but --format is {fmt}")
    if not out.parent.is_dir():
        what = "is a file" if out.parent.exists() else "does not exist"
        raise ExportError(f"--out {out}: its folder {out.parent} {what}")
    if out.exists() and not _exported_by_td3_jax(out, fmt):
        raise ExportError(f"--out {out} exists and is not a policy td3-jax exported: remove "
                          "it or choose another name")  # fmt: skip
    try:
        probe_write(out)
    except OSError as err:
        raise ExportError(f"--out {out}: cannot write it ({err.strerror or err})") from err


def _exported_by_td3_jax(path: Path, fmt: str) -> bool:
    """Whether ``path`` is a ``fmt`` policy file td3-jax wrote, read from its first bytes only:
    an npz (a zip) holding ``format_version.npy``; an ONNX model whose header is its IR
    version (field 1) then the producer name ``td3-jax`` (field 2)."""
    try:
        if fmt == "npz":
            if not zipfile.is_zipfile(path):
                return False
            with zipfile.ZipFile(path) as archive:
                return "format_version.npy" in archive.namelist()
        with open(path, "rb") as file:
            head = file.read(32)
    except (OSError, zipfile.BadZipFile):
        return False
    return _onnx_producer(head) == b"td3-jax"


def _onnx_producer(head: bytes) -> bytes | None:
    """The producer name in the first bytes of a serialised ONNX ModelProto (tag 0x08, the IR
    version as a varint; tag 0x12, a length, the name), ``None`` where they are not that."""
    if not head.startswith(b"\x08"):
        return None
    i = 1
    while i < len(head) and head[i] & 0x80:  # (the varint's continuation bytes)
        i += 1
    if i + 2 >= len(head) or head[i + 1] != 0x12:
        return None
    length = head[i + 2]
    return head[i + 3 : i + 3 + length]


def export_run(
    run_dir: Path, fmt: str, out: Path | None = None, member: int | None = None, env: Any = None
) -> tuple[Path, PolicyArrays]:
    """Exports a run's policy (:func:`load_run_policy`) as ``fmt`` to ``out`` (default
    :func:`default_output`); returns ``(path written, policy)``. ``env``: the environment
    object of a run trained on one."""
    if fmt not in FORMATS:
        raise ExportError(f"--format {fmt!r} is not one of {', '.join(FORMATS)}")
    if fmt == "onnx":
        require_onnx()  # before the (slower) restore
    from td3_jax.runner.rundir import require_run_dir

    require_run_dir(run_dir)  # (the line eval and plot give)
    out = Path(out) if out is not None else default_output(run_dir, fmt)
    check_output(out, fmt)
    policy = load_run_policy(Path(run_dir), member, env)
    try:
        return (save_onnx if fmt == "onnx" else save_npz)(policy, out), policy
    except OSError as err:
        raise ExportError(f"--out {out}: cannot write it ({err.strerror or err})") from err


__all__ = [
    "FORMATS",
    "ExportError",
    "PolicyArrays",
    "check_output",
    "export_run",
    "extract_policy",
    "load_run_policy",
    "save_npz",
    "save_onnx",
]
