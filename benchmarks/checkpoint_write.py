"""How long a checkpoint of a large train state holds the training loop up, written in the
foreground (``Checkpointer.save``) and in the background (``save(..., background=True)``, what
``td3-jax train`` does between chunks).

Usage::

    python -m benchmarks.checkpoint_write --gb 15.5 --dir /path/on/the/disk/to/measure

The state is one float32 ring of ``--gb`` gigabytes (filled with random values on the device,
like a replay buffer; G1's preset holds 15.5 GB) and a few small arrays. Prints one JSON line:
seconds the foreground save took, seconds until the background save returned (the device-to-host
copy), seconds until its write was complete (while a program donated and overwrote the saved
arrays, as the next chunk does), the restore (which verifies every array's checksum) and the
checkpoint's size on disk.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from td3_jax.runner.checkpoint import Checkpointer, state_bytes

ROW = 512  # floats per ring row


def make_state(gigabytes: float) -> dict:
    rows = int(gigabytes * 1e9 / (4 * ROW))
    ring = jax.jit(lambda key: jax.random.normal(key, (rows, ROW)))(jax.random.PRNGKey(0))
    small = {"params": jnp.ones((1024, 1024)), "step": jnp.zeros((), jnp.int32)}
    return jax.block_until_ready({"ring": ring, **small})


def timed(action) -> float:
    start = time.perf_counter()
    action()
    return round(time.perf_counter() - start, 2)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--gb", type=float, default=15.5)
    parser.add_argument("--dir", default=None, help="where to write (default: a temporary folder)")
    args = parser.parse_args()
    root = Path(args.dir or tempfile.mkdtemp(prefix="ckpt-bench-"))
    state = make_state(args.gb)
    abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), state)
    out = {"state_gb": round(state_bytes(state) / 1e9, 2), "device": jax.devices()[0].device_kind,
           "free_gb_before": round(shutil.disk_usage(root.parent).free / 1e9, 1)}  # fmt: skip
    ckpt = Checkpointer(root / "checkpoints", keep=1)
    out["foreground_save_s"] = timed(lambda: ckpt.save(1, state, {}))
    files = [p for p in (root / "checkpoints" / "1").rglob("*") if p.is_file()]
    out["size_on_disk_gb"] = round(sum(p.stat().st_size for p in files) / 1e9, 2)
    ring_sum = float(jnp.sum(state["ring"]))
    out["background_save_returned_s"] = timed(lambda: ckpt.save(2, state, {}, background=True))
    # As the training loop does: the next program takes the saved arrays over (donates them)
    # and overwrites them while the write goes on. The restore checks every array's checksum
    # (taken before the save), so a checkpoint holding overwritten values fails it.
    overwrite = jax.jit(lambda tree: jax.tree.map(lambda x: x - x, tree), donate_argnums=0)
    jax.block_until_ready(overwrite(state))
    out["saved_arrays_donated"] = all(x.is_deleted() for x in jax.tree.leaves(state))
    out["background_write_left_s"] = timed(ckpt.wait)
    restored = {}
    out["restore_s"] = timed(lambda: restored.update(ckpt.restore(abstract)[0]))
    out["restored_ring_as_saved"] = float(jnp.sum(restored["ring"])) == ring_sum
    ckpt.close()
    shutil.rmtree(root / "checkpoints", ignore_errors=True)
    print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
