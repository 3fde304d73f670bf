"""A TrainConfig refuses values of the wrong type where it is made, and the errors of
``td3_jax.train`` / ``td3_jax.make_train`` name fields and arguments, not command-line flags."""

from __future__ import annotations

import dataclasses
import inspect
import pickle
import re
import typing

import numpy as np
import pytest
from configs import tiny_config

import td3_jax
from td3_jax.common.errors import ConfigError
from td3_jax.config.python_names import field_names
from td3_jax.config.schema import TrainConfig, field_types, value_fits
from td3_jax.runner import run as run_module


@pytest.mark.parametrize(
    ("given", "message"),
    [
        (dict(total_steps="3000"),
         "TrainConfig.total_steps must be a whole number, got '3000' (str)"),
        (dict(total_steps=1000.5),
         "TrainConfig.total_steps must be a whole number, got 1000.5 (float)"),
        (dict(seed=True), "TrainConfig.seed must be a whole number, got True (bool)"),
        (dict(tau="0.1"), "TrainConfig.tau must be a number or None, got '0.1' (str)"),
        (dict(normalize_obs=1), "TrainConfig.normalize_obs must be True or False, got 1 (int)"),
        (dict(hidden_sizes=(256, "a")),
         "TrainConfig.hidden_sizes must be a tuple of whole numbers or None, got (256, 'a') "
         "(tuple)"),
        (dict(env=None), "TrainConfig.env must be a string, got None (NoneType)"),
    ],
)  # fmt: skip
def test_a_value_of_the_wrong_type_is_refused_where_the_config_is_made(given, message):
    with pytest.raises(ConfigError) as refused:
        TrainConfig(**given)
    assert str(refused.value) == message
    with pytest.raises(ConfigError):  # (a copy with a changed field is made the same way)
        dataclasses.replace(TrainConfig(), **given)


@pytest.mark.parametrize(
    ("name", "meant"),
    [("gamma", "discount"), ("total_timesteps", "total_steps"), ("num_env", "num_envs"),
     ("learning_rate", "actor_lr or critic_lr"), ("lr", "actor_lr or critic_lr"),
     ("buffer_sz", "buffer_size"), ("zzz", None)],
)  # fmt: skip
def test_a_keyword_that_is_no_field_names_the_field_meant(name, meant):
    """Other libraries' names (CleanRL's gamma, SB3's total_timesteps) and misspellings get
    the field they stand for, as the command line's flags do; a copy checks its changes too."""
    expected = f"TrainConfig() got an unexpected keyword argument {name!r}"
    expected += f"; did you mean {meant}?" if meant else ""
    with pytest.raises(TypeError) as refused:
        TrainConfig(**{name: 1})
    assert str(refused.value) == expected
    with pytest.raises(TypeError, match=re.escape(expected)):
        dataclasses.replace(TrainConfig(), **{name: 1})
    # (the check keeps the fields' signature, which help() and editors show)
    parameters = inspect.signature(TrainConfig).parameters
    assert list(parameters) == [field.name for field in dataclasses.fields(TrainConfig)]


@pytest.mark.parametrize(
    ("owner", "name", "meant"),
    [(td3_jax.TD3Config, "polcy_noise", "policy_noise"), (td3_jax.TD3Config, "gamma", "discount"),
     (td3_jax.TD3Config, "policy_delay", "policy_freq"),
     (td3_jax.DDPGConfig, "lr", "actor_lr or critic_lr"), (td3_jax.DDPGConfig, "zzz", None)],
)  # fmt: skip
def test_the_agents_configs_name_the_field_meant_too(owner, name, meant):
    """TD3Config and DDPGConfig (flax dataclasses, JAX pytrees) refuse an unknown keyword as
    TrainConfig does, and still build, copy and pass through JAX's tree functions."""
    import jax

    expected = f"{owner.__name__}() got an unexpected keyword argument {name!r}"
    expected += f"; did you mean {meant}?" if meant else ""
    with pytest.raises(TypeError) as refused:
        owner(**{name: 0.1})
    assert str(refused.value) == expected
    config = owner(tau=0.1)
    assert config.replace(discount=0.9).discount == 0.9 and config.tau == 0.1
    assert jax.tree.map(lambda leaf: leaf, config) == config
    assert pickle.loads(pickle.dumps(config)) == config
    parameters = inspect.signature(owner).parameters
    assert list(parameters) == [field.name for field in dataclasses.fields(owner)]


