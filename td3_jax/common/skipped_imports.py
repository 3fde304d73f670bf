"""Packages that td3-jax's dependencies import but td3-jax never uses, skipped while they import.

MuJoCo Playground imports PyTorch when it is imported, wherever PyTorch is installed, for its
wrappers to PyTorch trainers (RSL-RL): 3 s of each start of a Playground run on a GPU host with
PyTorch (docs/benchmarks.md, the T1 section's start-up). td3-jax imports Playground inside
:func:`skipping_unused_imports`, where ``import torch`` raises ``ImportError`` as if PyTorch were
not installed; Playground then leaves its PyTorch wrappers without PyTorch, as it does on a
machine without it. Afterwards ``import torch`` works as before, anywhere in the process.

So, in a process where td3-jax imported Playground before anything imported PyTorch,
Playground's ``wrapper_torch`` cannot be used; import ``torch`` before td3-jax makes a
Playground environment to keep it.
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterable, Iterator

#: What importing Playground imports without td3-jax using it: PyTorch.
UNUSED_BY_TD3_JAX = ("torch",)

__all__ = ["UNUSED_BY_TD3_JAX", "skipping_unused_imports"]


@contextlib.contextmanager
def skipping_unused_imports(names: Iterable[str] = UNUSED_BY_TD3_JAX) -> Iterator[list[str]]:
    """Inside, importing any of the top-level packages ``names`` that is not imported yet
    raises ``ImportError`` (``sys.modules[name] = None``); the names skipped. On leaving,
    those entries are removed again, so later imports find the packages as usual.

    Only for imports that handle a missing package (Playground's ``try: import torch``). Other
    threads importing one of ``names`` meanwhile would get the error too; td3-jax imports
    Playground before it starts any thread that could.
    """
    skipped = [name for name in names if name not in sys.modules]
    for name in skipped:
        sys.modules[name] = None
    try:
        yield skipped
    finally:
        for name in skipped:
            if name in sys.modules and sys.modules[name] is None:
                del sys.modules[name]
