"""Run an exported td3-jax policy (``td3-jax export --format npz``) with NumPy alone.

This module imports nothing but NumPy (not JAX, not flax, not the rest of td3-jax), so it can
be copied next to the ``.npz`` file onto a machine that has only NumPy::

    from policy_file import load      # or: from td3_jax.tools.policy_file import load
    policy = load("runs/pendulum/policy.npz")
    action = policy(obs)              # obs [..., observation_size] -> [..., action_size]

The policy computes, in float32, exactly what the trained actor does when it is evaluated:

1. ``z = clip((obs - mean) / std, -clip, clip)`` with the run's observation statistics
   (``std = sqrt(var + 1e-8)``; skipped when the run did not normalise observations);
2. the actor's network ``out`` of ``z``, then ``a = max_action * tanh(out)``. With
   ``dense_i(h) = h @ kernel_i + bias_i`` and ``ln_i(h) = (h - mean) / sqrt(var + eps) *
   ln_scale_i + ln_bias_i`` (LayerNorm over the features):

   - a plain (mlp) actor: for each hidden layer ``z = relu(ln_i(dense_i(z)))`` (the LayerNorm
     only when the run used ``--layer-norm``), then ``out = dense_last(z)``;
   - a residual actor of ``B`` blocks: ``h = dense_0(z)``; for each block ``b``,
     ``y = relu(ln_2b(dense_2b+1(h)))`` and ``h = h + relu(ln_2b+1(dense_2b+2(y)))``; then
     ``out = dense_2B+1(h / sqrt(mean(h^2) + rms_epsilon) * rms_scale)`` (an RMSNorm);

3. the action in the environment's own bounds: ``low + (clip(a, -1, 1) + 1) / 2 * (high - low)``.

File format, version 1 (a plain actor): ``kernel_i [in, out]`` and ``bias_i [out]`` for the
``num_layers`` Dense layers; ``ln_scale_i``, ``ln_bias_i`` (hidden layers) and ``ln_epsilon``
with layer norm; ``normalize``, ``obs_mean``, ``obs_std``, ``obs_clip``; ``max_action``,
``action_low``, ``action_high`` ``[action_size]``; and the metadata ``format_version``,
``env``, ``observation_size``, ``action_size``, ``layer_norm``, ``member``, ``env_steps``,
``precision``. Version 2 (a residual actor) adds ``network`` (``"residual"``; a file without
it is ``"mlp"``), ``blocks`` (``B``), ``rms_scale [width]`` and ``rms_epsilon``; its
``num_layers = 2B + 2`` Dense layers and ``2B`` LayerNorms (``ln_scale_i``, ``ln_bias_i``)
are numbered as above, and its ``layer_norm`` is false (the blocks always normalise). A plain
actor's file is still written as version 1. No array needs pickle.
"""

from __future__ import annotations

import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

#: The newest file format this module reads (2: residual actors).
FORMAT_VERSION = 2
#: The format of a plain (mlp) actor's file, which every version of this module reads.
MLP_VERSION = 1
#: The actor networks a file may hold (its ``network`` array; ``"mlp"`` without one).
NETWORKS = ("mlp", "residual")
#: The arrays a residual actor's file needs besides a plain one's.
RESIDUAL_ARRAYS = ("blocks", "rms_scale", "rms_epsilon")


class PolicyFileError(ValueError):
    """A file that is not an exported td3-jax policy this module can read."""


def _get(arrays: dict[str, np.ndarray], name: str, path: Path) -> np.ndarray:
    if name not in arrays:
        raise PolicyFileError(f"{path} is not a td3-jax policy file (no {name!r} array)")
    return arrays[name]


def read(path: str | Path) -> dict[str, np.ndarray]:
    """The arrays of the policy file ``path`` (float arrays as float32), checked for a known
    format version; :class:`PolicyFileError` otherwise."""
    path = Path(path)
    if path.is_file() and not zipfile.is_zipfile(path):  # e.g. an ONNX model
        raise PolicyFileError(f"{path} is not a policy file (an .npz of td3-jax export)")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
        raise PolicyFileError(f"cannot read {path} as a policy file ({err})") from err
    version = int(_get(arrays, "format_version", path))
    if version > FORMAT_VERSION:
        raise PolicyFileError(
            f"{path} has format version {version}; this loader reads up to {FORMAT_VERSION} "
            "(use the policy_file.py of the td3-jax that wrote it)"
        )
    if network(arrays) not in NETWORKS:
        raise PolicyFileError(f"{path} holds a {network(arrays)!r} actor; this loader runs "
                              f"{' and '.join(NETWORKS)} actors")  # fmt: skip
    _check_layers(arrays, path)
    return {k: v.astype(np.float32) if v.dtype.kind == "f" else v for k, v in arrays.items()}


def _check_layers(arrays: dict[str, np.ndarray], path: Path) -> None:
    """:class:`PolicyFileError` where an array the network needs is missing, or a residual
    actor's ``num_layers`` is not ``2 * blocks + 2``."""
    layers = int(_get(arrays, "num_layers", path))
    norms = layers - 1 if bool(_get(arrays, "layer_norm", path)) else 0
    if network(arrays) == "residual":
        for name in RESIDUAL_ARRAYS:
            _get(arrays, name, path)
        norms = 2 * int(arrays["blocks"])
        if layers != norms + 2:
            raise PolicyFileError(f"{path} is damaged: a residual actor of {norms // 2} blocks "
                                  f"has {norms + 2} layers, not {layers}")  # fmt: skip
    names = [f"{kind}_{i}" for i in range(layers) for kind in ("kernel", "bias")]
    names += [f"{kind}_{i}" for i in range(norms) for kind in ("ln_scale", "ln_bias")]
    for name in names + (["ln_epsilon"] if norms else []):
        _get(arrays, name, path)


