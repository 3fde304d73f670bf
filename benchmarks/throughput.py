"""Throughput of the pieces of the training loop on one device.

Measures, each on its second (compiled) call:
  raw      vmapped ``env.step`` of the source (Brax) in a lax.scan, zero actions: the ceiling;
  raw_random  the same with uniform random actions (what the loop does during warm-up: the
           physics costs more when the bodies move and collide);
  wrapped  the same through td3_jax.envs.step (action rescale, time limit, fresh-key auto-reset),
           zero actions; ``wrapped_random`` with random actions, with the default per-environment
           resets and (``wrapped_random_batch_reset``) with the whole batch reset on every step
           where an episode ended; also the mean number of episodes ending per step;
  loop     the full training chunk with gradient updates switched off (updates_per_iter=0,
           random warm-up actions), also with whole-batch resets (``loop_batch_reset``);
  updates  gradient updates per second of the TD3 update at several batch sizes;
  full     env steps per second of the full loop with a preset's settings.

Usage: python -m benchmarks.throughput --env brax/ant --envs 1024 4096 --batches 256 8192
Prints a table and writes JSON lines to --out.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from td3_jax import envs
from td3_jax.common import upstream
from td3_jax.config.build import make_trainer
from td3_jax.config.presets import preset
from td3_jax.config.schema import TrainConfig
from td3_jax.core.types import Transition


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


def _actions(key, num_envs: int, action_size: int, random: bool) -> jax.Array:
    if random:
        return jax.random.uniform(key, (num_envs, action_size), minval=-1.0, maxval=1.0)
    return jnp.zeros((num_envs, action_size))


def raw_rate(name: str, num_envs: int, steps: int, random: bool = False) -> float:
    from brax import envs as brax_envs

    env = brax_envs.get_environment(name.split("/", 1)[1], backend="mjx")
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), num_envs))

    @jax.jit
    def run(state):
        def body(s, key):
            return jax.vmap(env.step)(s, _actions(key, num_envs, env.action_size, random)), None

        keys = jax.random.split(jax.random.PRNGKey(1), steps)
        return jax.lax.scan(body, state, keys)[0]

    state = run(state)  # types of reset and step states differ: warm with a step state
    return num_envs * steps / timed(run, state)


def wrapped_rate(
    env: envs.Environment,
    num_envs: int,
    steps: int,
    random: bool = False,
    reset_slots=None,
    auto_reset: bool = True,
) -> tuple[float, float]:
    """Env steps/s through envs.step, and the mean number of episodes ending per step."""
    state = jax.device_put(envs.reset(env, jax.random.PRNGKey(0), num_envs))

    @jax.jit
    def run(state):
        def body(s, key):
            action = _actions(key, num_envs, env.action_size, random)
            s, result = envs.step(env, s, action, reset_slots=reset_slots, auto_reset=auto_reset)
            return s, jnp.sum(result.terminated | result.truncated)

        keys = jax.random.split(jax.random.PRNGKey(1), steps)
        return jax.lax.scan(body, state, keys)

    _, ended = run(state)
    return num_envs * steps / timed(run, state), float(jnp.mean(ended))


def loop_rate(cfg, batch_reset: bool = False) -> float:
    if batch_reset:  # every step with an ended episode resets the whole batch (the old way)
        default, envs.base.default_reset_slots = envs.base.default_reset_slots, lambda n: n
        try:
            trainer = make_trainer(cfg)
            return loop_rate_of(trainer, cfg)
        finally:
            envs.base.default_reset_slots = default
    return loop_rate_of(make_trainer(cfg), cfg)


def loop_rate_of(trainer, cfg) -> float:
    state = jax.device_put(jax.jit(trainer.init)(jax.random.PRNGKey(0)))
    options = upstream.compile_options(jax.devices()[0].platform, cfg.matmuls)
    chunk = jax.jit(trainer.chunk).lower(state).compile(compiler_options=options)  # as the CLI
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


def _parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    parser.add_argument("--env", default="brax/ant")
    parser.add_argument("--preset", default="ant")
    parser.add_argument("--envs", type=int, nargs="*", default=[1024, 4096, 16384])
    parser.add_argument("--batches", type=int, nargs="*", default=[256, 2048, 8192, 32768])
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--out", default="throughput.jsonl")
    parser.add_argument("--skip", nargs="*", default=[])
    return parser.parse_args()


def _env_rates(args: argparse.Namespace, env: Any, n: int, emit: Callable[..., None]) -> None:
    """The environment's own rates at ``n`` environments: raw Brax (random or zero actions),
    through td3-jax's wrapper (with and without the reset branch, one or batched resets)."""
    if "raw" not in args.skip and args.env.startswith("brax/"):
        emit(kind="raw_env_steps_per_s", num_envs=n, value=raw_rate(args.env, n, args.steps))
    if "raw_random" not in args.skip and args.env.startswith("brax/"):
        value = raw_rate(args.env, n, args.steps, random=True)
        emit(kind="raw_random_env_steps_per_s", num_envs=n, value=value)
    if "wrapped" not in args.skip:
        value, _ = wrapped_rate(env, n, args.steps)
        emit(kind="wrapped_env_steps_per_s", num_envs=n, value=value)
        value, _ = wrapped_rate(env, n, args.steps, auto_reset=False)
        emit(kind="wrapped_no_reset_branch_env_steps_per_s", num_envs=n, value=value)
    if "wrapped_random" not in args.skip:
        for kind, slots in (("", None), ("_batch_reset", n)):
            value, ended = wrapped_rate(env, n, args.steps, random=True, reset_slots=slots)
            emit(kind=f"wrapped_random{kind}_env_steps_per_s", num_envs=n, value=value,
                 episodes_ended_per_step=ended)  # fmt: skip


