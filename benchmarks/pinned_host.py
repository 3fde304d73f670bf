"""Whether allocating pinned host memory on a thread holds up a device loop running beside it.

On a GPU orbax copies a checkpoint's arrays into pinned host memory. The first time, the CUDA
driver pins that memory: about 6 s for T1's 11 GB state, the pause after a run's first chunk
(docs/benchmarks.md). This measures whether that allocation could run beside a chunk instead.
Usage (a fresh process each time: JAX keeps the pinned memory it allocated)::

    python -m benchmarks.pinned_host --gb 3 3 2 2 1 --matrix 8192 --iterations 2500 [--callback]

The loop is an XLA while loop whose trip count is an argument, as a training chunk's is, so the
host reads its condition every iteration: ``--iterations`` products of a bfloat16 ``--matrix``
square matrix, and with ``--callback`` a host callback in every iteration, as MuJoCo Warp's
steps are. It runs alone, then beside a thread that puts NumPy zeros of the ``--gb`` sizes in
pinned host memory and frees them (the first allocation), then alone again, then beside a
second allocation of the same sizes (which JAX serves from the memory it kept). Beside an
allocation, the seconds until the loop's call began and returned are given too (a call that
began late waited for Python's interpreter lock). Prints one JSON line of seconds.
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


def loop(callback: bool) -> Callable[[jax.Array, jax.Array], jax.Array]:
    """The jitted loop ``y <- tanh(y @ y) / 2`` on ``[n, n]``, ``iterations`` times (an
    argument, so XLA does not know the trip count and reads the condition each iteration)."""

    def body(carry: tuple) -> tuple:
        i, y = carry
        y = jnp.tanh(y @ y) * 0.5
        if callback:
            io_callback(lambda _: None, None, i, ordered=False)
        return i + 1, y

    def run(x: jax.Array, iterations: jax.Array) -> jax.Array:
        return jax.lax.while_loop(lambda c: c[0] < iterations, body, (jnp.int32(0), x))[1]

    return jax.jit(run)


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


def timed_beside(run: Callable[[], object], work: Callable[[], float]) -> dict[str, float]:
    """``run()`` beside ``work()`` on a thread started first: seconds from the thread's start
    until the call of ``run`` began (``call_began_s``), returned (``call_returned_s``) and its
    result was ready (``loop_s``), and the seconds ``work`` reported (``work_s``); an error of
    ``work`` is raised here."""
    result: list[float] = []
    failed: list[BaseException] = []

    def guarded() -> None:
        try:
            result.append(work())
        except BaseException as err:  # (raised on the main thread below)
            failed.append(err)

    thread = threading.Thread(target=guarded)
    start = time.perf_counter()
    thread.start()
    began = time.perf_counter() - start
    out = run()
    returned = time.perf_counter() - start
    jax.block_until_ready(out)
    seconds = time.perf_counter() - start
    thread.join()
    if failed:
        raise failed[0]
    return {"call_began_s": began, "call_returned_s": returned, "loop_s": seconds,
            "work_s": result[0]}  # fmt: skip


def measure(sizes: list[int], matrix: int, iterations: int, callback: bool) -> dict:
    """The loop's seconds alone and beside each allocation, with the allocations' seconds."""
    device = jax.devices()[0]
    x = jnp.full((matrix, matrix), 0.01, jnp.bfloat16, device=device)
    n = jnp.int32(iterations)
    f = loop(callback)
    jax.block_until_ready(f(x, n))  # (compiled)

    def alone() -> float:
        start = time.perf_counter()
        jax.block_until_ready(f(x, n))
        return time.perf_counter() - start

    out: dict = {"device": device.device_kind, "callback": callback, "gb": sum(sizes) / 1e9}
    out["loop_alone_s"] = alone()
    for which in ("first", "second"):
        if which == "second":
            out["loop_alone_again_s"] = alone()
        timed = timed_beside(lambda: f(x, n), lambda: allocate_and_free(sizes, device))
        out.update({f"{which}_allocation_s": timed.pop("work_s"),
                    **{f"{which}_{k}": v for k, v in timed.items()}})  # fmt: skip
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
