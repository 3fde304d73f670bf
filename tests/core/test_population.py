"""Seeds and sweeps as one vmapped program, and the statistics over seeds."""

from __future__ import annotations

import dataclasses
import json
import re

import jax
import numpy as np
import pytest

from td3_jax.cli.app import main as cli_main
from td3_jax.config.build import make_population, make_train, member_hyperparams, members
from td3_jax.config.schema import ConfigError, TrainConfig
from td3_jax.core import stats
from td3_jax.runner.run import train

TINY = TrainConfig(
    num_envs=4,
    total_steps=256,
    eval_every=128,
    warmup_steps=32,
    batch_size=32,
    updates_per_iter=2,
    hidden_sizes=(16, 16),
    eval_envs=2,
    buffer_size=256,
)
COMPARED = ("eval_return_mean", "critic_loss", "actor_loss")


def _close(a: float, b: float) -> bool:
    return a == pytest.approx(b, rel=2e-3, abs=2e-3)


@pytest.fixture(scope="module")
def three_seeds(tmp_path_factory):
    out = tmp_path_factory.mktemp("seeds")
    cfg = dataclasses.replace(TINY, seed=5, seeds=3)
    return cfg, train(cfg, out, progress=False)


@pytest.mark.runs
def test_seed_k_of_a_population_is_the_single_seed_run(three_seeds, tmp_path):
    cfg, records = three_seeds
    for k in range(cfg.seeds):
        single = train(dataclasses.replace(cfg, seed=cfg.seed + k, seeds=1), tmp_path / f"s{k}",
                       progress=False)  # fmt: skip
        for batched, alone in zip(records, single, strict=True):
            member = batched["per_member"][k]
            assert member["seed"] == cfg.seed + k
            for key in COMPARED:
                assert _close(member[key], alone[key]), (k, key, member[key], alone[key])


def test_population_record_carries_the_statistics_over_seeds(three_seeds):
    _, records = three_seeds
    last = records[-1]
    means = np.array([m["eval_return_mean"] for m in last["per_member"]])
    assert last["members"] == 3
    assert last["eval_return_mean"] == pytest.approx(means.mean())
    assert last["eval_return_median"] == pytest.approx(np.median(means))
    assert last["eval_return_iqm"] == pytest.approx(stats.iqm(means))
    assert last["eval_return_ci95_low"] <= last["eval_return_mean"] <= last["eval_return_ci95_high"]
    assert (
        means.min() <= last["eval_return_ci95_low"] and last["eval_return_ci95_high"] <= means.max()
    )


@pytest.mark.runs
def test_a_swept_value_trains_like_a_run_configured_with_it(tmp_path):
    """Hyperparameters traced through vmap give the numbers of the constant-config run."""
    sweep = {"actor_lr": [1e-3, 1e-2], "tau": [0.005, 0.05]}
    prepared = []
    records = train(TINY, tmp_path / "sweep", progress=False, sweep=sweep,
                    on_prepared=lambda: prepared.append(len(list(tmp_path.iterdir()))))  # fmt: skip
    assert prepared == [1]  # once, with the run's directory made (and locked), before training
    population = members(TINY, sweep)
    assert len(population) == 4 and len(records[-1]["per_member"]) == 4
    for index in (1, 2):  # two different combinations are enough
        settings = records[-1]["per_member"][index]["settings"]
        assert settings == dict(population[index].overrides)
        alone = train(dataclasses.replace(TINY, **settings), tmp_path / f"alone{index}",
                      progress=False)  # fmt: skip
        for key in COMPARED:
            assert _close(records[-1]["per_member"][index][key], alone[-1][key]), key


