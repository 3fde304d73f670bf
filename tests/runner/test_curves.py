"""Learning curves from metrics.jsonl (td3_jax.runner.curves): what a run's curve holds, the names
of compared runs, and the images written."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from td3_jax.common.errors import ConfigError
from td3_jax.runner.curves import (
    _band_name,
    _draw_members,
    is_td3_jax_figure,
    mixed_envs_warning,
    no_return_warning,
    plot_comparison,
    plot_curve,
    read_curve,
    run_labels,
)


def _write_records(run: Path, records: list[dict]) -> Path:
    run.mkdir(parents=True, exist_ok=True)
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    return run


def _one_member(steps: int, mean: float, std: float, wall: float, **extra) -> dict:
    return {"env": "gymnax/Pendulum-v1", "env_steps": steps, "wall_time_s": wall,
            "eval_return_mean": mean, "eval_return_std": std, **extra}  # fmt: skip


def test_a_run_of_one_member_is_its_mean_with_a_band_of_one_std(tmp_path):
    """Mean ± std over episodes, at the evaluated policy's env steps where the record names
    them (the evaluation inside the chunk); a null (a NaN written as JSON) stays a NaN."""
    run = _write_records(tmp_path / "run", [
        _one_member(100, -5.0, 2.0, 1.5, eval_policy_env_steps=-1),  # (no round finished yet)
        _one_member(200, -3.0, 0.5, 3.0, eval_policy_env_steps=100),
        _one_member(300, None, 1.0, 4.5, eval_policy_env_steps=200),
    ])  # fmt: skip
    curve = read_curve(run)
    assert curve.steps == [100, 100, 200]
    assert curve.wall == [1.5, 3.0, 4.5]
    assert curve.mean[:2] == [-5.0, -3.0] and curve.mean[2] != curve.mean[2]
    assert curve.lower[:2] == [-7.0, -3.5] and curve.upper[:2] == [-3.0, -2.5]
    assert curve.members == [] and curve.policy_steps and curve.env == "gymnax/Pendulum-v1"


def test_a_run_of_several_members_keeps_each_member_and_the_ci_band(tmp_path):
    records = [
        {"env": "e", "env_steps": steps, "wall_time_s": steps / 10, "eval_return_mean": mean,
         "eval_return_ci95_low": mean - 1, "eval_return_ci95_high": mean + 2,
         "per_member": [{"eval_return_mean": a}, {"eval_return_mean": b}]}
        for steps, mean, a, b in ((10, 1.5, 1.0, 2.0), (20, 3.5, 3.0, 4.0))
    ]  # fmt: skip
    curve = read_curve(_write_records(tmp_path / "sweep", records))
    assert curve.members == [[1.0, 3.0], [2.0, 4.0]]
    assert curve.lower == [0.5, 2.5] and curve.upper == [3.5, 5.5]
    assert curve.steps == [10, 20] and not curve.policy_steps
    assert curve.swept == ("", "")  # (seeds alone: no swept values)
    assert curve.band == "mean over members, their range"  # (2 members: the CI is the range)
    four = [{**r, "per_member": r["per_member"] * 2} for r in records]
    assert read_curve(_write_records(tmp_path / "four", four)).band == (
        "mean over members, 95% bootstrap CI")  # fmt: skip
    # one of four diverged by the end: the band is over the other three, their range
    diverged = [{**r, "per_member": [*(r["per_member"] * 2)[:3], {"eval_return_mean": None}]}
                for r in records]  # fmt: skip
    curve = read_curve(_write_records(tmp_path / "diverged", diverged))
    assert curve.band == "mean over members, their range"
    assert _band_name(curve) == "4 members, range"
    assert _band_name(read_curve(_write_records(tmp_path / "four", four))) == "4 members, 95% CI"


class _Axes:
    """Records what is drawn on it: each line's y values, colour and legend label."""

    def __init__(self):
        self.lines = []

    def plot(self, x, y, **style):
        self.lines.append((list(y), style.get("color"), style.get("label")))