def network(arrays: dict[str, np.ndarray]) -> str:
    """The actor's network in a file's arrays: ``"mlp"`` or ``"residual"``."""
    return str(arrays["network"]) if "network" in arrays else "mlp"


def _layer_norm(h: np.ndarray, scale: np.ndarray, bias: np.ndarray, eps: np.float32):
    """LayerNorm over the last axis of ``h [..., width]`` (float32 throughout)."""
    mean = h.mean(axis=-1, keepdims=True, dtype=np.float32)
    var = np.square(h - mean).mean(axis=-1, keepdims=True, dtype=np.float32)
    return (h - mean) / np.sqrt(var + eps) * scale + bias


def _rms_norm(h: np.ndarray, scale: np.ndarray, eps: np.float32) -> np.ndarray:
    """RMSNorm over the last axis of ``h [..., width]``: ``h / sqrt(mean(h^2) + eps) * scale``."""
    mean_square = np.square(h).mean(axis=-1, keepdims=True, dtype=np.float32)
    return h / np.sqrt(mean_square + eps) * scale


def _dense(arrays: dict[str, np.ndarray], i: int, z: np.ndarray) -> np.ndarray:
    """Dense layer ``i``: ``z [..., in] @ kernel_i + bias_i -> [..., out]``."""
    return z @ arrays[f"kernel_{i}"] + arrays[f"bias_{i}"]


def _norm(arrays: dict[str, np.ndarray], i: int, z: np.ndarray) -> np.ndarray:
    """LayerNorm ``i`` of ``z [..., features]``."""
    eps = np.float32(arrays["ln_epsilon"])
    return _layer_norm(z, arrays[f"ln_scale_{i}"], arrays[f"ln_bias_{i}"], eps)


def _relu(z: np.ndarray) -> np.ndarray:
    return np.maximum(z, np.float32(0.0))


def _mlp(arrays: dict[str, np.ndarray], z: np.ndarray) -> np.ndarray:
    """A plain actor's network, ``[..., observation_size] -> [..., action_size]``."""
    last = int(arrays["num_layers"]) - 1
    for i in range(last):
        z = _dense(arrays, i, z)
        if bool(arrays["layer_norm"]):
            z = _norm(arrays, i, z)
        z = _relu(z)
    return _dense(arrays, last, z)


def _residual(arrays: dict[str, np.ndarray], z: np.ndarray) -> np.ndarray:
    """A residual actor's network, ``[..., observation_size] -> [..., action_size]``."""
    blocks = int(arrays["blocks"])
    h = _dense(arrays, 0, z)
    for b in range(blocks):
        y = _relu(_norm(arrays, 2 * b, _dense(arrays, 2 * b + 1, h)))
        h = h + _relu(_norm(arrays, 2 * b + 1, _dense(arrays, 2 * b + 2, y)))
    h = _rms_norm(h, arrays["rms_scale"], np.float32(arrays["rms_epsilon"]))
    return _dense(arrays, 2 * blocks + 1, h)


def forward(arrays: dict[str, np.ndarray], obs: np.ndarray) -> np.ndarray:
    """Actions ``[..., action_size]`` in the environment's bounds for ``obs [...,
    observation_size]``, from the arrays of :func:`read` (computed in float32)."""
    z = np.asarray(obs, np.float32)
    if bool(arrays["normalize"]):
        clip = arrays["obs_clip"]
        z = np.clip((z - arrays["obs_mean"]) / arrays["obs_std"], -clip, clip)
    z = (_residual if network(arrays) == "residual" else _mlp)(arrays, z)
    action = arrays["max_action"] * np.tanh(z)
    low, high = arrays["action_low"], arrays["action_high"]
    return low + (np.clip(action, -1.0, 1.0) + np.float32(1.0)) * np.float32(0.5) * (high - low)


def load(path: str | Path) -> Callable[[np.ndarray], np.ndarray]:
    """The policy in ``path``: ``policy(obs[..., observation_size]) -> action[...,
    action_size]`` (float32, within ``[action_low, action_high]``).

    The callable also has the attributes ``observation_size``, ``action_size``,
    ``action_low``, ``action_high``, ``env``, ``network`` (``"mlp"`` or ``"residual"``) and
    ``arrays`` (everything in the file). An
    observation of another size raises :class:`PolicyFileError`.
    """
    arrays = read(path)
    size = int(_get(arrays, "observation_size", Path(path)))

    def policy(obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, np.float32)
        if obs.ndim == 0 or obs.shape[-1] != size:
            raise PolicyFileError(
                f"the policy in {path} takes observations [..., {size}], got shape {obs.shape}"
            )
        return forward(arrays, obs)

    policy.observation_size = size
    policy.action_size = int(arrays["action_size"])
    policy.action_low, policy.action_high = arrays["action_low"], arrays["action_high"]
    policy.env = str(arrays["env"])
    policy.network = network(arrays)
    policy.arrays = arrays
    return policy


__all__ = [
    "FORMAT_VERSION",
    "MLP_VERSION",
    "PolicyFileError",
    "forward",
    "load",
    "network",
    "read",
]
