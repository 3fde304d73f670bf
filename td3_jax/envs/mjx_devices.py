"""MJX on the local devices of a multi-process run.

MJX's ``put_model``/``make_data``/``put_data`` place their arrays on ``jax.devices()[0]`` when no
device is given. With several processes (``jax.distributed``) that is process 0's first device,
which no other process can address: a Brax or Playground environment made there holds (and its
traced step closes over) arrays that process 1 cannot lower ("Closing over jax.Array that spans
non-addressable devices"). :func:`place_on_local_devices` makes MJX choose this process's first
device of the same platform instead; with one process nothing changes.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax

from td3_jax.common import upstream

__all__ = ["local_device", "place_on_local_devices", "with_local_default"]

_MARK = "_td3_jax_local_devices"


def local_device(device: Any) -> Any:
    """``device`` when this process can address it, else this process's first device of the
    same platform (``device`` itself when this process has none of that platform)."""
    if device in jax.local_devices():
        return device
    try:
        same_platform = jax.local_devices(backend=device.platform)
    except RuntimeError:  # no such backend here
        return device
    return same_platform[0] if same_platform else device


def with_local_default(resolve: Callable[..., tuple[Any, Any]]) -> Callable[..., tuple[Any, Any]]:
    """Wraps MJX's ``_resolve_impl_and_device(impl, device) -> (impl, device)`` so a device it
    picks by default is a local one; an explicit ``device`` is kept as given."""

    @functools.wraps(resolve)
    def resolve_locally(impl=None, device=None):
        chosen_impl, chosen = resolve(impl, device)
        return chosen_impl, chosen if device is not None else local_device(chosen)

    setattr(resolve_locally, _MARK, True)
    return resolve_locally


def place_on_local_devices() -> bool:
    """Makes MJX's default device this process's own (idempotent). Returns whether MJX was
    found and adjusted (``False``: MJX is not installed); call it after
    ``jax.distributed.initialize`` and before making environments. An MJX without the function
    wrapped raises :class:`td3_jax.common.upstream.UpstreamChanged` rather than leaving it alone."""
    from td3_jax.envs.physics import import_mjx_quietly

    import_mjx_quietly()  # (first here in a gymnax run: without MJX's notes on a missing Warp)
    resolve = upstream.mjx_device_resolver()
    if resolve is None:  # MJX not installed: gymnax environments only
        return False
    if not getattr(resolve, _MARK, False):
        upstream.set_mjx_device_resolver(with_local_default(resolve))
    return True
