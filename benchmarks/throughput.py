"""Throughput of the pieces of the training loop on one device.

Measures, each on its second (compiled) call:
  raw      vmapped ``env.step`` of the source (Brax) in a lax.scan, zero actions: the ceiling;
  wrapped  the same through td3_jax.envs.step (action rescale, time limit, fresh-key auto-reset);
  loop     the full training chunk with gradient updates switched off (updates_per_iter=0);
  updates  gradient updates per second of the TD3 update at several batch sizes;
  full     env steps per second of the full loop with a preset's settings.

Usage: python benchmarks/throughput.py --env brax/ant --envs 1024 4096 --batches 256 8192
Prints a table and writes JSON lines to --out.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import jax
import jax.numpy as jnp

from td3_jax import envs
from td3_jax.config import preset
from td3_jax.training import make_trainer
from td3_jax.types import Transition


def timed(fn, *args, repeats: int = 2):
    """Seconds of the fastest of ``repeats`` calls after a warm-up call (compile excluded)."""
    out = fn(*args)
    jax.block_until_ready(out)
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - start)
    return best


def raw_rate(name: str, num_envs: int, steps: int) -> float:
    from brax import envs as brax_envs

    env = brax_envs.get_environment(name.split("/", 1)[1], backend="mjx")
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), num_envs))
    action = jnp.zeros((num_envs, env.action_size))

    @jax.jit
    def run(state):
        return jax.lax.scan(
            lambda s, _: (jax.vmap(env.step)(s, action), None), state, None, length=steps
        )[0]

    state = run(state)  # types of reset and step states differ: warm with a step state
    return num_envs * steps / timed(run, state)


def wrapped_rate(env: envs.Environment, num_envs: int, steps: int) -> float:
    state = jax.device_put(envs.reset(env, jax.random.PRNGKey(0), num_envs))
    action = jnp.zeros((num_envs, env.action_size))

    @jax.jit
    def run(state):
        return jax.lax.scan(
            lambda s, _: (envs.step(env, s, action)[0], None), state, None, length=steps
        )[0]

    return num_envs * steps / timed(run, state)


def loop_rate(cfg) -> float:
    trainer = make_trainer(cfg)
    state = jax.device_put(jax.jit(trainer.init)(jax.random.PRNGKey(0)))
    chunk = jax.jit(trainer.chunk)
    steps = cfg.iters_per_chunk * cfg.env_steps_per_iter
    return steps / timed(lambda s: chunk(s)[1], state)


def update_rate(cfg, batch_size: int, n: int = 100) -> float:
    trainer = make_trainer(cfg)
    agent = trainer.agent
    o, a = trainer.env.observation_size, trainer.env.action_size
    key = jax.random.PRNGKey(0)
    batch = Transition(
        jax.random.normal(key, (batch_size, o)),
        jnp.zeros((batch_size, a)),
        jnp.zeros(batch_size),
        jax.random.normal(key, (batch_size, o)),
        jnp.zeros(batch_size),
    )

    @jax.jit
    def run(state):
        return jax.lax.scan(
            lambda s, k: agent.update(s, batch, k), state, jax.random.split(key, n)
        )[0]

    return n / timed(run, agent.init(key))


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--env", default="brax/ant")
    parser.add_argument("--preset", default="ant")
    parser.add_argument("--envs", type=int, nargs="*", default=[1024, 4096, 16384])
    parser.add_argument("--batches", type=int, nargs="*", default=[256, 2048, 8192, 32768])
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--out", default="throughput.jsonl")
    parser.add_argument("--skip", nargs="*", default=[])
    args = parser.parse_args()
    base = dataclasses.replace(preset(args.preset), env=args.env)
    env = envs.make(args.env)
    rows = []

    def emit(**row):
        row.update(device=jax.devices()[0].device_kind, jax=jax.__version__, env=args.env)
        rows.append(row)
        print(json.dumps(row), flush=True)

    for n in args.envs:
        if "raw" not in args.skip and args.env.startswith("brax/"):
            emit(kind="raw_env_steps_per_s", num_envs=n, value=raw_rate(args.env, n, args.steps))
        if "wrapped" not in args.skip:
            emit(kind="wrapped_env_steps_per_s", num_envs=n, value=wrapped_rate(env, n, args.steps))
        if "loop" not in args.skip:
            cfg = dataclasses.replace(
                base,
                num_envs=n,
                updates_per_iter=0,
                warmup_steps=0,
                eval_every=n * args.steps,
                buffer_size=max(n * args.steps, 1),
            )
            emit(kind="loop_no_updates_env_steps_per_s", num_envs=n, value=loop_rate(cfg))
    if "updates" not in args.skip:
        for b in args.batches:
            emit(kind="updates_per_s", batch_size=b, value=update_rate(base, b))
    if "full" not in args.skip:
        cfg = dataclasses.replace(base, warmup_steps=0)
        emit(
            kind="full_loop_env_steps_per_s",
            num_envs=cfg.num_envs,
            updates_per_iter=cfg.updates_per_iter,
            batch_size=cfg.batch_size,
            value=loop_rate(cfg),
        )
    with open(args.out, "a") as f:
        for row in rows:
            f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
