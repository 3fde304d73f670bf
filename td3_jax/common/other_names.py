"""The settings a name not td3-jax's most likely means: another library's name for one
(``gamma``: ``discount``), the end of ours (``lr``: ``actor-lr`` and ``critic-lr``), or the
closest spelling. The command line offers them for an unknown flag, the config classes
(:func:`~td3_jax.common.keywords.keywords_named`) for an unknown keyword."""

from __future__ import annotations

import difflib
from collections.abc import Iterable

__all__ = ["OTHER_NAMES", "names_meant"]

#: Other libraries' names for td3-jax's settings (CleanRL, Stable-Baselines3, FastTD3), as flags
#: without their dashes: ``gamma`` is ``discount``.
OTHER_NAMES = {
    "gamma": ("discount",),
    "env-name": ("env",),
    "actor-learning-rate": ("actor-lr",),
    "critic-learning-rate": ("critic-lr",),
    "num-steps": ("n-step",),
    "use-wandb": ("wandb",),
    "learning-starts": ("warmup-steps",),
    "learning-rate": ("actor-lr", "critic-lr"),
    "total-timesteps": ("total-steps",),
    "n-envs": ("num-envs",),
    "env-id": ("env",),
    "policy-frequency": ("policy-freq",),
    "policy-delay": ("policy-freq",),
    "target-policy-noise": ("policy-noise",),
    "target-noise-clip": ("noise-clip",),
    "exploration-noise": ("expl-noise",),
    "action-noise": ("expl-noise",),
    "gradient-steps": ("updates-per-iter",),
    "num-updates": ("updates-per-iter",),
    "std-min": ("expl-noise-min",),
    "std-max": ("expl-noise-max",),
    "num-eval-envs": ("eval-envs",),
    "eval-freq": ("eval-every",),
    "eval-interval": ("eval-every",),
    "track": ("wandb",),
    "wandb-project-name": ("wandb-project",),
}


def names_meant(bare: str, names: Iterable[str]) -> list[str]:
    """The names among ``names`` (flags without their dashes: ``actor-lr``) that ``bare`` most
    likely means: by another library's name (``gamma``: ``discount``) or as the end of ours
    (``lr``: ``actor-lr``, ``critic-lr``), each also under ``sweep-`` (``sweep-gamma``:
    ``sweep-discount``); else the one closest in spelling; ``[]``: none close."""
    names = list(names)
    stem = bare.removeprefix("sweep-")
    prefix = bare[: len(bare) - len(stem)]
    other = [prefix + n for n in OTHER_NAMES.get(stem.replace("_", "-"), ())]
    ours = [n for n in other if n in names]
    ends = sorted(n for n in names if n.startswith(prefix) and n.endswith("-" + stem)
                  and not n.startswith("no-") and n != bare)  # fmt: skip
    return ours or ends or difflib.get_close_matches(bare, names, n=1, cutoff=0.7)