def test_a_sweeps_members_are_coloured_and_named_by_their_swept_values(tmp_path):
    """Two learning rates x two seeds: the seeds of one rate share a colour, and each rate is
    named once in the legend; a run of seeds alone keeps its unnamed member lines."""
    settings = [
        {"actor_lr": 0.001},
        {"actor_lr": 0.001},
        {"actor_lr": 0.0003},
        {"actor_lr": 0.0003},
    ]
    members = [{"eval_return_mean": float(i), "seed": i % 2, "settings": settings[i]}
               for i in range(4)]  # fmt: skip
    record = {
        "env": "e",
        "env_steps": 10,
        "wall_time_s": 1.0,
        "eval_return_mean": 1.5,
        "eval_return_ci95_low": 0.0,
        "eval_return_ci95_high": 3.0,
        "per_member": members,
    }
    curve = read_curve(_write_records(tmp_path / "sweep", [record]))  # fmt: skip
    assert curve.swept == ("actor_lr=0.001",) * 2 + ("actor_lr=0.0003",) * 2
    ax = _Axes()
    _draw_members(ax, curve.steps, curve, ["red", "blue"])
    assert ax.lines == [([0.0], "red", "actor_lr=0.001"), ([1.0], "red", None),
                        ([2.0], "blue", "actor_lr=0.0003"), ([3.0], "blue", None)]  # fmt: skip
    ax = _Axes()
    _draw_members(ax, curve.steps, curve._replace(swept=("", "", "", "")), ["red"])
    assert [line[1:] for line in ax.lines] == [(None, None)] * 4


def _two_rates_two_seeds() -> list[dict]:
    """The records of a sweep of two rates x two seeds over two points, the second seed of
    the first rate diverged at the second point."""
    swept = [{"actor_lr": 0.001}] * 2 + [{"actor_lr": 0.0003}] * 2
    returns = [(1.0, 3.0, 10.0, 20.0), (2.0, None, 30.0, 50.0)]  # (per point, per member)
    return [{"env": "e", "env_steps": 10 * (p + 1), "wall_time_s": p + 1.0,
             "eval_return_mean": 0.0, "eval_return_ci95_low": -1.0,
             "eval_return_ci95_high": 1.0,
             "per_member": [{"eval_return_mean": r, "settings": swept[i]}
                            for i, r in enumerate(returns[p])]}
            for p in range(2)]  # fmt: skip


def test_a_sweep_on_its_own_draws_each_settings_mean_not_one_over_all(tmp_path):
    """Two rates x two seeds over two points, one seed diverged at the second: each setting's
    mean line (over its finite members) in its members' colour, and no line or band pooled
    over the settings; a run of seeds keeps its mean and band."""
    from td3_jax.runner.curves import _draw, setting_means

    curve = read_curve(_write_records(tmp_path / "sweep", _two_rates_two_seeds()))
    assert setting_means(curve) == [("actor_lr=0.001", [2.0, 2.0]),
                                    ("actor_lr=0.0003", [15.0, 40.0])]  # fmt: skip
    ax, wall, filled = _Axes(), _Axes(), []
    ax.fill_between = wall.fill_between = lambda *args, **kwargs: filled.append(args)
    _draw([ax, wall], curve, None, "black", ["red", "blue"])
    assert ax.lines[4:] == [([2.0, 2.0], "red", None), ([15.0, 40.0], "blue", None)]
    assert not filled and all(line[1] != "black" for line in ax.lines)
    seeds = curve._replace(swept=("", "", "", ""))
    assert setting_means(seeds) == []
    _draw([ax, wall], seeds, None, "black", ["red"])
    assert ax.lines[-1][1] == "black" and len(filled) == 2  # (its band, on both axes)


def test_a_compared_sweep_is_a_curve_per_setting_with_its_members_range(tmp_path, monkeypatch):
    """In a comparison a sweep is one curve per setting (its mean, and the range of its 3 or
    fewer finite members: their bootstrap CI), labelled with the run and the setting; a run of
    one member beside it keeps its own curve."""
    from td3_jax.runner import curves as module

    sweep = read_curve(_write_records(tmp_path / "sweep", _two_rates_two_seeds()))
    parts = module.setting_curves(sweep)
    assert [setting for setting, _ in parts] == ["actor_lr=0.001", "actor_lr=0.0003"]
    first, second = (part for _, part in parts)
    assert first.mean == [2.0, 2.0] and first.lower == [1.0, 2.0] and first.upper == [3.0, 2.0]
    assert second.mean == [15.0, 40.0] and second.lower == [10.0, 30.0]
    assert second.upper == [20.0, 50.0] and len(second.members) == 2
    single = read_curve(_write_records(tmp_path / "one", [_one_member(10, -5.0, 1.0, 1.0)]))
    saved = []
    monkeypatch.setattr(module, "_save", lambda labelled, path, title: saved.extend(labelled))
    plot_comparison([sweep, single], ["sweep", "one"], tmp_path / "both.png")
    assert [label for _, label in saved] == [
        "sweep actor_lr=0.001 (2 members, range)", "sweep actor_lr=0.0003 (2 members, range)",
        f"one ({_band_name(single)})"]  # fmt: skip
    assert module.setting_curves(single) == []
    one_seed = sweep._replace(members=sweep.members[::2], swept=sweep.swept[::2])
    saved.clear()
    plot_comparison([one_seed], ["sweep"], tmp_path / "one.png")
    assert [label for _, label in saved] == ["sweep actor_lr=0.001 (1 member)",
                                             "sweep actor_lr=0.0003 (1 member)"]  # fmt: skip
    assert all(part.lower == part.upper == part.mean for part, _ in saved)  # (no band)