def test_values_of_the_right_kind_are_taken_as_given():
    """Whole floats for counts (``total_steps=1e6``), ints and NumPy scalars for floats,
    lists for sizes: the kinds a Python caller or a config.json gives, kept as the field's own
    plain Python type."""
    cfg = TrainConfig(total_steps=1e6, tau=1, actor_lr=np.float32(1e-3), num_envs=np.int64(8),
                      normalize_obs=np.bool_(False), hidden_sizes=[64, 64])  # fmt: skip
    plain = (cfg.total_steps, cfg.tau, cfg.actor_lr, cfg.num_envs, cfg.normalize_obs,
             cfg.hidden_sizes)  # fmt: skip
    assert plain == (1_000_000, 1.0, float(np.float32(1e-3)), 8, False, (64, 64))
    assert [type(v) for v in plain] == [int, float, float, int, bool, tuple]
    hash(cfg)  # (plain values: the config hashes, and config.json can write it)


def test_value_fits_checks_a_literal_s_choices_only_when_asked():
    kind = field_types()["algo"]
    assert value_fits("td3", kind) and not value_fits("sac", kind)
    assert value_fits("sac", kind, choices=False)
    assert not value_fits(3.5, field_types()["impl"]) and value_fits(None, field_types()["impl"])


@pytest.mark.parametrize(
    ("flags", "names"),
    [
        ("--total-steps 2000 is not below (--total-steps 2000): try --warmup-steps 1000",
         "total_steps=2000 is not below (total_steps=2000): try warmup_steps=1000"),
        ("--eval-every 1000 given but the run was started with --eval-every 1008",
         "eval_every=1000 given but the run was started with eval_every=1008"),
        ("x already holds a run; pass --resume or choose a new --out",
         "x already holds a run; pass resume=True or choose a new out_dir"),
        ("--no-eval-in-chunk ends the run; --eval-in-chunk does not",
         "eval_in_chunk=False ends the run; eval_in_chunk=True does not"),
        ("--hidden-sizes 256 256 and --critic-hidden-sizes 512",
         "hidden_sizes=(256, 256) and critic_hidden_sizes=(512,)"),
        ("--sweep-tau 0.1 0.2 differ from --sweep-foo",
         "sweep={'tau': [0.1, 0.2]} differ from --sweep-foo"),
        ("--actor-lr 3e-4 and --tau -1; --critic c51; --critic plain.",
         "actor_lr=3e-4 and tau=-1; critic c51; critic='plain'."),
        ("--env gymnax/CartPole-v1 given, started with --env brax/ant.",
         "env='gymnax/CartPole-v1' given, started with env='brax/ant'."),
        ("--total-steps runs as 2016; cannot change on --resume yet; leave it out to resume",
         "total_steps runs as 2016; cannot change on a resume yet; give the run's own value to "
         "resume (td3_jax.runner.rundir.load_config(out_dir) is the run's config)"),
        ("only --total-steps, --wandb, --matmuls may change; --hidden-sizes 256 256.",
         "only total_steps, wandb=True, matmuls may change; hidden_sizes=(256, 256)."),
        ("--v-min -inf, --tau nan", "v_min=-inf, tau=nan"),
        ("cannot be written; continue with: td3-jax train --out 'runs/a b' --resume --seed 1",
         "cannot be written; continue with: td3-jax train --out 'runs/a b' --resume --seed 1"),
        ("(td3-jax eval --run x); --resume too", "(td3-jax eval --run x); resume=True too"),
        ("--out infra and --out runs, --out 5.", "out_dir infra and out_dir runs, out_dir=5."),
        ("--not-a-flag 3, --preset t1 and pre--total-steps",
         "--not-a-flag 3, --preset t1 and pre--total-steps"),
    ],
)  # fmt: skip
def test_flags_in_a_message_become_python_names(flags, names):
    assert field_names(flags) == names


@pytest.mark.runs
def test_the_public_train_and_make_train_name_fields_the_cli_flags(tmp_path, capsys):
    """The same refusal: through ``td3_jax.train`` and ``td3_jax.make_train`` in Python's
    names, through the command line's ``train`` (``td3_jax.runner.run.train``) in its flags."""
    bad = tiny_config(total_steps=32, warmup_steps=32)
    expected = "warmup_steps=32 is not below the 32 env steps the run collects (total_steps=32)"
    for public in (lambda: td3_jax.train(bad, tmp_path / "a", progress=False),
                   lambda: td3_jax.make_train(bad)):  # fmt: skip
        with pytest.raises(ConfigError, match=f"^{re.escape(expected)}"):
            public()
    with pytest.raises(ConfigError, match=r"^--warmup-steps 32 is not below"):
        run_module.train(bad, tmp_path / "b", progress=False)
    assert td3_jax.train.__doc__ == run_module.train.__doc__
    assert inspect.signature(td3_jax.train) == inspect.signature(run_module.train)
    for public in (td3_jax.train, td3_jax.make_train):  # (e.g. sent to a process pool)
        assert pickle.loads(pickle.dumps(public)) is public


