"""Summary lines that say what they mean: the done line's ± says what it is over (seeds, a
sweep's members) and counts the members that diverged; plot names the figure it cannot
write, not the temporary file beside it."""

from __future__ import annotations

import errno
from pathlib import Path

import pytest
from support import TINY_FLAGS, assert_one_line_error, main

from td3_jax.cli.notes import done_line, members_note

BELOW = "; per setting below)"


def record(members: int, diverged: int = 0) -> dict:
    last = {"members": members, "env_steps": 128, "wall_time_s": 9.0,
            "eval_return_mean": -123.8, "eval_return_std": 4.2}  # fmt: skip
    if diverged:
        last["diverged_members"] = [f"critic_lr={i}" for i in range(diverged)]
    return last


@pytest.mark.parametrize(
    ("members", "diverged", "sweeping", "note"),
    [
        (1, 0, False, " over its evaluation episodes"),  # (one seed)
        (4, 0, False, " over all 4 seeds"),
        (4, 1, False, " over the 3 seeds that did not diverge (1 of 4 diverged)"),
        (4, 0, True, " over all 4 members (per setting below)"),
        (1, 0, True, " over its evaluation episodes"),  # (a sweep of one: no table)
        (2, 1, True, " over the 1 member that did not diverge (1 of 2 diverged" + BELOW),
        (6, 2, True, " over the 4 members that did not diverge (2 of 6 diverged" + BELOW),
    ],
)
def test_the_done_line_says_what_its_spread_is_over(members, diverged, sweeping, note):
    last = record(members, diverged)
    assert members_note(last, sweeping) == note
    line = done_line(last, Path("runs/x"), pooled=note)
    assert f"eval return -123.8 ± 4.2{note}; outputs in runs/x" in line


@pytest.mark.runs
def test_a_sweep_with_a_diverged_member_counts_it(tmp_path, capsys):
    """A sweep whose critic_lr 1e30 diverges at once: the done line's ± is over the one
    member left, and says so."""
    out = tmp_path / "sweep"
    code, stdout, err = main(["sweep", *TINY_FLAGS, "--sweep-critic-lr", "1e-3", "1e30",
                              "--out", str(out), "--quiet"], capsys)  # fmt: skip
    assert code == 0, err
    assert "member critic_lr=1e+30 seed=7 diverged" in err
    (done,) = [line for line in stdout.splitlines() if line.startswith("done: ")]
    assert " ± 0.0 over the 1 member that did not diverge (1 of 2 diverged; per setting " in done
    assert "over all 2 members" not in done


def test_plot_names_the_figure_it_cannot_write(tmp_path, monkeypatch, capsys):
    """On a read-only file system the temporary file beside the figure can be neither written
    nor removed (EROFS, where removing a missing file is otherwise no error): the line names
    curve.png, not curve.png.<pid>.tmp."""
    import matplotlib.figure

    from td3_jax.runner.curves import Curve

    curve = Curve(env="gymnax/Pendulum-v1", steps=[64], wall=[3.0], mean=[-120.0],
                  lower=[-130.0], upper=[-110.0], band="std", members=[],
                  policy_steps=False)  # fmt: skip
    monkeypatch.setattr("td3_jax.cli.finished._curve_to_plot", lambda run: curve)
    run = tmp_path / "run"
    run.mkdir()

    def read_only(path, *args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system", str(path))

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig",
                        lambda figure, path, **kwargs: read_only(path))  # fmt: skip
    monkeypatch.setattr(Path, "unlink", read_only)  # (every removal refused too)
    code, _, err = main(["plot", "--run", str(run)], capsys)
    monkeypatch.undo()
    assert_one_line_error(code, err, f"cannot write {run / 'curve.png'}: Read-only file system",
                          "--out FILE")  # fmt: skip
    assert ".tmp" not in err
