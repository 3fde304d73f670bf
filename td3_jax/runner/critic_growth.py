"""A warning when the critics' loss grows without bound over several evaluations.

TD3's critics regress on targets built from their own estimates; where those targets run away
(rewards far from unit scale, a discount near 1 over long episodes, too little exploration for
the critics to see what their targets claim), the loss does not settle but keeps multiplying,
and the policy, which follows the critics, learns little meanwhile. Nothing stops such a run:
the losses stay finite for a long time. The host loop says so once
(:func:`growth_warning`), naming what to look at.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from itertools import pairwise
from typing import Any

#: Evaluations in a row at each of which the critic loss at least doubled.
GROWTH_EVALUATIONS = 3
#: How much the loss grows at each of them: at least this factor.
GROWTH_FACTOR = 2.0
#: The loss the last of them exceeds (a loss of rewards of unit scale stays far below).
GROWTH_FLOOR = 1e3


def growing_without_bound(losses: Sequence[float]) -> bool:
    """Whether the last :data:`GROWTH_EVALUATIONS` of ``losses`` (one per evaluation, oldest
    first) each at least doubled the one before it (:data:`GROWTH_FACTOR`) and the last exceeds
    :data:`GROWTH_FLOOR`; non-finite or non-positive values never count."""
    recent = [float(loss) for loss in losses[-(GROWTH_EVALUATIONS + 1):]]
    if len(recent) <= GROWTH_EVALUATIONS:
        return False
    if not all(math.isfinite(loss) and loss > 0 for loss in recent):
        return False
    grew = all(after >= GROWTH_FACTOR * before for before, after in pairwise(recent))
    return grew and recent[-1] > GROWTH_FLOOR


def growth_warning(records: Sequence[dict[str, Any]]) -> str | None:
    """A warning when the critic loss of ``records`` (a run's evaluation records, oldest first:
    ``critic_loss``, the mean over the chunk's updates and the members that did not diverge)
    grows without bound (:func:`growing_without_bound`), naming what to look at; ``None``
    otherwise."""
    losses = [record.get("critic_loss", math.nan) for record in records]
    if not growing_without_bound(losses):
        return None
    last = records[-1]
    return (
        f"the critic loss at least doubled at each of the last {GROWTH_EVALUATIONS} "
        f"evaluations, to {last['critic_loss']:,.0f} at env step {last['env_steps']:,}: the "
        "critics' targets grow without bound and the policy learns little while they do. Look "
        "at the reward scale (rewards of about 1 per step learn best: scale your environment's, "
        "or --return-bound 5 divides them by running return statistics), at --total-steps (a "
        "longer run may settle) and at the exploration noise (--expl-noise: too little, and "
        "the critics never see the actions their targets value)"
    )


__all__ = [
    "GROWTH_EVALUATIONS",
    "GROWTH_FACTOR",
    "GROWTH_FLOOR",
    "growing_without_bound",
    "growth_warning",
]
