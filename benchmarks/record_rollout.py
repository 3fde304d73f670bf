"""Saves a run's recorded evaluation episodes (joint positions and rewards per step) to an .npz,
so the frames can be drawn on another machine (``td3_jax.render.rollout_frames``): the GPU box
trains and rolls out, a machine with OpenGL draws.

Usage: python3 benchmarks/record_rollout.py RUN_DIR OUT.npz [--episodes N] [--seed S]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from td3_jax import render


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--episodes", type=int, default=1)
    parser.add_argument("--seed", type=int, default=12345)
    args = parser.parse_args()
    recorded = render.rollout(args.run, episodes=args.episodes, seed=args.seed)
    arrays = {f"positions_{i}": p for i, p in enumerate(recorded.positions)}
    arrays |= {f"rewards_{i}": r for i, r in enumerate(recorded.rewards)}
    np.savez(args.out, returns=recorded.returns, member=recorded.member, env=recorded.env.name,
             **arrays)  # fmt: skip
    print(f"{args.out}: {recorded.env.name} member {recorded.member} returns {recorded.returns}")


if __name__ == "__main__":
    main()
