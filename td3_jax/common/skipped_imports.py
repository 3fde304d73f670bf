"""Packages that td3-jax's dependencies import but td3-jax never uses, skipped while they import.

MuJoCo Playground imports PyTorch when it is imported, wherever PyTorch is installed, for its
wrappers to PyTorch trainers (RSL-RL): 3 s of each start of a Playground run on a GPU host with
PyTorch (docs/benchmarks.md, the T1 section's start-up). td3-jax imports Playground inside
:func:`skipping_unused_imports`, where ``import torch`` in that thread raises ``ImportError``
as if PyTorch were not installed; Playground then leaves its PyTorch wrappers without PyTorch,
as it does on a machine without it. Other threads, and every import afterwards, find PyTorch as
usual.

So, in a process where td3-jax imported Playground before anything imported PyTorch,
Playground's ``wrapper_torch`` cannot be used; import ``torch`` before td3-jax makes a
Playground environment to keep it.
"""

from __future__ import annotations

import contextlib
import importlib.abc
import sys
import threading
from collections.abc import Iterable, Iterator
from typing import Any

#: What importing Playground imports without td3-jax using it: PyTorch.
UNUSED_BY_TD3_JAX = ("torch",)

__all__ = ["UNUSED_BY_TD3_JAX", "skipping_unused_imports"]


class _Refusing(importlib.abc.MetaPathFinder):
    """Refuses the top-level packages ``names`` (and their submodules) to imports made in the
    thread ``thread``; leaves every other import to the finders after it."""

    def __init__(self, names: Iterable[str], thread: int) -> None:
        self.names, self.thread = frozenset(names), thread

    def find_spec(self, fullname: str, path: Any = None, target: Any = None) -> None:
        top = fullname.partition(".")[0]
        if (top in self.names and top not in sys.modules
                and threading.get_ident() == self.thread):  # fmt: skip
            raise ModuleNotFoundError(f"No module named {fullname!r} (skipped by td3-jax: "
                                      "not needed)", name=fullname)  # fmt: skip
        return None


@contextlib.contextmanager
def skipping_unused_imports(names: Iterable[str] = UNUSED_BY_TD3_JAX) -> Iterator[list[str]]:
    """Inside, importing any of the top-level packages ``names`` that is not imported yet
    raises ``ModuleNotFoundError`` in this thread; the names skipped. Nothing changes for other
    threads, nor for a package already imported, nor after leaving.

    Only for imports that handle a missing package (Playground's ``try: import torch``); a
    probe of one, ``importlib.util.find_spec("torch")``, raises the same error meanwhile (in
    this thread). Once another thread has imported the package, this one gets it too.
    """
    skipped = [name for name in names if name not in sys.modules]
    finder = _Refusing(skipped, threading.get_ident())
    sys.meta_path.insert(0, finder)
    try:
        yield skipped
    finally:
        sys.meta_path.remove(finder)
