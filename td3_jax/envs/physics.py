"""Which physics steps MuJoCo Playground's tasks: MJX's JAX implementation or MuJoCo Warp.

MuJoCo Warp (MJX's ``impl="warp"``, Playground's default since 0.2.0) runs the robots several
times faster than the JAX implementation on an NVIDIA GPU and compiles far less XLA. It needs
the ``warp`` package (``pip install 'td3-jax[warp]'``) and an NVIDIA GPU (CUDA).
:func:`warp_missing` only looks for it; :func:`import_mjx_quietly` imports MJX (and with it
Warp, where installed) without the notes MJX prints where Warp is missing.

Warp keeps some of its data once for all the environments stepped together (contacts,
counters): those leaves carry no batch axis (:func:`td3_jax.envs.base.reset_ended` leaves them
alone), and its contact buffer is sized for all of them (:func:`contact_capacity`).
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import io
import sys
from collections.abc import Iterator
from typing import Any

from td3_jax.common import runtime, upstream

__all__ = [
    "IMPLS",
    "PLAYGROUND_WORLDS",
    "WARP_ON_CPU",
    "WRONG_PHYSICS",
    "contact_capacity",
    "default_impl",
    "import_mjx_quietly",
    "quiet_solver_limits",
    "resolve",
    "warp_missing",
    "without_warp_import_notes",
]

IMPLS = ("warp", "jax")
#: Set to 1, MuJoCo Warp may run on its CPU kernels (slow; for the tests of the Warp path on
#: machines without a GPU). Without it, Warp needs an NVIDIA GPU.
WARP_ON_CPU = "TD3_JAX_WARP_ON_CPU"
#: Playground's tasks size Warp's contact buffer for this many environments (``naconmax`` in
#: their configs is per-environment contacts times 8192).
PLAYGROUND_WORLDS = 8192


#: MuJoCo Warp's overflow flags (its ``OverflowType``) that mean dropped contacts, constraints
#: or collision pairs, i.e. wrong physics: all but the solver's and line search's iteration
#: limits (bits 9 and 10), which Playground's tasks reach by design (few iterations). Checked
#: against Warp's own flags by ``tests/common/test_upstream.py``.
WRONG_PHYSICS = (1 << 9) - 1 | (1 << 11)
_ITERATION_LIMITS = (1 << 9) | (1 << 10)


def quiet_solver_limits(task: Any) -> None:
    """Stops MuJoCo Warp from printing a warning at every step where the solver or the line
    search reached its iteration limit (Playground's tasks use few iterations on purpose);
    its warnings of real overflows stay. ``task``: a Playground task on Warp."""
    upstream.quiet_warp_overflow_warnings(task, _ITERATION_LIMITS)
    import warp

    warp.config.log_level = warp.LOG_WARNING  # no line per kernel module loaded or compiled


def warp_missing() -> str | None:
    """Why MuJoCo Warp cannot run here (what to install, or the hardware it needs), or
    ``None`` when it can."""
    if importlib.util.find_spec("warp") is None:
        return "MuJoCo Warp is not installed (pip install 'td3-jax[warp]')"
    import jax

    device = jax.devices()[0]
    version = str(getattr(getattr(device, "client", None), "platform_version", "")).lower()
    on_cpu = device.platform == "cpu" and runtime.env_switch(WARP_ON_CPU) is True
    if not on_cpu and (device.platform != "gpu" or "cuda" not in version):
        slowly = f"; {WARP_ON_CPU}=1 runs its CPU kernels, slowly" * (device.platform == "cpu")
        here = f"JAX's default device here is {device.platform}{slowly}"
        return f"MuJoCo Warp needs an NVIDIA GPU ({here})"
    return None


def default_impl() -> str:
    """``warp`` where it can run (:func:`warp_missing`), else ``jax``."""
    return "jax" if warp_missing() else "warp"


def resolve(impl: str | None) -> str:
    """The physics for ``impl`` (``None``: :func:`default_impl`); ``ValueError`` naming what is
    missing when ``warp`` is asked for where it cannot run, or for an unknown name."""
    if impl is None:
        return default_impl()
    if impl not in IMPLS:
        raise ValueError(f"unknown --impl {impl!r}; choose warp or jax")
    missing = warp_missing() if impl == "warp" else None
    if missing:
        raise ValueError(f"--impl warp: {missing}; or use --impl jax")
    return impl


def contact_capacity(task_naconmax: int, worlds: int, per_world: int | None) -> int:
    """Warp's contact buffer (shared by all the environments stepped together): ``per_world``
    contacts for each of ``worlds`` environments; by default the task's own share (its
    ``naconmax`` spread over Playground's 8192 environments) and never less than its
    ``naconmax``."""
    if per_world:
        return per_world * max(worlds, 1)
    return max(task_naconmax, max(1, task_naconmax // PLAYGROUND_WORLDS) * max(worlds, 1))


#: The lines MJX prints when first imported where MuJoCo Warp is not installed (JAX physics is
#: used then: nothing failed).
WARP_IMPORT_NOTES = ("Failed to import warp:", "Failed to import mujoco_warp:")


class _WithoutNotes(io.TextIOBase):
    """A text stream that passes each line written to ``stream`` as soon as it ends, less the
    lines starting with :data:`WARP_IMPORT_NOTES`."""

    def __init__(self, stream: Any):
        self.stream, self.pending = stream, ""

    def writable(self) -> bool:
        return True

    def write(self, text: str) -> int:
        lines = (self.pending + text).splitlines(True)
        self.pending = lines.pop() if lines and not lines[-1].endswith("\n") else ""
        self.stream.write("".join(x for x in lines if not x.startswith(WARP_IMPORT_NOTES)))
        return len(text)

    def flush(self) -> None:
        """Passes a flushed partial line (a ``\r`` progress bar) unless it may begin a note."""
        notes = WARP_IMPORT_NOTES
        if self.pending and not any(n.startswith(self.pending[: len(n)]) for n in notes):
            self.stream.write(self.pending)
            self.pending = ""
        self.stream.flush()


@contextlib.contextmanager
def without_warp_import_notes() -> Iterator[None]:
    """Drops MJX's :data:`WARP_IMPORT_NOTES` from what is printed inside; every other line
    passes as soon as it is written (no standard output: nothing to filter)."""
    if sys.stdout is None:
        yield
        return
    filtered = _WithoutNotes(sys.stdout)
    try:
        with contextlib.redirect_stdout(filtered):
            yield
    finally:
        if filtered.pending and not filtered.pending.startswith(WARP_IMPORT_NOTES):
            filtered.stream.write(filtered.pending)  # (a last line without its newline)


def import_mjx_quietly() -> bool:
    """Imports MuJoCo MJX (seconds, the first time) without its notes about a missing Warp;
    whether it is installed. Call it before anything else imports MJX (Brax, Playground)."""
    if "mujoco.mjx" in sys.modules:  # (imported: no need to catch the output of other threads)
        return True
    with without_warp_import_notes():
        try:
            importlib.import_module("mujoco.mjx")
        except ImportError:  # no MuJoCo: the environments that need it say so when made
            return False
    return True
