"""Run an exported td3-jax policy (``td3-jax export --format npz``) with NumPy alone.

This module imports nothing but NumPy (not JAX, not flax, not the rest of td3-jax), so it can
be copied next to the ``.npz`` file onto a machine that has only NumPy::

    from policy_file import load      # or: from td3_jax.policy_file import load
    policy = load("runs/pendulum/policy.npz")
    action = policy(obs)              # obs [..., observation_size] -> [..., action_size]

The policy computes, in float32, exactly what the trained actor does when it is evaluated:

1. ``z = clip((obs - mean) / std, -clip, clip)`` with the run's observation statistics
   (``std = sqrt(var + 1e-8)``; skipped when the run did not normalise observations);
2. for each hidden layer ``h = relu(layer_norm(z @ kernel + bias))`` (the LayerNorm only when
   the run used ``--layer-norm``: ``(h - mean) / sqrt(var + eps) * scale + bias`` over the
   features), then ``a = max_action * tanh(h @ kernel + bias)``;
3. the action in the environment's own bounds: ``low + (clip(a, -1, 1) + 1) / 2 * (high - low)``.

File format (version 1): ``kernel_i [in, out]`` and ``bias_i [out]`` for the ``num_layers``
Dense layers; ``ln_scale_i``, ``ln_bias_i`` (hidden layers) and ``ln_epsilon`` with layer norm;
``normalize``, ``obs_mean``, ``obs_std``, ``obs_clip``; ``max_action``, ``action_low``,
``action_high`` ``[action_size]``; and the metadata ``format_version``, ``env``,
``observation_size``, ``action_size``, ``layer_norm``, ``member``, ``env_steps``,
``precision``. No array needs pickle.
"""

from __future__ import annotations

import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

#: The newest file format this module reads.
FORMAT_VERSION = 1


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
    return {k: v.astype(np.float32) if v.dtype.kind == "f" else v for k, v in arrays.items()}


def _layer_norm(h: np.ndarray, scale: np.ndarray, bias: np.ndarray, eps: np.float32):
    """LayerNorm over the last axis of ``h [..., width]`` (float32 throughout)."""
    mean = h.mean(axis=-1, keepdims=True, dtype=np.float32)
    var = np.square(h - mean).mean(axis=-1, keepdims=True, dtype=np.float32)
    return (h - mean) / np.sqrt(var + eps) * scale + bias


def forward(arrays: dict[str, np.ndarray], obs: np.ndarray) -> np.ndarray:
    """Actions ``[..., action_size]`` in the environment's bounds for ``obs [...,
    observation_size]``, from the arrays of :func:`read` (computed in float32)."""
    z = np.asarray(obs, np.float32)
    if bool(arrays["normalize"]):
        clip = arrays["obs_clip"]
        z = np.clip((z - arrays["obs_mean"]) / arrays["obs_std"], -clip, clip)
    layers = int(arrays["num_layers"])
    for i in range(layers):
        z = z @ arrays[f"kernel_{i}"] + arrays[f"bias_{i}"]
        if i + 1 < layers:
            if bool(arrays["layer_norm"]):
                eps = np.float32(arrays["ln_epsilon"])
                z = _layer_norm(z, arrays[f"ln_scale_{i}"], arrays[f"ln_bias_{i}"], eps)
            z = np.maximum(z, np.float32(0.0))
    action = arrays["max_action"] * np.tanh(z)
    low, high = arrays["action_low"], arrays["action_high"]
    return low + (np.clip(action, -1.0, 1.0) + np.float32(1.0)) * np.float32(0.5) * (high - low)


def load(path: str | Path) -> Callable[[np.ndarray], np.ndarray]:
    """The policy in ``path``: ``policy(obs[..., observation_size]) -> action[...,
    action_size]`` (float32, within ``[action_low, action_high]``).

    The callable also has the attributes ``observation_size``, ``action_size``,
    ``action_low``, ``action_high``, ``env`` and ``arrays`` (everything in the file). An
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
    policy.arrays = arrays
    return policy


__all__ = [
    "FORMAT_VERSION",
    "PolicyFileError",
    "forward",
    "load",
    "read",
]
