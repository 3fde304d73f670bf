"""How td3-jax speaks on stderr: ``td3-jax: warning: ...`` for what works but likely
surprises, ``td3-jax: error: ...`` for what stops a command (one line each)."""

from __future__ import annotations

import sys

__all__ = ["error", "warn"]


def warn(warning: str) -> None:
    """Prints ``warning`` to stderr as ``td3-jax: warning: WARNING``, at once."""
    print(f"td3-jax: warning: {warning}", file=sys.stderr, flush=True)


def error(message: str) -> None:
    """Prints ``message`` to stderr as ``td3-jax: error: MESSAGE``."""
    print(f"td3-jax: error: {message}", file=sys.stderr)
