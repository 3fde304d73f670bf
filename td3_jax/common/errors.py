"""Every error td3-jax raises on purpose, in one hierarchy.

Each carries the exit code the command line ends with when it reaches it (``exit_code``): 2
for bad input (a setting, a name, a file, a checkpoint, a full disk), 3 for a run stopped
because training or its physics went wrong, 1 for an upstream library that changed under
td3-jax. The message is one line saying what happened and what to do. The defining modules
re-export their own (``td3_jax.config.schema.ConfigError`` is
``td3_jax.common.errors.ConfigError``), except :class:`td3_jax.tools.policy_file.PolicyFileError`,
which stays in that NumPy-only file.
"""

from __future__ import annotations

import difflib
import errno
import sys
from collections.abc import Sequence


class Td3JaxError(Exception):
    """The base of td3-jax's own errors."""

    exit_code = 2


class ConfigError(Td3JaxError, ValueError):
    """A setting that cannot work."""


class LockUnavailableError(ConfigError):
    """A run directory whose lock its file system refuses (not one another run holds)."""


class ExportError(ConfigError):
    """A run, member or output that cannot be exported."""


class RenderError(ConfigError):
    """A rollout that cannot be rendered."""


class GLUnavailableError(RenderError):
    """No headless OpenGL context can be created."""


class NotRenderableError(RenderError):
    """An environment without a scene to draw."""


class UnknownEnvironmentError(Td3JaxError, ValueError):
    """An environment name that no source knows; the message names the closest known ones
    (when none is close: how names are written, and ``td3-jax envs`` to list them)."""


class EnvironmentOptionError(Td3JaxError, ValueError):
    """An option a task cannot take."""


class MissingAssetsError(Td3JaxError, ValueError):
    """No searched place holds a task's robot folder."""


class CustomEnvironmentError(Td3JaxError, ValueError):
    """An environment of your own (an object, or ``--env module.path:factory``) that td3-jax
    cannot use: a factory that cannot be found or fails, an object of an unknown kind, or an
    environment whose reset or step does not meet :mod:`td3_jax.envs.custom`'s contract."""


class CheckpointError(Td3JaxError, RuntimeError):
    """A checkpoint that is missing, corrupt or does not match the run's configuration."""


class CorruptCheckpointError(CheckpointError):
    """A checkpoint that cannot be read, or whose arrays fail their checksums."""


class CheckpointWriteError(CheckpointError):
    """A checkpoint that could not be written (a full disk, no permission); none of it is left."""


class OutputWriteError(Td3JaxError, RuntimeError):
    """A run stopped because one of its outputs could not be written (a full disk); the
    message names it, the last good checkpoint and how to go on."""


class WandbError(Td3JaxError, RuntimeError):
    """Weights & Biases cannot be used for a run (``--wandb``): the package is missing, online
    mode has no login, or its run cannot start; said before anything compiles."""


class TrainingStopped(Td3JaxError, RuntimeError):
    """A run stopped because what it computed went wrong, or because another process of a
    several-process run did; its last good checkpoint is kept."""

    exit_code = 3


class NonFiniteError(TrainingStopped):
    """A loss or parameter became NaN/inf."""


class PhysicsOverflowError(TrainingStopped):
    """MuJoCo Warp ran out of contact or constraint buffer (its physics was wrong)."""


class ProcessLostError(TrainingStopped):
    """Another process of a several-process run never reached the chunk boundary this one
    waited at (it stopped, or hangs)."""


class UpstreamChanged(Td3JaxError, RuntimeError):
    """An upstream library no longer has a private name td3-jax relies on
    (:mod:`td3_jax.common.upstream`)."""

    exit_code = 1


#: The errors of a write that the system refused: a full disk, a quota, a read-only file
#: system, no permission (EPERM: an immutable file, some network or FUSE mounts). Each is one
#: line naming the file and exit 2 at the command line, and stops a run keeping its last
#: good checkpoint.
WRITE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM)


__all__ = [
    "WRITE_ERRNOS",
    "CheckpointError",
    "CheckpointWriteError",
    "ConfigError",
    "CorruptCheckpointError",
    "CustomEnvironmentError",
    "EnvironmentOptionError",
    "ExportError",
    "GLUnavailableError",
    "LockUnavailableError",
    "MissingAssetsError",
    "NonFiniteError",
    "NotRenderableError",
    "OutputWriteError",
    "PhysicsOverflowError",
    "ProcessLostError",
    "RenderError",
    "Td3JaxError",
    "TrainingStopped",
    "UnknownEnvironmentError",
    "UpstreamChanged",
    "WandbError",
    "did_you_mean",
    "in_td3_jax",
    "outside_stacklevel",
]


def in_td3_jax(module: str) -> bool:
    """Whether the module named ``module`` is td3-jax's own (not ``td3_jax_experiments``)."""
    return module == "td3_jax" or module.startswith("td3_jax.")


def outside_stacklevel() -> int:
    """The ``stacklevel`` of a warning from the calling function that points at the first
    caller outside td3-jax (the line of the user's ``td3_jax.train(...)``)."""
    frame, level = sys._getframe(1), 1
    while frame.f_back is not None and in_td3_jax(frame.f_globals.get("__name__", "")):
        frame, level = frame.f_back, level + 1
    return level


def did_you_mean(word: str, names: Sequence[str]) -> str:
    """``; did you mean 'name'?``, the end of a one-line error, for the name of ``names``
    closest to ``word`` (case aside; dotted names compared by their last part, those of
    ``word`` and of each name alike), else ``""``."""
    last = word.rpartition(".")[2]
    lowered = {name.rpartition(".")[2].lower(): name for name in names}
    close = difflib.get_close_matches(last.lower(), list(lowered), n=1)
    return f"; did you mean {lowered[close[0]]!r}?" if close else ""
