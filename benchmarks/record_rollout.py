"""Saves a run's recorded evaluation episodes (joint positions and rewards per step) to an .npz,
so the frames can be drawn on another machine (``td3_jax.tools.render.rollout_frames``): the GPU box
trains and rolls out, a machine with OpenGL draws.

Usage: python -m benchmarks.record_rollout RUN_DIR OUT.npz [--episodes N] [--seed S]
       python -m benchmarks.record_rollout --draw OUT.npz VIDEO.gif [--steps N] [--every K]
         [--dt S]
         (the first episode, its first N steps, every K-th frame; the environment is made from
         the name in the .npz, which needs its assets here but compiles nothing)
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from td3_jax.tools import render


def draw(recording: Path, video: Path, steps: int, every: int, size: tuple[int, int],
         dt: float) -> None:  # fmt: skip
    """Draws the first episode of a saved recording into ``video`` (labelled frames)."""
    from td3_jax import envs

    saved = np.load(recording)
    env = envs.make(str(saved["env"]))
    positions, rewards = saved["positions_0"][:steps], saved["rewards_0"][:steps]
    recorded = render.Rollout(env, int(saved["member"]), saved["returns"], [positions], [rewards])
    frames = render.rollout_frames(recorded, width=size[0], height=size[1])[0][::every]
    fps = 1.0 / (dt * every)  # real time
    render.write_video(video, frames, fps)
    print(f"{video}: {len(frames)} frames at {fps:.1f} fps, return of the episode "
          f"{float(saved['returns'][0]):.1f} ({len(saved['rewards_0'])} steps)")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--episodes", type=int, default=1)
    parser.add_argument("--seed", type=int, default=12345)
    parser.add_argument("--draw", action="store_true", help="RUN is a saved .npz, OUT a video")
    parser.add_argument("--steps", type=int, default=10**9)
    parser.add_argument("--every", type=int, default=1)
    parser.add_argument("--size", type=int, nargs=2, default=(240, 180))
    parser.add_argument("--dt", type=float, default=0.02, help="seconds per env step")
    args = parser.parse_args()
    if args.draw:
        draw(args.run, args.out, args.steps, args.every, tuple(args.size), args.dt)
        return
    recorded = render.rollout(args.run, episodes=args.episodes, seed=args.seed)
    arrays = {f"positions_{i}": p for i, p in enumerate(recorded.positions)}
    arrays |= {f"rewards_{i}": r for i, r in enumerate(recorded.rewards)}
    np.savez(args.out, returns=recorded.returns, member=recorded.member, env=recorded.env.name,
             **arrays)  # fmt: skip
    print(f"{args.out}: {recorded.env.name} member {recorded.member} returns {recorded.returns}")


if __name__ == "__main__":
    main()
