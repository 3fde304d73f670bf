"""Where the residual critics' update time goes: benchmarks/updates.py's residual critics (the
``g1`` preset's two blocks of 256, C51, bf16, FastTD3's rules, batch 32768, G1's sizes) with
their LayerNorms replaced, one variant a process:

* ``base``: flax's LayerNorm as the library uses it (one-pass variance, float32 statistics);
* ``none``: no normalisation (identity; the time the LayerNorms cost, not a usable network);
* ``rms``: RMSNorm (no mean subtracted) in their place;
* ``nof32``: LayerNorm with statistics in the activations' dtype (bf16);
* ``slowvar``: LayerNorm with the two-pass variance.

A diagnostic: it replaces ``flax.linen.LayerNorm`` in this process only. On the GPU machine,
with the robot presets' cuBLAS matmuls:

    export XLA_FLAGS=--xla_gpu_enable_triton_gemm=false
    for v in base none rms nof32 slowvar; do python -m benchmarks.residual_norms $v; done
"""

from __future__ import annotations

import functools
import sys

import flax.linen as nn

VARIANTS = ("base", "none", "rms", "nof32", "slowvar")


class Identity(nn.Module):
    """Stands where a LayerNorm was (same constructor arguments), returning its input."""

    dtype: object = None
    param_dtype: object = None

    def __call__(self, x):
        return x


def patch_layer_norm(variant: str) -> None:
    """Replace ``flax.linen.LayerNorm`` by ``variant``'s normalisation."""
    layer_norm = nn.LayerNorm
    replacements = {
        "base": layer_norm,
        "none": Identity,
        "rms": lambda dtype=None, param_dtype=None: nn.RMSNorm(
            dtype=dtype, param_dtype=param_dtype
        ),
        "nof32": functools.partial(layer_norm, force_float32_reductions=False),
        "slowvar": functools.partial(layer_norm, use_fast_variance=False),
    }
    nn.LayerNorm = replacements[variant]


def main() -> None:
    variant = sys.argv[1] if len(sys.argv) > 1 else ""
    if variant not in VARIANTS:
        raise SystemExit(f"usage: python -m benchmarks.residual_norms VARIANT (one of "
                         f"{', '.join(VARIANTS)})")
    patch_layer_norm(variant)
    from benchmarks import updates  # (after the patch: the networks are built in its calls)

    sys.argv = ["updates.py", "--out", f"/tmp/residual_norms_{variant}", "--batches", "32768",
                "--shapes", "103x216x29", "--networks", "residual", "--critics", "distributional",
                "--precisions", "bfloat16", "--rules", "fasttd3"]  # fmt: skip
    print(f"variant {variant}", flush=True)
    updates.main()


if __name__ == "__main__":
    main()