def test_weight_norm_bounds_are_swept_as_traced_values():
    """Two bounds become two members whose hyperparameters carry them; without
    --max-weight-norm (no bounding) sweeping them would change nothing and is refused."""
    bounded = dataclasses.replace(TINY, max_weight_norm=5.0)
    population = members(bounded, {"max_weight_norm": [0.5, 2.0]})
    assert [dict(m.overrides) for m in population] == [
        {"max_weight_norm": 0.5}, {"max_weight_norm": 2.0}
    ]  # fmt: skip
    stacked = member_hyperparams(bounded, population)
    np.testing.assert_allclose(stacked.agent.max_weight_norm, [0.5, 2.0])
    with pytest.raises(ConfigError, match="max_weight_norm"):
        members(TINY, {"max_weight_norm": [0.5, 2.0]})


def test_member_hyperparams_are_each_members_own_setting_in_the_members_order():
    """Members that share a setting (seeds of one sweep value) get it from one computation; a
    population of 3 seeds x 2 learning rates, listed seed-major, keeps its order; 10^5 seeds
    of one setting take well under a second (they took minutes, one per member)."""
    import time

    population = members(dataclasses.replace(TINY, seeds=3), {"actor_lr": [1e-3, 3e-4]})
    stacked = member_hyperparams(TINY, population)
    expected = [dict(m.overrides)["actor_lr"] for m in population]
    assert sorted(set(expected)) == [3e-4, 1e-3] and len(expected) == 6
    np.testing.assert_allclose(stacked.agent.actor_lr, expected, rtol=1e-6)
    assert np.all(stacked.agent.critic_lr == stacked.agent.critic_lr[0])  # (not swept)
    many = members(dataclasses.replace(TINY, seeds=100_000))
    start = time.perf_counter()
    stacked = member_hyperparams(TINY, many)
    assert time.perf_counter() - start < 10  # (generous for a busy 2-core machine)
    assert stacked.agent.actor_lr.shape == (100_000,)
    one = member_hyperparams(TINY, many[:1])
    assert jax.tree.all(jax.tree.map(lambda a, b: np.all(a == b), stacked, one))


def test_member_keys_are_each_seeds_own_key():
    """All members' keys at once equal ``PRNGKey(seed)`` one by one, across the 32-bit range."""
    from td3_jax.core.population import Member, member_keys

    seeds = [0, 1, 7, 2**31 - 1, 2**31, 3_000_000_000, 2**32 - 1]
    keys = member_keys([Member(seed) for seed in seeds])
    expected = np.stack([np.asarray(jax.random.PRNGKey(seed)) for seed in seeds])
    assert isinstance(keys, np.ndarray) and keys.shape == (7, 2)
    np.testing.assert_array_equal(keys, expected)


def test_sweep_of_an_unknown_setting_is_refused():
    with pytest.raises(ConfigError, match="cannot sweep") as refused:
        members(TINY, {"batch_size": [32, 64]})
    assert "did you mean" not in str(refused.value)  # (nothing close: the list alone)
    for name, meant in (("actr_lr", "actor_lr"), ("gamma", "discount")):
        with pytest.raises(ConfigError, match=rf"cannot sweep \['{name}'\]; did you mean "
                           rf"{meant}\? sweepable: actor_lr, "):  # fmt: skip
            members(TINY, {name: [0.1, 0.2]})
    with pytest.raises(ConfigError, match=r"cannot sweep \['actr_lr', 'gamma'\]; actr_lr: did "
                       r"you mean actor_lr\? gamma: did you mean discount\? sweepable"):
        members(TINY, {"actr_lr": [0.1, 0.2], "gamma": [0.9, 0.99]})


@pytest.mark.runs
def test_sweep_command_prints_a_ranked_table(tmp_path, capsys):
    cli_main([
        "sweep", "--sweep-actor-lr", "1e-3", "1e-2", "--seeds", "2", "--out", str(tmp_path / "s"),
        "--num-envs", "4", "--total-steps", "128", "--eval-every", "128", "--warmup-steps", "32",
        "--batch-size", "32", "--updates-per-iter", "2", "--hidden-sizes", "16", "16",
        "--eval-envs", "2", "--buffer-size", "256", "--quiet",
    ])  # fmt: skip
    out = capsys.readouterr().out
    assert "rank" in out and "95% CI" in out
    # the done line's return is of all four members (two settings): said so, not as one run's
    assert re.search(r"done: .* eval return \S+ ± \S+ over all 4 members \(per setting below\)",
                     out)  # fmt: skip
    assert "actor_lr=0.001" in out and "actor_lr=0.01" in out
    table = out[out.index("rank") :]
    assert table.index("1 ") < table.index("2 ")


