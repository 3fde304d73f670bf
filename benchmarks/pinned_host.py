"""Whether allocating pinned host memory on a thread holds up a device loop running beside it.

On a GPU orbax copies a checkpoint's arrays into pinned host memory, and the first time the
CUDA driver pins that memory (about 6 s for T1's 11 GB state: the pause after a run's first
chunk, docs/benchmarks.md). This measures whether that allocation could run beside a chunk
instead. Usage (a fresh process each time: JAX keeps the pinned memory it allocated)::

    python -m benchmarks.pinned_host --gb 3 3 2 2 1 --matrix 8192 --iterations 2500 [--callback]

The loop is an XLA while loop, as a training chunk is (the host reads its condition every
iteration): ``--iterations`` products of a bfloat16 ``--matrix`` square matrix, and with
``--callback`` a host callback in every iteration, as MuJoCo Warp's steps are. It runs alone,
then beside a thread that puts NumPy zeros of the ``--gb`` sizes in pinned host memory and frees
them (the first allocation), then alone again, then beside a second allocation of the same
sizes (which JAX serves from the memory it kept). Prints one JSON line of seconds.
"""

from __future__ import annotations

import argparse
import json
import threading
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import io_callback
from jax.sharding import SingleDeviceSharding


def loop(iterations: int, callback: bool) -> Callable[[jax.Array], jax.Array]:
    """The jitted loop ``y <- tanh(y @ y) / 2``, ``iterations`` times, on ``[n, n]``."""

    def body(carry: tuple) -> tuple:
        i, y = carry
        y = jnp.tanh(y @ y) * 0.5
        if callback:
            io_callback(lambda _: None, None, i, ordered=False)
        return i + 1, y

    return jax.jit(lambda x: jax.lax.while_loop(lambda c: c[0] < iterations, body, (0, x))[1])


def allocate_and_free(sizes: list[int], device: jax.Device) -> float:
    """Seconds to place zeros of ``sizes`` bytes (float32) in ``device``'s pinned host memory,
    all held at once; then frees them."""
    pinned = SingleDeviceSharding(device, memory_kind="pinned_host")
    start = time.perf_counter()
    held = [jax.device_put(np.zeros(size // 4, np.float32), pinned) for size in sizes]
    jax.block_until_ready(held)
    seconds = time.perf_counter() - start
    for array in held:
        array.delete()
    return seconds


def timed_beside(run: Callable[[], object], work: Callable[[], float]) -> tuple[float, float]:
    """``(seconds of run(), seconds work() reported)``, ``work`` on a thread started first."""
    result: list[float] = []
    thread = threading.Thread(target=lambda: result.append(work()))
    start = time.perf_counter()
    thread.start()
    jax.block_until_ready(run())
    seconds = time.perf_counter() - start
    thread.join()
    return seconds, result[0]


def measure(sizes: list[int], matrix: int, iterations: int, callback: bool) -> dict:
    """The loop's seconds alone and beside each allocation, with the allocations' seconds."""
    device = jax.devices()[0]
    x = jnp.full((matrix, matrix), 0.01, jnp.bfloat16, device=device)
    f = loop(iterations, callback)
    jax.block_until_ready(f(x))  # (compiled)

    def alone() -> float:
        start = time.perf_counter()
        jax.block_until_ready(f(x))
        return time.perf_counter() - start

    out = {"device": device.device_kind, "callback": callback, "gb": sum(sizes) / 1e9}
    out["loop_alone_s"] = alone()
    out["loop_beside_first_s"], out["first_allocation_s"] = timed_beside(
        lambda: f(x), lambda: allocate_and_free(sizes, device))
    out["loop_alone_again_s"] = alone()
    out["loop_beside_second_s"], out["second_allocation_s"] = timed_beside(
        lambda: f(x), lambda: allocate_and_free(sizes, device))
    return {k: round(v, 3) if k.endswith("_s") else v for k, v in out.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--gb", type=float, nargs="+", default=[3, 3, 2, 2, 1],
                        help="the pinned buffers' sizes in GB, held at once")
    parser.add_argument("--matrix", type=int, default=8192)
    parser.add_argument("--iterations", type=int, default=2500)
    parser.add_argument("--callback", action="store_true",
                        help="a host callback in every iteration of the loop")
    args = parser.parse_args()
    sizes = [int(gb * 1e9) for gb in args.gb]
    print(json.dumps(measure(sizes, args.matrix, args.iterations, args.callback)), flush=True)


if __name__ == "__main__":
    main()
