"""One of two processes that train one td3-jax run together from Python, joined through
``jax.distributed``: each process steps half the environments and samples half of each batch
from its own half of the replay ring (``replay_shards=2``), and the gradients are averaged.

Start both, in one folder (on a GPU host, each with its own ``CUDA_VISIBLE_DEVICES``; on a CPU,
``JAX_PLATFORMS=cpu``)::

    python examples/two_processes.py --process-id 0
    python examples/two_processes.py --process-id 1

``td3-jax train ... --local-processes 2`` does the same from the command line, and more: for
MJX and Playground environments it places each process's models on its own devices, and a
Ctrl-C stops both together (guides/multi-gpu.md).
"""

from __future__ import annotations

import argparse

import jax

import td3_jax as tj
from td3_jax.common.errors import Td3JaxError


def train(process_id: int, coordinator: str, out: str, total_steps: int) -> list[dict]:
    """This process's side of the run: join, train, leave. Returns the run's records (the
    same in both processes)."""
    jax.distributed.initialize(coordinator, num_processes=2, process_id=process_id)
    try:
        cfg = tj.TrainConfig(env="gymnax/Pendulum-v1", replay_shards=2, total_steps=total_steps)
        return tj.train(cfg, out, progress=process_id == 0)
    finally:
        jax.distributed.shutdown()  # waits for the other: neither ends under the other's call


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--process-id", type=int, choices=(0, 1), required=True)
    parser.add_argument("--coordinator", default="localhost:12355", help="HOST:PORT of process 0")
    parser.add_argument("--out", default="runs/pendulum-two-processes")
    parser.add_argument("--total-steps", type=int, default=20_000)
    args = parser.parse_args()
    try:
        records = train(args.process_id, args.coordinator, args.out, args.total_steps)
    except Td3JaxError as err:  # a refusal (an --out that holds a run), the other one failed, ...
        raise SystemExit(f"process {args.process_id}: {err}") from None
    print(f"process {args.process_id}: eval return {records[-1]['eval_return_mean']:.1f}")


if __name__ == "__main__":
    main()