def test_odd_numbers_are_refused_or_made_plain_where_the_config_is_made():
    """A NumPy float holding a whole number is a count like a Python one; a fraction is a
    float; a number too large for a float is one ConfigError."""
    import fractions

    cfg = TrainConfig(num_envs=np.float32(8.0), tau=fractions.Fraction(1, 4))
    assert (cfg.num_envs, type(cfg.num_envs), cfg.tau, type(cfg.tau)) == (8, int, 0.25, float)
    with pytest.raises(ConfigError, match="too large for a float setting"):
        TrainConfig(tau=10**400)
    assert value_fits(object(), typing.Any)


@pytest.mark.parametrize(
    ("given", "advice"),
    [({"env": "gymnax/Pendulum-v1"}, "TrainConfig(**settings) makes one of a dict"),
     ("pendulum", "make one with TrainConfig(env=..., ...)"),
     (None, "make one with TrainConfig(env=..., ...)"),
     ("x" * 70, "make one with TrainConfig(env=..., ...)")],
)  # fmt: skip
def test_train_and_make_train_refuse_anything_but_a_train_config_by_name(given, advice, tmp_path):
    """A dict of settings or a preset's name is one TypeError that says what to pass, where it
    was an AttributeError from deep inside; nothing is written. A long value is cut to 60
    characters."""
    shown = repr(given) if len(repr(given)) <= 60 else "'" + "x" * 56 + "..."
    expected = f"cfg must be a td3_jax.TrainConfig, got {shown} ({type(given).__name__})"
    for call in (lambda: td3_jax.make_train(given), lambda: td3_jax.train(given, tmp_path / "r")):
        with pytest.raises(TypeError) as refused:
            call()
        assert str(refused.value) == f"{expected}; {advice}"
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("out_dir", [5, None, "", b"runs/x"])
def test_train_refuses_an_out_dir_that_is_no_path_by_name(out_dir):
    with pytest.raises(TypeError) as refused:
        td3_jax.train(tiny_config(), out_dir)
    assert str(refused.value) == (f"out_dir must be a directory's path (str or os.PathLike), "
                                  f"got {out_dir!r} ({type(out_dir).__name__})")  # fmt: skip


def test_make_train_says_that_it_trains_one_agent_per_key_where_seeds_asks_for_more():
    import dataclasses
    import warnings

    with pytest.warns(UserWarning, match=r"one agent per key: seeds=3 is for td3_jax") as said:
        td3_jax.make_train(dataclasses.replace(tiny_config(), seeds=3))
    assert [w.filename for w in said] == [__file__]  # (the caller's line, not td3-jax's)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        td3_jax.make_train(tiny_config())  # (one seed: nothing said)