def _loop_rates(args: argparse.Namespace, base: TrainConfig, n: int,
                emit: Callable[..., None]) -> None:  # fmt: skip
    """The training loop's rate at ``n`` environments with no updates (random actions
    throughout, as in a warm-up), with per-slot and batched resets."""
    if "loop" in args.skip:
        return
    steps = n * args.steps
    cfg = dataclasses.replace(base, num_envs=n, updates_per_iter=0, warmup_steps=steps,
                              eval_every=steps, buffer_size=max(steps, 1))  # fmt: skip
    emit(kind="loop_no_updates_env_steps_per_s", num_envs=n, value=loop_rate(cfg))
    if "loop_batch_reset" not in args.skip:
        value = loop_rate(cfg, batch_reset=True)
        emit(kind="loop_no_updates_batch_reset_env_steps_per_s", num_envs=n, value=value)


def _learner_rates(args: argparse.Namespace, base: TrainConfig, emit: Callable[..., None]) -> None:
    """Updates per second at each batch size, then the preset's full loop (no warm-up)."""
    if "updates" not in args.skip:
        for b in args.batches:
            emit(kind="updates_per_s", batch_size=b, value=update_rate(base, b))
    if "full" not in args.skip:
        cfg = dataclasses.replace(base, warmup_steps=0)
        emit(kind="full_loop_env_steps_per_s", num_envs=cfg.num_envs,
             updates_per_iter=cfg.updates_per_iter, batch_size=cfg.batch_size,
             value=loop_rate(cfg))  # fmt: skip


def main() -> None:
    args = _parse_args()
    base = dataclasses.replace(preset(args.preset), env=args.env)
    env = envs.make(args.env)
    rows = []

    def emit(**row):
        row.update(device=jax.devices()[0].device_kind, jax=jax.__version__, env=args.env)
        rows.append(row)
        print(json.dumps(row), flush=True)

    for n in args.envs:
        _env_rates(args, env, n, emit)
        _loop_rates(args, base, n, emit)
    _learner_rates(args, base, emit)
    with open(args.out, "a") as f:
        for row in rows:
            f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