@pytest.mark.runs
def test_make_train_vmaps_over_keys():
    train_fn = make_train(TINY)
    states, metrics = jax.jit(jax.vmap(train_fn))(jax.random.split(jax.random.PRNGKey(0), 2))
    assert metrics["eval_returns"].shape == (2, TINY.num_chunks, TINY.eval_envs)
    assert states.env_steps.tolist() == [256, 256]
    # one key alone gives the same numbers as its row of the vmapped run
    _, alone = jax.jit(train_fn)(jax.random.split(jax.random.PRNGKey(0), 2)[1])
    np.testing.assert_allclose(metrics["critic_loss"][1], alone["critic_loss"], rtol=2e-3)


def test_iqm_matches_a_trimmed_mean_by_hand():
    assert stats.iqm([1, 2, 3, 4, 5, 6, 7, 8]) == pytest.approx(np.mean([3, 4, 5, 6]))
    assert stats.iqm(np.arange(100)) == pytest.approx(np.mean(np.arange(25, 75)))
    # n not divisible by 4: the boundary values count by the fraction inside [25%, 75%]
    assert stats.iqm([0, 10, 100]) == pytest.approx((0 * 1 / 12 + 10 * 1 / 3 + 100 * 1 / 12) / 0.5)
    assert stats.iqm([1000, 1, 2, 3]) == pytest.approx(2.5)  # robust to the outlier


def test_bootstrap_ci_covers_the_mean_and_narrows_with_more_seeds():
    rng = np.random.default_rng(0)
    small, large = rng.normal(10, 2, 8), rng.normal(10, 2, 512)
    lo_s, hi_s = stats.bootstrap_ci(small)
    lo_l, hi_l = stats.bootstrap_ci(large)
    assert lo_s <= small.mean() <= hi_s and lo_l <= large.mean() <= hi_l
    assert hi_l - lo_l < (hi_s - lo_s) / 4
    # the normal-theory 95% interval of the mean, 2 * 1.96 * sigma / sqrt(n), for the large sample
    assert hi_l - lo_l == pytest.approx(2 * 1.96 * large.std() / np.sqrt(512), rel=0.15)
    assert stats.bootstrap_ci([3.0]) == (3.0, 3.0)


@pytest.mark.parametrize("count", [2, 3, 4, 6])
def test_the_interval_is_named_a_range_where_the_bootstrap_gives_the_values_range(count):
    """With 3 or fewer distinct values the percentile bootstrap's 95% interval of the mean is
    exactly [min, max] (an all-min resample is at least 1/27 likely, above the 2.5% tail), and
    its label says "range"; from 4 on it lies inside the range and is a "95% CI"."""
    values = np.arange(count, dtype=np.float64) * 3.0 - 1.0
    low, high = stats.bootstrap_ci(values)
    is_range = (low, high) == (values.min(), values.max())
    assert is_range == (count < stats.CI_NARROWER_FROM)
    assert stats.interval_name(count) == ("range" if is_range else "95% CI")