def test_no_record_is_no_curve_and_an_edited_record_is_named(tmp_path):
    assert read_curve(tmp_path) is None and plot_curve(tmp_path) is None
    assert not (tmp_path / "curve.png").exists()
    _write_records(tmp_path, [_one_member(1, 0.0, 0.0, 0.0), {"env_steps": 2}])
    with pytest.raises(ConfigError, match=r"record 2 of .* lacks wall_time_s, eval_return_mean"):
        read_curve(tmp_path)


def test_compared_runs_are_named_by_folder_unless_two_share_a_name():
    runs = [Path("runs/a/run"), Path("runs/b/run"), Path("runs/ant"), Path("other")]
    assert run_labels(runs) == ["runs/a/run", "runs/b/run", "ant", "other"]


def test_a_run_given_as_dot_is_named_by_its_folder_and_a_link_by_its_own_name(
    tmp_path, monkeypatch
):
    (tmp_path / "ant-run" / "sub").mkdir(parents=True)
    (tmp_path / "ant-run" / "latest").symlink_to(tmp_path / "ant-run" / "sub")
    monkeypatch.chdir(tmp_path / "ant-run")
    assert run_labels([Path("."), Path("sub")]) == ["ant-run", "sub"]
    assert run_labels([Path("sub/..")]) == ["ant-run"]
    assert run_labels([Path("latest"), Path("..")]) == ["latest", tmp_path.name]


def test_a_comparison_of_different_environments_is_warned_about(tmp_path):
    pendulum = read_curve(_write_records(tmp_path / "a", [_one_member(1, -9.0, 1.0, 1.0)]))
    ant = read_curve(
        _write_records(tmp_path / "b", [{**_one_member(1, 900.0, 1.0, 1.0), "env": "brax/ant"}])
    )
    assert mixed_envs_warning([pendulum, pendulum]) is None
    said = mixed_envs_warning([pendulum, ant, pendulum])
    assert said is not None and "(gymnax/Pendulum-v1, brax/ant);" in said
    unnamed = read_curve(_write_records(tmp_path / "c", [
        {**_one_member(1, 900.0, 1.0, 1.0), "env": ""}]))  # fmt: skip
    assert mixed_envs_warning([pendulum, unnamed]) is None
    assert "(brax/ant, gymnax/Pendulum-v1);" in mixed_envs_warning([ant, unnamed, pendulum])


def test_the_images_are_written_in_the_format_their_suffix_names(tmp_path):
    one = _write_records(tmp_path / "one", [_one_member(s, -s, 1.0, s) for s in (1, 2, 3)])
    assert plot_curve(one).read_bytes()[:4] == b"\x89PNG"
    assert plot_curve(one, tmp_path / "one.svg").read_text().lstrip().startswith("<?xml")
    curves = [read_curve(one), read_curve(one)]
    path = plot_comparison(curves, ["a", "b"], tmp_path / "both.pdf")
    assert path.read_bytes()[:5] == b"%PDF-"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["both.pdf", "one", "one.svg"]
    for figure in (one / "curve.png", tmp_path / "one.svg", path):  # (plot replaces only these)
        assert is_td3_jax_figure(figure), figure
    assert not is_td3_jax_figure(one / "metrics.jsonl")


def test_a_run_without_a_finite_return_is_warned_about(tmp_path):
    """Every record null (JSON's NaN) or infinite: its figure would be empty axes."""
    records = [_one_member(1, -1.0, 0.0, 1.0), _one_member(2, -1.0, 0.0, 2.0)]
    records[0]["eval_return_mean"], records[1]["eval_return_mean"] = None, float("-inf")
    run = _write_records(tmp_path / "nan", records)
    said = no_return_warning(read_curve(run), run)
    assert (
        said == f"{run}: no record has a finite evaluation return (each is null or "
        "infinite), so its curve is empty"
    )
    records[1]["eval_return_mean"] = -3.0
    finite = _write_records(tmp_path / "one", records)
    assert no_return_warning(read_curve(finite), finite) is None
