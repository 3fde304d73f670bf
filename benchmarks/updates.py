"""Gradient updates per second of the TD3 update with FastTD3-size networks (issue 14).

For every combination of critic (plain, distributional C51 with 101 atoms), precision (float32,
bfloat16 matmuls), batch size and (observation, action) size, ``--updates`` TD3 updates
(critic 1024-512-256, actor 512-256-128, two critics, policy_freq 2, AdamW) run in one
``lax.scan`` on a fixed device-resident batch; the time of the fastest of ``--repeats`` calls
after a warm-up call (compile excluded) gives updates/s. Replay sampling is not included.

Usage (from the project root): python3 benchmarks/updates.py --out DIR
Prints a table and writes DIR/updates.csv (and DIR/updates.jsonl).
"""

from __future__ import annotations

import argparse
import csv
import functools
import itertools
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from td3_jax import actor_critic as ac
from td3_jax.types import Transition

CRITIC_HIDDEN, ACTOR_HIDDEN = (1024, 512, 256), (512, 256, 128)
COLUMNS = ("critic", "precision", "batch", "obs", "act", "updates_per_s", "ms_per_update",
           "samples_per_s", "device", "jax")  # fmt: skip


def make_spec(critic: str, precision: str, obs: int, act: int, layer_norm: bool) -> ac.AgentSpec:
    options = ac.AgentOptions(
        num_atoms=101 if critic == "distributional" else 0,
        actor_hidden_sizes=ACTOR_HIDDEN,
        critic_hidden_sizes=CRITIC_HIDDEN,
        layer_norm=layer_norm,
        precision=precision,
        actor_q="min",
    )
    return ac.make_spec(CRITIC_HIDDEN, obs, act, num_critics=2, target_smoothing=True,
                        policy_freq=2, options=options)  # fmt: skip


def random_batch(key: jax.Array, batch: int, obs: int, act: int) -> Transition:
    keys = jax.random.split(key, 4)
    return Transition(
        obs=jax.random.normal(keys[0], (batch, obs)),
        action=jax.random.uniform(keys[1], (batch, act), minval=-1.0, maxval=1.0),
        reward=jax.random.normal(keys[2], (batch,)),
        next_obs=jax.random.normal(keys[3], (batch, obs)),
        done=jnp.zeros((batch,)),
    )


@functools.partial(jax.jit, static_argnums=(0, 4), donate_argnums=2)
def run_updates(spec, hp, state, batch, n, key):
    """``n`` updates on ``batch`` in one scan; returns the state and the last critic loss."""
    step = lambda s, k: ac.update(spec, hp, s, batch, k)
    state, metrics = jax.lax.scan(step, state, jax.random.split(key, n))
    return state, metrics["critic_loss"][-1]


def updates_per_second(spec, batch_size: int, updates: int, repeats: int) -> float:
    hp = ac.AgentHyperparams(
        **{k: jnp.float32(v) for k, v in dict(
            discount=0.99, tau=0.005, actor_lr=3e-4, critic_lr=3e-4, policy_noise=0.2,
            noise_clip=0.5, weight_decay=0.1, v_min=-10.0, v_max=10.0).items()}
    )  # fmt: skip
    key = jax.random.PRNGKey(0)
    state = jax.jit(functools.partial(ac.init, spec))(key)  # distinct buffers: donated
    batch = random_batch(key, batch_size, spec.observation_size, spec.action_size)
    state, loss = run_updates(spec, hp, state, batch, updates, key)  # compile + warm-up
    jax.block_until_ready(loss)
    best = float("inf")
    for i in range(repeats):
        start = time.perf_counter()
        state, loss = run_updates(spec, hp, state, batch, updates, jax.random.PRNGKey(i + 1))
        jax.block_until_ready(loss)
        best = min(best, time.perf_counter() - start)
    if not jnp.isfinite(loss):
        raise RuntimeError(f"non-finite critic loss {float(loss)} for {spec.options}")
    return updates / best


def shape(text: str) -> tuple[int, int]:
    obs, act = text.lower().split("x")
    return int(obs), int(act)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, help="directory for updates.csv/.jsonl")
    parser.add_argument("--batches", type=int, nargs="+", default=[8192, 32768])
    parser.add_argument("--shapes", type=shape, nargs="+", default=[(85, 12), (180, 23)],
                        help="OBSxACT sizes (default: 85x12 180x23)")  # fmt: skip
    parser.add_argument("--critics", nargs="+", default=["plain", "distributional"])
    parser.add_argument("--precisions", nargs="+", default=["float32", "bfloat16"])
    parser.add_argument("--updates", type=int, default=50, help="updates per timed call")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--layer-norm", action="store_true")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    device = jax.devices()[0].device_kind
    rows = []
    combos = itertools.product(args.shapes, args.batches, args.critics, args.precisions)
    print(" ".join(f"{c:>14}" for c in COLUMNS[:8]), flush=True)
    with (out / "updates.jsonl").open("w") as log:
        for (obs, act), batch, critic, precision in combos:
            spec = make_spec(critic, precision, obs, act, args.layer_norm)
            rate = updates_per_second(spec, batch, args.updates, args.repeats)
            row = dict(
                critic=critic,
                precision=precision,
                batch=batch,
                obs=obs,
                act=act,
                updates_per_s=round(rate, 2),
                ms_per_update=round(1000 / rate, 3),
                samples_per_s=round(rate * batch),
                device=device,
                jax=jax.__version__,
            )
            rows.append(row)
            log.write(json.dumps(row) + "\n")
            print(" ".join(f"{row[c]!s:>14}" for c in COLUMNS[:8]), flush=True)
    with (out / "updates.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    print(f"wrote {out / 'updates.csv'} ({device})")


if __name__ == "__main__":
    main()
