"""Gradient updates per second of the TD3 update with FastTD3-size networks.

For every combination of critic (plain, distributional C51 with 101 atoms), precision (float32,
bfloat16 matmuls), batch size, (observation, action) size and C51 projection, ``--updates`` TD3
updates (critic 1024-512-256, actor 512-256-128, two critics, policy_freq 2, AdamW) run in one
``lax.scan`` on a fixed device-resident batch; the time of the fastest of ``--repeats`` calls
after a warm-up call (compile excluded) gives updates/s. Replay sampling is not included unless
``--ring ROWS``: then every update draws its batch from a filled ring of ``ROWS`` rows laid out
as the trainer's (both observation rows, action, reward, done, ended), as in the training loop.

``--shapes OBSxACT`` or ``OBSxCRITICxACT`` (an asymmetric critic on a larger observation whose
first OBS features are the actor's, as the Playground robots': G1 103x216x29, T1 85x180x23).
``--rules fasttd3``: the presets' FastTD3 rules (target critics averaged after every update,
the C51 target head chosen by projected means, no target actor, actor on the lower head);
``paper`` (default): the library's. ``--projections library einsum``: the C51 projection as the
library computes it (``library``) and, as the baseline in the same command, the dense form
td3-jax used before 2026-11-25 (``einsum``, over ``[..., atoms, atoms]`` weights).

``--networks mlp residual``: the critics plain (1024-512-256) and/or in the `g1` preset's
residual layout (two blocks of 256); ``--actors mlp residual``: the actor plain (512-256-128)
and/or residual (two blocks of 128, FlashSAC's, ``--actor-network residual``);
``--max-weight-norm B``: each combination also with its weights bounded to norm B after every
step. The robot presets' cuBLAS matmuls: run with
``XLA_FLAGS=--xla_gpu_enable_triton_gemm=false``.

Usage (from the project root): python -m benchmarks.updates --out DIR
Prints a table and writes DIR/updates.csv (and DIR/updates.jsonl).
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import functools
import itertools
import json
import time
from pathlib import Path
from unittest import mock

import jax
import jax.numpy as jnp

from td3_jax.core import actor_critic as ac
from td3_jax.core import distributional, replay
from td3_jax.core.types import Transition

CRITIC_HIDDEN, ACTOR_HIDDEN = (1024, 512, 256), (512, 256, 128)
NETWORK_SIZES = {"mlp": CRITIC_HIDDEN, "residual": (256, 256)}
ACTOR_SIZES = {"mlp": ACTOR_HIDDEN, "residual": (128, 128)}
COLUMNS = ("critic", "network", "actor", "bound", "precision", "batch", "shape", "rules",
           "projection", "ring", "updates_per_s", "ms_per_update", "samples_per_s", "device",
           "jax")  # fmt: skip
RULES = {
    "paper": dict(actor_q="min"),
    "fasttd3": dict(actor_q="min", target_actor=False, target_update="every_update",
                    c51_target_head="projected"),
}  # fmt: skip


def einsum_project(probs, target_z, v_min, v_max):
    """The C51 projection as td3-jax computed it before 2026-11-25 (the baseline): an einsum
    over the ``[..., j, i]`` weights, which XLA lowers to a batched matrix-vector product."""
    num_atoms = probs.shape[-1]
    b = (jnp.clip(target_z, v_min, v_max) - v_min) / ((v_max - v_min) / (num_atoms - 1))
    atoms = jnp.arange(num_atoms, dtype=b.dtype)
    weights = jnp.clip(1.0 - jnp.abs(b[..., :, None] - atoms), 0.0, 1.0)
    return jnp.einsum("...j,...ji->...i", probs, weights)


def projection(name: str):
    """A context in which the C51 projection is ``name``'s (``library``: the library's own)."""
    if name == "library":
        return contextlib.nullcontext()
    return mock.patch.object(distributional, "project", einsum_project)


def make_spec(
    critic: str,
    precision: str,
    shape: tuple,
    layer_norm: bool,
    rules: str,
    network: str = "mlp",
    bound: bool = False,
    actor: str = "mlp",
):
    obs, critic_obs, act = shape
    hidden = NETWORK_SIZES[network]
    options = ac.AgentOptions(
        num_atoms=101 if critic == "distributional" else 0,
        actor_hidden_sizes=ACTOR_SIZES[actor],
        critic_hidden_sizes=hidden,
        layer_norm=layer_norm,
        precision=precision,
        critic_network=network,
        actor_network=actor,
        bound_weights=bound,
        **RULES[rules],
    )
    return ac.make_spec(hidden, obs, act, num_critics=2, target_smoothing=True,
                        policy_freq=2, options=options,
                        critic_observation_size=critic_obs)  # fmt: skip


def random_rows(key: jax.Array, rows: int, row: int, act: int) -> Transition:
    """``rows`` random transitions of ``row``-feature observation rows."""
    keys = jax.random.split(key, 4)
    return Transition(
        obs=jax.random.normal(keys[0], (rows, row)),
        action=jax.random.uniform(keys[1], (rows, act), minval=-1.0, maxval=1.0),
        reward=jax.random.normal(keys[2], (rows,)),
        next_obs=jax.random.normal(keys[3], (rows, row)),
        done=jnp.zeros((rows,)),
    )


def agent_batch(spec: ac.AgentSpec, rows: Transition) -> Transition:
    """Rows split as the trainer splits them: the actor's first features, the critics' all."""
    if spec.critic_observation_size is None:
        return rows
    o = spec.observation_size
    return rows._replace(obs=rows.obs[:, :o], next_obs=rows.next_obs[:, :o],
                         critic_obs=rows.obs, next_critic_obs=rows.next_obs)  # fmt: skip


@functools.partial(jax.jit, static_argnums=(0, 1))
def filled_ring(spec: ac.AgentSpec, rows: int, key: jax.Array) -> replay.ReplayBuffer:
    """A full one-slice ring of ``rows`` random rows, ``(Transition, ended)`` as stored."""
    row = spec.critic_observation_size or spec.observation_size
    data = (random_rows(key, rows, row, spec.action_size), jnp.zeros((rows,), bool))
    full = jnp.full((), rows, jnp.int32)
    return replay.ReplayBuffer(jax.tree.map(lambda x: x[None], data), full[None] * 0, full[None])


def draw(spec, source, key, batch_size: int) -> Transition:
    """A batch: the fixed one, or ``batch_size`` rows sampled from the ring ``source``."""
    if isinstance(source, Transition):
        return source
    return agent_batch(spec, replay.sample_slices(source, key, batch_size, 1, 1, 0.99))


@functools.partial(jax.jit, static_argnums=(0, 4, 6, 7), donate_argnums=2)
def run_updates(spec, hp, state, source, n, key, batch_size, project_name):
    """``n`` updates in one scan; returns the state and the last critic loss. The C51
    projection ``project_name`` is a static argument, so each gets its own program."""

    def step(state, key):
        sample_key, update_key = jax.random.split(key)
        batch = draw(spec, source, sample_key, batch_size)
        return ac.update(spec, hp, state, batch, update_key)

    with projection(project_name):
        state, metrics = jax.lax.scan(step, state, jax.random.split(key, n))
    return state, metrics["critic_loss"][-1]


def agent_hyperparams(bound: float | None = None) -> ac.AgentHyperparams:
    settings = dict(discount=0.99, tau=0.005, actor_lr=3e-4, critic_lr=3e-4, policy_noise=0.2,
                    noise_clip=0.5, weight_decay=0.1, v_min=-10.0, v_max=10.0)  # fmt: skip
    if bound is not None:
        settings["max_weight_norm"] = bound
    return ac.AgentHyperparams(**{k: jnp.float32(v) for k, v in settings.items()})


def updates_per_second(spec, batch_size: int, args: argparse.Namespace, project_name: str) -> float:
    """Updates per second of the fastest of ``args.repeats`` timed calls; with
    ``args.profile``, a trace of one more call written there."""
    updates, ring = args.updates, args.ring
    bound = args.max_weight_norm if spec.options.bound_weights else None
    hp, key = agent_hyperparams(bound), jax.random.PRNGKey(0)
    state = jax.jit(functools.partial(ac.init, spec))(key)  # distinct buffers: donated
    row = spec.critic_observation_size or spec.observation_size
    source = (
        filled_ring(spec, ring, key)
        if ring
        else agent_batch(spec, random_rows(key, batch_size, row, spec.action_size))
    )
    run = functools.partial(run_updates, spec, hp, n=updates, batch_size=batch_size,
                            project_name=project_name)  # fmt: skip
    state, loss = run(state, source, key=key)  # compile + warm-up
    jax.block_until_ready(loss)
    best = float("inf")
    for i in range(args.repeats):
        start = time.perf_counter()
        state, loss = run(state, source, key=jax.random.PRNGKey(i + 1))
        jax.block_until_ready(loss)
        best = min(best, time.perf_counter() - start)
    if not jnp.isfinite(loss):
        raise RuntimeError(f"non-finite critic loss {float(loss)} for {spec.options}")
    if args.profile:
        with jax.profiler.trace(args.profile, create_perfetto_trace=True):
            jax.block_until_ready(run(state, source, key=jax.random.PRNGKey(99)))
    return updates / best


def shape(text: str) -> tuple[int, int | None, int]:
    sizes = [int(n) for n in text.lower().split("x")]
    if len(sizes) == 2:
        return sizes[0], None, sizes[1]
    return tuple(sizes)


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, help="directory for updates.csv/.jsonl")
    parser.add_argument("--batches", type=int, nargs="+", default=[8192, 32768])
    parser.add_argument("--shapes", type=shape, nargs="+", default=[(85, None, 12),
                        (180, None, 23)], help="OBSxACT or OBSxCRITICxACT sizes "
                        "(default: 85x12 180x23)")  # fmt: skip
    parser.add_argument("--critics", nargs="+", default=["plain", "distributional"])
    parser.add_argument("--precisions", nargs="+", default=["float32", "bfloat16"])
    parser.add_argument("--rules", nargs="+", default=["paper"], choices=sorted(RULES))
    parser.add_argument("--projections", nargs="+", default=["library"],
                        choices=["library", "einsum"])  # fmt: skip
    parser.add_argument(
        "--ring",
        type=int,
        default=0,
        help="rows of a ring to sample each batch from (0: a fixed batch)",
    )
    parser.add_argument("--updates", type=int, default=50, help="updates per timed call")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--layer-norm", action="store_true")
    parser.add_argument("--networks", nargs="+", default=["mlp"], choices=sorted(NETWORK_SIZES),
                        help="the critics' layout: mlp (1024-512-256) and/or residual (two "
                        "blocks of 256, the g1 preset's)")  # fmt: skip
    parser.add_argument("--actors", nargs="+", default=["mlp"], choices=sorted(ACTOR_SIZES),
                        help="the actor's layout: mlp (512-256-128) and/or residual (two "
                        "blocks of 128, FlashSAC's)")  # fmt: skip
    parser.add_argument(
        "--max-weight-norm",
        type=float,
        default=None,
        help="also time each combination with weights bounded to this norm",
    )
    parser.add_argument("--profile", default="", help="directory for a profiler trace of "
                        "each combination's last call (perfetto .json.gz)")  # fmt: skip
    args = parser.parse_args()
    if args.max_weight_norm is not None and not args.max_weight_norm > 0:
        parser.error(f"--max-weight-norm must be positive, not {args.max_weight_norm}")
    return args


def measure(args, combo: tuple) -> dict:
    shape_, batch, critic, network, actor, bound, precision, rules, proj = combo
    if proj != "library" and critic != "distributional":
        return {}
    spec = make_spec(critic, precision, shape_, args.layer_norm, rules, network, bound, actor)
    rate = updates_per_second(spec, batch, args, proj)
    return dict(critic=critic, network=network, actor=actor,
                bound=args.max_weight_norm if bound else "", precision=precision, batch=batch,
                shape="x".join(str(n) for n in shape_ if n), rules=rules, projection=proj,
                ring=args.ring, updates_per_s=round(rate, 2), ms_per_update=round(1000 / rate, 3),
                samples_per_s=round(rate * batch), device=jax.devices()[0].device_kind,
                jax=jax.__version__)  # fmt: skip


def main() -> None:
    args = parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    bounds = [False, True] if args.max_weight_norm is not None else [False]
    combos = itertools.product(args.shapes, args.batches, args.critics, args.networks,
                               args.actors, bounds, args.precisions, args.rules,
                               args.projections)  # fmt: skip
    print(" ".join(f"{c:>13}" for c in COLUMNS[:13]), flush=True)
    with (out / "updates.jsonl").open("w") as log:
        for combo in combos:
            row = measure(args, combo)
            if not row:
                continue
            rows.append(row)
            log.write(json.dumps(row) + "\n")
            print(" ".join(f"{row[c]!s:>13}" for c in COLUMNS[:13]), flush=True)
    with (out / "updates.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    print(f"wrote {out / 'updates.csv'} ({jax.devices()[0].device_kind})")


if __name__ == "__main__":
    main()
