"""The GPU kernels of a JAX profiler trace by total time, and the matmuls' share.

Reads a ``perfetto_trace.json.gz`` that ``jax.profiler.trace(..., create_perfetto_trace=True)``
wrote (e.g. ``python -m benchmarks.updates --profile DIR``: one per combination, in
``DIR/plugins/profile/<time>/``) and prints, for the events of the device processes (those
named ``/device:...``, e.g. ``/device:GPU:0``; memory copies on their streams count as
"other"): the time of every stream, the time of the matrix products
(cuBLAS/cuBLASLt kernels: ``nvjet``, ``gemm``, ``xmma``, ``cutlass`` in their names) against
everything else (XLA's fused elementwise and reduction kernels), and the ``--top`` kernels.

    python -m benchmarks.trace_top [--top 25] TRACE...
"""

from __future__ import annotations

import argparse
import collections
import gzip
import json

MATMUL_MARKS = ("nvjet", "gemm", "xmma", "cutlass")


def is_matmul(kernel: str) -> bool:
    """Whether ``kernel`` (a GPU kernel's name) is a matrix product's."""
    name = kernel.lower()
    return any(mark in name for mark in MATMUL_MARKS)


def device_kernels(events: list[dict]) -> tuple[collections.Counter, collections.Counter, dict]:
    """``(microseconds by kernel, calls by kernel, microseconds by stream)`` of the complete
    events (``ph == "X"``) of the processes named ``/device:...``."""
    meta = [e for e in events if e.get("ph") == "M"]
    threads = {
        (e["pid"], e.get("tid")): e.get("args", {}).get("name", "")
        for e in meta
        if e.get("name") == "thread_name"
    }
    devices = {
        e["pid"]
        for e in meta
        if e.get("name") == "process_name"
        and e.get("args", {}).get("name", "").startswith("/device")
    }
    time, calls, streams = collections.Counter(), collections.Counter(), collections.Counter()
    for e in events:
        if e.get("ph") == "X" and e["pid"] in devices:
            time[e["name"]] += e.get("dur", 0)
            calls[e["name"]] += 1
            streams[threads.get((e["pid"], e.get("tid")), "?")] += e.get("dur", 0)
    return time, calls, dict(streams)


def report(path: str, top: int) -> None:
    """Print the summary of one trace file."""
    with gzip.open(path) as f:
        trace = json.load(f)
    events = trace["traceEvents"] if isinstance(trace, dict) else trace
    time, calls, streams = device_kernels(events)
    total = sum(time.values())
    matmuls = sum(t for name, t in time.items() if is_matmul(name))
    print(f"== {path}")
    for stream, t in sorted(streams.items(), key=lambda kv: -kv[1]):
        print(f"   stream {stream}: {t / 1e3:.1f} ms")
    share = 100 * matmuls / max(total, 1)
    print(
        f"   kernels {total / 1e3:.1f} ms: matmuls {matmuls / 1e3:.1f} ms ({share:.0f}%), "
        f"other {(total - matmuls) / 1e3:.1f} ms"
    )
    for name, t in time.most_common(top):
        kind = "matmul" if is_matmul(name) else "other "
        print(f"   {t / 1e3:9.2f} ms {calls[name]:6d} {kind} {name[:100]}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("traces", nargs="+", help="perfetto_trace.json.gz files")
    parser.add_argument("--top", type=int, default=25, help="kernels to list (by total time)")
    args = parser.parse_args()
    for path in args.traces:
        report(path, args.top)


if __name__ == "__main__":
    main()