def test_make_train_says_where_its_whole_chunks_run_other_steps_than_the_command():
    """7 environments, eval_every=64, total_steps=128: make_train runs cfg's 3 chunks of 9
    iterations (63 steps each, eval_every rounded down: 189 steps), one row of metrics each,
    and says so; the command runs chunks of 10 iterations (fewer steps past the end) and stops
    at 19 iterations, 133 steps. Whole chunks of whole iterations: nothing said."""
    import warnings

    import jax

    cfg = tiny_config(num_envs=7, eval_every=64, total_steps=128)
    with pytest.warns(UserWarning, match=r"3 whole chunks of 9 iterations: 189 env steps per "
                      r"key, where the command line stops at 133 \(total_steps=128\)") as said:
        train = td3_jax.make_train(cfg)
    assert [w.filename for w in said] == [__file__]
    _, metrics = jax.eval_shape(train, td3_jax.key_for_seed(0))
    assert metrics["eval_returns"].shape == (cfg.num_chunks, cfg.eval_envs) == (3, 2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        td3_jax.make_train(tiny_config(num_envs=8, eval_every=64, total_steps=128))


def test_python_train_says_how_an_eval_every_of_part_iterations_runs(tmp_path, capsys):
    """16 environments: eval_every=100 runs as 96 (6 iterations; 112 would run more steps past
    256), which the library says as the command does, in field names; a whole eval_every (what
    the command hands over, rounded and said already) says nothing."""
    cfg = tiny_config(num_envs=16, eval_every=100, total_steps=256)
    kept = run_module._eval_every_within_run(cfg, tmp_path / "a", resume=False, say=True)
    assert kept == cfg and kept.steps_per_chunk == 96
    assert capsys.readouterr().out == ("eval_every=100 runs as 96 (whole iterations of 16 env "
                                       "steps)\n")  # fmt: skip
    whole = tiny_config(num_envs=16, eval_every=96, total_steps=256)
    assert run_module._eval_every_within_run(whole, tmp_path / "b", resume=False, say=True) == whole
    assert capsys.readouterr().out == ""


def test_the_trained_function_says_what_key_it_takes(tmp_path):
    """An int seed, or a batch of keys to the unbatched function, was JAX's "invalid PRNG key
    data"; one key of either kind trains, and so does a batch under jax.vmap."""
    import jax

    from td3_jax.core import training

    train = td3_jax.make_train(tiny_config())
    for wrong, shown in ((0, "got int 0"), (jax.random.split(jax.random.PRNGKey(0), 3),
                                            "got an array of shape (3, 2)")):  # fmt: skip
        with pytest.raises(TypeError) as refused:
            train(wrong)
        assert str(refused.value) == (
            "train takes one PRNG key (td3_jax.key_for_seed(seed) or jax.random.PRNGKey(seed)), "
            f"{shown}; for several keys, jax.vmap the function over them")  # fmt: skip
    for key in (td3_jax.key_for_seed(0), jax.random.key(0)):
        training.check_key(key)
    jax.eval_shape(jax.vmap(train), jax.random.split(jax.random.PRNGKey(0), 2))


def test_a_sweep_of_one_number_says_to_give_a_list(tmp_path):
    with pytest.raises(ConfigError) as refused:
        td3_jax.train(tiny_config(), tmp_path / "r", sweep={"actor_lr": 1e-3})
    assert str(refused.value) == (
        "sweep values are a list for each setting, e.g. {'actor_lr': [0.001, ...]}; got "
        "{'actor_lr': 0.001}")  # fmt: skip
    assert not (tmp_path / "r").exists()


def test_train_refuses_a_preset_label_that_names_no_preset(tmp_path):
    """``preset=`` only labels the run in config.json; a misspelt one was recorded as it was."""
    with pytest.raises(ConfigError, match=r"unknown preset 'pendullum'; did you mean "
                       r"pendulum or ddpg-pendulum\?"):  # fmt: skip
        td3_jax.train(tiny_config(), tmp_path / "r", preset="pendullum")
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize(
    ("wrong", "said"),
    [({"algo": "sac"}, "unknown algo 'sac'; choose one of td3, ddpg"),
     ({"env": "gymnax/Pendulum-v2"},
      "unknown environment 'gymnax/Pendulum-v2'; did you mean gymnax/Pendulum-v1?")],
)  # fmt: skip
def test_a_misspelt_name_is_said_before_a_size_that_does_not_fit(wrong, said, tmp_path):
    """A config wrong twice (a warm-up longer than the run, and a misspelt choice or
    environment) names the misspelling first, from make_train and from train alike."""
    from td3_jax.common.errors import Td3JaxError

    cfg = TrainConfig(total_steps=1000, **wrong)  # (warmup_steps=2000 does not fit in 1000)
    for call in (lambda: td3_jax.make_train(cfg), lambda: td3_jax.train(cfg, tmp_path / "r")):
        with pytest.raises(Td3JaxError) as refused:
            call()
        assert str(refused.value).startswith(said)
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize(
    ("function", "name", "meant"),
    [(td3_jax.train, "resum", "resume"), (td3_jax.train, "time_budget", "time_budget_s"),
     (td3_jax.make_train, "axisname", "axis_name"), (td3_jax.train, "zzz", None)],
)  # fmt: skip
def test_train_and_make_train_name_the_keyword_meant_before_they_run(
    function, name, meant, tmp_path
):
    """``tj.train(cfg, out, resum=True)`` says ``resume`` before it touches ``out``; the
    signature shown by help() and the reference stays the function's own."""
    import inspect

    expected = f"{function.__name__}() got an unexpected keyword argument {name!r}"
    expected += f"; did you mean {meant}?" if meant else ""
    with pytest.raises(TypeError) as refused:
        function(TrainConfig(), **({"out_dir": tmp_path / "run"} if function is td3_jax.train
                                   else {}), **{name: True})  # fmt: skip
    assert str(refused.value) == expected
    assert not (tmp_path / "run").exists()
    assert "cfg" in inspect.signature(function).parameters
