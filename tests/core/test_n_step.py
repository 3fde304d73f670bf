"""n-step folding (``td3_jax.core.n_step``) and runs read from the ring (``replay.sample_runs``)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from td3_jax.core import n_step, replay
from td3_jax.core.types import Transition

GAMMA = 0.9


def run_of(ended, done, rewards=(1.0, 2.0, 3.0)):
    """One run of len(rewards) steps; obs/next_obs of step j are [j] / [10 + j], action [j]."""
    n = len(rewards)
    steps = np.arange(n, dtype=np.float32)
    run = Transition(
        obs=steps[None, :, None],
        action=steps[None, :, None],
        reward=np.asarray([rewards], np.float32),
        next_obs=(10 + steps)[None, :, None],
        done=np.asarray([done], np.float32),
    )
    return run, np.asarray([ended], np.float32)


@pytest.mark.parametrize(
    "ended, done, reward, last, bootstrap",
    [
        # No end: 1 + 0.9 * 2 + 0.81 * 3, bootstrapped with 0.9^3 (0.9 * (1 - done)).
        ([0, 0, 0], [0, 0, 0], 5.23, 2, 0.81),
        # Terminated at the second step: no bootstrap, the third step is the next episode's.
        ([0, 1, 0], [0, 1, 0], 2.8, 1, 0.0),
        # Truncated at the first step: an ordinary 1-step transition.
        ([1, 0, 0], [0, 0, 0], 1.0, 0, 1.0),
        # Truncated at the second step: bootstrapped from its true last observation with 0.9^2.
        ([0, 1, 1], [0, 0, 1], 2.8, 1, 0.9),
    ],
)
def test_fold_hand_computed(ended, done, reward, last, bootstrap):
    run, ended = run_of(ended, done)
    out = jax.tree.map(np.asarray, n_step.fold(run, ended, GAMMA))
    np.testing.assert_allclose(out.reward, [reward], rtol=1e-6)
    np.testing.assert_array_equal(out.next_obs, [[10.0 + last]])
    np.testing.assert_array_equal(out.obs, [[0.0]])
    np.testing.assert_array_equal(out.action, [[0.0]])
    # The update's target is reward + GAMMA * (1 - done) * Q'.
    np.testing.assert_allclose(GAMMA * (1 - out.done), [GAMMA * bootstrap], rtol=1e-6)


def test_fold_of_one_step_is_the_transition():
    run, ended = run_of([1], [1], rewards=(4.0,))
    out = n_step.fold(run, ended, GAMMA)
    assert float(out.reward[0]) == 4.0 and float(out.done[0]) == 1.0
    run, ended = run_of([0], [0], rewards=(4.0,))
    assert float(n_step.fold(run, ended, GAMMA).done[0]) == 0.0


def test_fold_with_traced_discount_under_jit():
    run, ended = run_of([0, 0, 0], [0, 0, 0])
    out = jax.jit(n_step.fold)(run, ended, jnp.float32(0.5))
    np.testing.assert_allclose(out.reward, [1 + 0.5 * 2 + 0.25 * 3])


def _two_env_ring(steps: int, capacity: int = 10):
    """A ring filled by 2 environments for ``steps`` steps; row value = 10 * step + env."""
    buffer = replay.init(capacity, jnp.zeros(()))
    for t in range(steps):
        buffer = replay.add(buffer, jnp.asarray([10.0 * t, 10.0 * t + 1]))
    return buffer


def test_runs_are_consecutive_steps_of_one_environment_and_only_written_ones():
    # 8 steps of 2 envs into 10 slots: steps 3..7 are kept; runs of 3 start at steps 3..5.
    buffer = _two_env_ring(8)
    runs = np.asarray(replay.sample_runs(buffer, jax.random.PRNGKey(0), 3000, 3, 2))
    np.testing.assert_array_equal(runs[:, 1] - runs[:, 0], 10.0)
    np.testing.assert_array_equal(runs[:, 2] - runs[:, 0], 20.0)
    starts, counts = np.unique(runs[:, 0], return_counts=True)
    np.testing.assert_array_equal(starts, [30, 31, 40, 41, 50, 51])
    assert counts.min() > 3000 / 6 * 0.8  # uniform over the valid starts


def test_runs_before_wrapping_start_at_the_first_row():
    buffer = _two_env_ring(3)  # rows 0..5 hold steps 0..2
    runs = np.asarray(replay.sample_runs(buffer, jax.random.PRNGKey(1), 500, 2, 2))
    np.testing.assert_array_equal(np.unique(runs[:, 0]), [0, 1, 10, 11])


def test_runs_longer_than_the_filled_part_raise():
    with pytest.raises(ValueError, match="need more than 4 filled slots"):
        replay.sample_runs(_two_env_ring(2), jax.random.PRNGKey(0), 4, 3, 2)