def test_population_keeps_reset_and_warmup_branches():
    """Under the seed vmap the batch-level conditions are reduced over members and stay conds
    (and loops)."""
    cfg = dataclasses.replace(TINY, seeds=2)
    program = make_population(cfg, members(cfg))
    jaxpr = str(jax.make_jaxpr(program.chunk)(program.hyperparams, program.abstract_state, 4))
    assert jaxpr.count("cond[") >= 2  # "learning started" and the delayed actor step
    # The reset rounds' count is max-reduced over the members (pmax only serves that), so the
    # reset loop is one loop for all members, not a per-member one.
    assert jaxpr.count("pmax[") == 1 and jaxpr.count("while[") >= 2
    train_fn = make_train(TINY, axis_name="seeds")
    vmapped = jax.vmap(train_fn, axis_name="seeds")
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    assert str(jax.make_jaxpr(vmapped)(keys)).count("cond[") >= 2


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_a_non_finite_swept_value_is_refused_before_anything_compiles(value):
    with pytest.raises(ConfigError, match=r"finite.*--sweep-critic-lr"):
        members(TINY, {"critic_lr": [1e-3, float(value)]})


def test_an_impossible_swept_value_names_its_sweep_flag():
    with pytest.raises(ConfigError) as err:
        members(TINY, {"actor_lr": [1e-3, -1.0], "tau": [0.005]})
    message = str(err.value)
    assert message.startswith("--sweep-actor-lr must ") and message.endswith(", got -1.0")
    assert re.search(r"(^|\s)--actor-lr", message) is None
    with pytest.raises(ConfigError, match=r"^--sweep-tau must be in \(0, 1\], got 2.0$"):
        members(TINY, {"actor_lr": [1e-3], "tau": [2.0]})
    # a setting that is not swept keeps its own flag
    with pytest.raises(ConfigError, match=r"^--v-min \(5.0\) must be below --sweep-v-max"):
        members(dataclasses.replace(TINY, critic="distributional", v_min=5.0), {"v_max": [1.0]})


@pytest.mark.runs
def test_a_diverging_member_is_marked_and_the_others_go_on(tmp_path, capsys):
    """One exploding setting does not stop the sweep (nor every resume)."""
    out = tmp_path / "s"
    args = [
        "sweep", "--sweep-critic-lr", "1e30", "1e-3", "--out", str(out),
        "--num-envs", "4", "--total-steps", "256", "--eval-every", "128", "--warmup-steps", "32",
        "--batch-size", "32", "--updates-per-iter", "2", "--hidden-sizes", "16", "16",
        "--eval-envs", "2", "--buffer-size", "256", "--quiet",
    ]  # fmt: skip
    cli_main(args)
    captured = capsys.readouterr()
    assert "critic_lr=1e+30 seed=0 diverged" in captured.err
    records = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["env_steps"] for r in records] == [128, 256]
    last = records[-1]
    exploded, fine = last["per_member"]
    assert exploded["diverged"] is True and exploded["eval_return_mean"] is None
    assert "diverged" not in fine and np.isfinite(fine["eval_return_mean"])
    assert last["diverged_members"] == ["critic_lr=1e+30 seed=0"]
    assert last["eval_return_mean"] == pytest.approx(fine["eval_return_mean"])  # the live ones
    table = captured.out[captured.out.index("rank") :]
    assert table.index("critic_lr=0.001") < table.index("critic_lr=1e+30")  # diverged: last
    # td3-jax eval shows the diverged member as the sweep table does: no returns
    cli_main(["eval", "--run", str(out), "--episodes", "2"])
    lines = capsys.readouterr().out.splitlines()
    cells = lambda line: [c.strip() for c in re.split(r"[│┃|]", line) if c.strip()]
    (exploded,) = [cells(line) for line in lines if "critic_lr=1e+30 seed=0" in line]
    assert exploded == ["critic_lr=1e+30 seed=0 (diverged)", "-", "-", "-", "-"]
    (fine,) = [cells(line) for line in lines if "critic_lr=0.001 seed=0" in line]
    assert fine[0] == "critic_lr=0.001 seed=0" and all(re.fullmatch(r"-?\d+\.\d", c)
                                                        for c in fine[1:])  # fmt: skip
    assert not any(line.startswith("over ") for line in lines)  # one live member: no aggregate
