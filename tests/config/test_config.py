"""Tests of the training configuration (``td3_jax.config.schema``) and the presets
(``td3_jax.config.presets``): validation, presets, derived sizes.

The derived quantities are checked against values worked out by hand in the comments, and the
agent defaults against the numbers of the TD3 paper and of the DDPG Pendulum baseline.
"""

from __future__ import annotations

import dataclasses

import pytest

from td3_jax.config import schema as config
from td3_jax.config.build import agent_config, ou_params
from td3_jax.config.presets import ENV_PRESETS, PRESETS, device_defaults, env_preset, preset
from td3_jax.config.schema import ConfigError, TrainConfig, validate
from td3_jax.core.td3 import DDPGConfig, TD3Config

# A small valid configuration to derive broken ones from (only one field changed each time).
SMALL = TrainConfig(
    num_envs=4,
    total_steps=1_000,
    batch_size=32,
    buffer_size=500,
    warmup_steps=100,
    eval_every=200,
    hidden_sizes=(16, 16),
)


def test_defaults_validate():
    cfg = TrainConfig()
    assert validate(cfg) is cfg


def test_small_config_validates():
    assert validate(SMALL) is SMALL


@pytest.mark.parametrize(
    "changes, match",
    [
        # batch larger than the buffer: a batch the 16-row ring holds, or a ring of one batch
        (
            dict(buffer_size=16, batch_size=32),
            "replay buffer \\(16 transitions\\); try --batch-size 16, or --buffer-size 32 or more$",
        ),
        # ... the batch offered a multiple of the 3 shards (the 8-row ring holds 6 of it)
        (
            dict(num_envs=3, eval_every=210, buffer_size=8, batch_size=15, replay_shards=3),
            "try --batch-size 6, or --buffer-size 15 or more$",
        ),
        # a batch larger than all the run collects (1 chunk = 8 steps): it would never update
        (
            dict(num_envs=1, eval_every=8, total_steps=8, batch_size=16),
            "never update; try --batch-size 8, or --total-steps 16 or more$",
        ),
        # ... where the ring is also smaller than the batch, a longer run needs a larger ring
        (
            dict(num_envs=1, eval_every=8, total_steps=8, batch_size=32, buffer_size=16),
            "try --batch-size 8, or --total-steps 32 or more with --buffer-size 32 or more$",
        ),
        (dict(num_envs=0), "num-envs"),
        (dict(num_envs=-3), "num-envs"),
        (dict(total_steps=-1), "total-steps"),
        (dict(total_steps=0), "total-steps must be positive"),
        (dict(warmup_steps=-1), "warmup-steps"),
        # one iteration (32 envs x 1 step) adds more than the 16-transition buffer
        (dict(num_envs=32, buffer_size=16, batch_size=8), "iteration"),
        # ... or 4 envs x 8 steps per iteration
        (dict(steps_per_iter=8, buffer_size=16, batch_size=8), "iteration"),
        (dict(discount=-0.01), "discount"),
        (dict(discount=1.01), "discount"),
        (dict(hidden_sizes=(0,)), "hidden-sizes"),
        (dict(hidden_sizes=(16, 0)), "hidden-sizes"),
        (dict(hidden_sizes=()), "hidden-sizes"),
        (dict(batch_size=0), "batch-size"),
        (dict(eval_every=0), "eval-every"),
        (dict(tau=0.0), "tau"),
        (dict(tau=1.5), "tau"),
        (dict(episode_length=0), "episode-length"),
        (dict(algo="sac"), "unknown --algo 'sac'; choose one of td3, ddpg"),
        (dict(exploration="OU"), "unknown --exploration 'OU'; choose one of gaussian, ou"),
        (dict(n_step=0), "n-step"),
        # 3-step runs over 4 envs span 12 rows; the ring holds 8
        (dict(n_step=3, buffer_size=8, batch_size=4), "n-step"),
    ],
)
def test_validate_rejects(changes, match):
    cfg = dataclasses.replace(SMALL, **changes)
    with pytest.raises(ConfigError, match=match):
        validate(cfg)


@pytest.mark.parametrize(
    "changes",
    [
        dict(discount=0.0),
        dict(discount=1.0),
        dict(total_steps=101),  # the warm-up's 100 steps and one iteration more (104)
        dict(warmup_steps=0),
        dict(tau=1.0),
        # batch exactly the buffer's size, one iteration exactly filling it
        dict(num_envs=32, buffer_size=32, batch_size=32),
        dict(hidden_sizes=(1,)),
    ],
)
def test_validate_accepts_edge_values(changes):
    cfg = dataclasses.replace(SMALL, **changes)
    assert validate(cfg) is cfg


def test_config_error_is_a_value_error():
    assert issubclass(ConfigError, ValueError)


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_every_preset_builds_a_valid_config(name):
    cfg = TrainConfig(**PRESETS[name])
    assert validate(cfg) is cfg
    assert preset(name) == cfg
    for key, value in PRESETS[name].items():
        assert getattr(cfg, key) == value


def test_preset_none_is_the_defaults_and_unknown_preset_is_an_error():
    assert preset(None) == TrainConfig()
    # The defaults are the `pendulum` preset (what `td3-jax train` runs with no flags).
    assert TrainConfig() == preset("pendulum")
    with pytest.raises(ConfigError, match="unknown preset 'nope'"):
        preset("nope")


@pytest.mark.parametrize(
    "cfg, env_steps_per_iter, iters_per_chunk, num_chunks, replay_capacity",
    [
        # defaults: 16 envs x 1 step = 16 per iteration; 4000 // 16 = 250 iterations per chunk
        # (4000 steps); 20000 / 4000 = 5 chunks; capacity: the run's 20000 steps, below
        # buffer_size.
        (TrainConfig(), 16, 250, 5, 20_000),
        (TrainConfig(total_steps=1_000_000), 16, 250, 250, 100_000),
        # 3 envs x 2 steps = 6; 100 // 6 = 16 iterations (96 steps) per chunk;
        # ceil(1000 / 96) = 11 chunks (1056 steps); capacity 500.
        (
            TrainConfig(
                num_envs=3, steps_per_iter=2, eval_every=100, total_steps=1_000, buffer_size=500
            ),
            6,
            16,
            11,
            500,
        ),
        # eval_every below one iteration: still one iteration (64 steps) per chunk;
        # ceil(100 / 64) = 2 chunks (128 steps); capacity 128, the run's length.
        (
            TrainConfig(num_envs=64, eval_every=10, total_steps=100, buffer_size=1000),
            64,
            1,
            2,
            128,
        ),
        # one step still runs one chunk: 8 envs, 40 // 8 = 5 iterations, 40 steps.
        (TrainConfig(num_envs=8, eval_every=40, total_steps=1), 8, 5, 1, 40),
        # total_steps an exact multiple of a chunk: 1 env, 2000 per chunk, 10 chunks.
        (TrainConfig(**PRESETS["ddpg-pendulum"]), 1, 2_000, 10, 20_000),
    ],
)
def test_derived_quantities(cfg, env_steps_per_iter, iters_per_chunk, num_chunks, replay_capacity):
    assert cfg.env_steps_per_iter == env_steps_per_iter
    assert cfg.iters_per_chunk == iters_per_chunk
    assert cfg.num_chunks == num_chunks
    assert cfg.replay_capacity == replay_capacity
    # The chunks cover total_steps; the run ends at it, rounded up to a whole iteration.
    assert cfg.chunked_steps == num_chunks * iters_per_chunk * env_steps_per_iter >= cfg.run_steps
    assert cfg.run_steps == -(-cfg.total_steps // env_steps_per_iter) * env_steps_per_iter


def test_replay_capacity_follows_the_run_up_to_buffer_size():
    """A ring never has more rows than the run collects: a run extended with --resume
    --total-steps grows it (test_rundir checks that the numbers equal a straight run's)."""
    short, long = TrainConfig(total_steps=4_000), TrainConfig(total_steps=8_000)
    assert (short.replay_capacity, long.replay_capacity) == (4_000, 8_000)
    assert TrainConfig(total_steps=10**6).replay_capacity == TrainConfig().buffer_size
    # a buffer larger than the run is fine (the ring is sampled over its filled part)
    assert validate(dataclasses.replace(SMALL, buffer_size=10 * SMALL.total_steps))


def test_a_ring_smaller_than_one_iteration_is_refused_with_sizes_that_work():
    """16 environments add 16 transitions an iteration: a ring of 10 is refused, naming the
    least size that works (the batch of 256 must fit too) and a larger one; both validate."""
    cfg = TrainConfig(num_envs=16, batch_size=256, buffer_size=10, total_steps=20_000)
    with pytest.raises(ConfigError) as refused:
        validate(cfg)
    message = str(refused.value)
    assert message.startswith("one iteration adds 16 transitions but the replay buffer holds "
                              "only 10: give --buffer-size 256 at least, to hold a batch of "
                              "256 (a ring")  # fmt: skip
    assert "e.g. --buffer-size 16000," in message
    for size in (256, 16000):
        assert validate(dataclasses.replace(cfg, buffer_size=size))
    # 3-step targets over 128 environments read 256 stored rows past a sample: 257 at least
    cfg = TrainConfig(num_envs=128, batch_size=64, n_step=3, buffer_size=100, total_steps=10**5)
    with pytest.raises(ConfigError, match="give --buffer-size 257 at least, as 3-step targets "
                                          "read 256 stored rows past a sample"):
        validate(cfg)
    assert validate(dataclasses.replace(cfg, buffer_size=257))
    # A run of one iteration (10^6 environments, 20k steps) has no larger ring to suggest.
    cfg = TrainConfig(num_envs=10**6, batch_size=256, buffer_size=10, total_steps=20_000)
    with pytest.raises(ConfigError) as refused:
        validate(cfg)
    assert str(refused.value).endswith("give --buffer-size 1000000 at least"), refused.value


def test_agent_config_td3_defaults():
    # TrainConfig's default networks are the pendulum preset's 256-256; hidden_sizes=None
    # leaves the algorithm's own default (TD3: the paper's 400-300).
    assert tuple(agent_config(TrainConfig(algo="td3")).hidden_sizes) == (256, 256)
    agent = agent_config(TrainConfig(algo="td3", hidden_sizes=None))
    assert isinstance(agent, TD3Config)
    assert tuple(agent.hidden_sizes) == (400, 300)
    assert agent.tau == pytest.approx(0.005)
    assert agent.actor_lr == pytest.approx(1e-3)
    assert agent.critic_lr == pytest.approx(1e-3)
    assert agent.discount == pytest.approx(0.99)
    assert agent.policy_noise == pytest.approx(0.2)
    assert agent.noise_clip == pytest.approx(0.5)
    assert agent.policy_freq == 2


def test_agent_config_ddpg_defaults():
    agent = agent_config(TrainConfig(algo="ddpg"))
    assert isinstance(agent, DDPGConfig)
    assert tuple(agent.hidden_sizes) == (256, 256)
    assert agent.actor_lr == pytest.approx(1e-4)
    assert agent.critic_lr == pytest.approx(1e-3)
    assert agent.tau == pytest.approx(1e-2)
    assert agent.discount == pytest.approx(0.99)


@pytest.mark.parametrize("algo, cls", [("td3", TD3Config), ("ddpg", DDPGConfig)])
def test_agent_config_uses_given_values(algo, cls):
    cfg = TrainConfig(
        algo=algo,
        hidden_sizes=(32, 8, 4),
        actor_lr=3e-4,
        critic_lr=2e-4,
        tau=0.25,
        discount=0.9,
        policy_noise=0.3,
        noise_clip=0.7,
        policy_freq=5,
    )
    agent = agent_config(cfg)
    assert isinstance(agent, cls)
    assert tuple(agent.hidden_sizes) == (32, 8, 4)
    assert agent.actor_lr == pytest.approx(3e-4)
    assert agent.critic_lr == pytest.approx(2e-4)
    assert agent.tau == pytest.approx(0.25)
    assert agent.discount == pytest.approx(0.9)
    if algo == "td3":
        assert agent.policy_noise == pytest.approx(0.3)
        assert agent.noise_clip == pytest.approx(0.7)
        assert agent.policy_freq == 5


def test_agent_config_mixes_given_and_default_values():
    # Only the learning rate given: DDPG keeps its own hidden sizes and tau.
    agent = agent_config(TrainConfig(algo="ddpg", actor_lr=5e-4))
    assert agent.actor_lr == pytest.approx(5e-4)
    assert tuple(agent.hidden_sizes) == (256, 256)
    assert agent.tau == pytest.approx(1e-2)
    # Only tau given: TD3 keeps (400, 300) and its actor learning rate.
    agent = agent_config(TrainConfig(algo="td3", tau=0.05, hidden_sizes=None))
    assert agent.tau == pytest.approx(0.05)
    assert tuple(agent.hidden_sizes) == (400, 300)
    assert agent.actor_lr == pytest.approx(1e-3)


def test_ou_params_follow_the_config():
    cfg = TrainConfig(ou_theta=0.2, ou_sigma=0.4, ou_min_sigma=0.1, ou_decay_period=1234)
    params = ou_params(cfg)
    assert params.theta == pytest.approx(0.2)
    assert params.max_sigma == pytest.approx(0.4)
    assert params.min_sigma == pytest.approx(0.1)
    assert params.decay_period == pytest.approx(1234.0)


def test_replay_shards_must_divide_envs_batch_and_capacity():
    from td3_jax.config.schema import ConfigError, TrainConfig, validate

    ok = TrainConfig(num_envs=8, batch_size=64, buffer_size=512, replay_shards=4)
    assert validate(ok) is ok
    for bad in (
        dict(num_envs=6, batch_size=64, buffer_size=512, replay_shards=4),
        dict(num_envs=8, batch_size=66, buffer_size=512, replay_shards=4),
        dict(num_envs=8, batch_size=64, buffer_size=510, replay_shards=4),
        dict(num_envs=8, batch_size=64, buffer_size=512, replay_shards=0),
    ):
        with pytest.raises(ConfigError, match="replay-shards"):
            validate(TrainConfig(**bad))


def test_every_environment_preset_is_made_for_its_environment():
    for env, name in ENV_PRESETS.items():
        assert PRESETS[name]["env"] == env
        assert env_preset(env) == name
    # every preset with an environment of its own is reachable from it (ddpg-pendulum
    # shares Pendulum with the default `pendulum` preset)
    assert {p["env"] for p in PRESETS.values() if "env" in p} == set(ENV_PRESETS)
    assert env_preset("brax/hopper") is None


def test_device_defaults_scale_with_the_device():
    cpu = device_defaults("brax/hopper", accelerator=False)
    gpu = device_defaults("brax/hopper", accelerator=True)
    assert cpu == TrainConfig(env="brax/hopper")
    assert cpu.num_envs <= 64 <= 4096 <= gpu.num_envs
    assert gpu == TrainConfig(**{**PRESETS["ant"], "env": "brax/hopper"})
    assert validate(cpu) and validate(gpu)


@pytest.mark.parametrize("name", ["actor_lr", "critic_lr", "tau", "expl_noise", "ou_sigma"])
@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_non_finite_float_settings_are_refused(name, value):
    with pytest.raises(ConfigError, match=rf"--{name.replace('_', '-')} must be a finite number"):
        validate(TrainConfig(**{name: value}))


@pytest.mark.parametrize(("name", "network"), [("actor_lr", "actor"), ("critic_lr", "critic")])
def test_a_learning_rate_of_zero_is_refused_and_a_tiny_one_accepted(name, network):
    """At 0 the network never changes: a run trained and exited 0 having learnt nothing."""
    flag = "--" + name.replace("_", "-")
    with pytest.raises(ConfigError, match=rf"^{flag} must be positive: at 0 the {network} never"):
        validate(TrainConfig(**{name: 0.0}))
    assert validate(TrainConfig(**{name: 1e-12}))


def test_a_sweep_value_of_zero_for_a_learning_rate_is_refused(capsys, tmp_path):
    """A sweep's members are checked as runs of their own: --sweep-critic-lr 0 1e-3 is refused
    in one line naming the sweep's flag, before anything is built."""
    from support import main

    out = tmp_path / "run"
    args = ["sweep", "--sweep-critic-lr", "0", "1e-3", "--out", str(out)]
    code, _, err = main(args, capsys)
    assert code == 2
    assert err.strip().endswith("--sweep-critic-lr must be positive: at 0 the critic never learns")
    assert not out.exists()


def test_the_replay_ring_never_has_more_rows_than_the_run_collects():
    """A tiny run of a robot preset (8.4M-row ring) used to allocate the whole ring: 26 GB."""

    full = preset("t1")
    t1 = dataclasses.replace(full, num_envs=8, total_steps=2048, eval_every=1024,
                             warmup_steps=0, batch_size=64, replay_shards=1)  # fmt: skip
    assert t1.run_steps == 2048 and t1.replay_capacity == 2048
    assert full.replay_capacity == min(full.buffer_size, full.run_steps)
    rounded = dataclasses.replace(t1, total_steps=2049)  # rounded up to whole chunks: 3072
    assert rounded.replay_capacity == 3072
    assert dataclasses.replace(t1, buffer_size=1000).replay_capacity == 1000


def test_a_warm_up_as_long_as_the_run_is_refused():
    """A run whose random warm-up covers all its steps would exit 0 having learnt nothing."""
    with pytest.raises(ConfigError, match=r"--warmup-steps 20000 is not below the 20000 env"):
        validate(TrainConfig(total_steps=20_000, warmup_steps=20_000))
    with pytest.raises(ConfigError, match=r"learns; try --warmup-steps 10000 or a longer"):
        validate(TrainConfig(total_steps=20_000, warmup_steps=30_000))
    validate(TrainConfig(total_steps=20_000, warmup_steps=10_000))  # as the tip says
    validate(TrainConfig(total_steps=20_000, warmup_steps=19_999))
    validate(TrainConfig(total_steps=64, warmup_steps=100, updates_per_iter=0))  # no learning asked


@pytest.mark.parametrize(("seed", "seeds"), [(-1, 1), (2**32, 1), (2**32 - 2, 3), (10**20, 1)])
def test_a_seed_jax_cannot_tell_apart_is_refused(seed, seeds):
    """JAX keys hold 32 bits of a seed: --seed 4294967296 trained seed 0's run again, and
    10**20 ended in an OverflowError traceback."""
    with pytest.raises(ConfigError, match=rf"^--seed {seed}.* must be in \[0, 4294967295\]"):
        validate(TrainConfig(seed=seed, seeds=seeds))
    assert validate(TrainConfig(seed=2**32 - 3, seeds=3))


def test_a_run_longer_than_its_int32_counters_is_refused():
    """The env-step and update counters are int32 in the compiled program: past 2**31 - 1 the
    env steps wrapped negative and the run went back to its random warm-up, unannounced."""
    with pytest.raises(ConfigError, match=r"^--total-steps 2,147,483,648 is more than the "
                                          r"2,147,483,647 env steps"):  # fmt: skip
        validate(TrainConfig(total_steps=2**31, eval_every=2**31))
    with pytest.raises(ConfigError, match=r"\(run as 2,147,484,000: whole chunks\)"):
        validate(TrainConfig(total_steps=2**31 - 100, eval_every=4000))
    with pytest.raises(ConfigError, match="gradient updates, more than the 2,147,483,647"):
        validate(TrainConfig(total_steps=2**30, eval_every=2**20, updates_per_iter=64))
    # one iteration past the counters names the environments, not --total-steps
    big = "100,000,000,000,000,000,000"
    said = f"^one iteration of --num-envs {big} x --steps-per-iter 1 is {big} env steps, more than"
    with pytest.raises(ConfigError, match=said + " the 2,147,483,647 a run can count"):
        validate(TrainConfig(num_envs=10**20))
    longest = 2**31 - 1 - (2**31 - 1) % 16  # whole iterations of 16 environments
    assert validate(TrainConfig(total_steps=longest, eval_every=longest))


@pytest.mark.parametrize(("setting", "value", "says"), [
    ("tau", -0.5, "--tau must be in (0, 1], got -0.5"),
    ("tau", 0.0, "--tau must be in (0, 1], got 0.0"),
    ("return_bound", -1.0, "--return-bound must be positive, got -1.0"),
    ("return_bound", 0.0, "--return-bound must be positive, got 0.0"),
    ("max_grad_norm", -1.0, "--max-grad-norm must be positive, got -1.0"),
    ("discount", -0.1, "--discount must be in [0, 1], got -0.1"),
])  # fmt: skip
def test_a_setting_with_a_range_says_it_on_either_side(setting, value, says):
    """--tau -0.5 said 'must not be negative' where --tau 0 said 'must be in (0, 1]'."""
    with pytest.raises(ConfigError) as raised:
        validate(TrainConfig(**{setting: value}))
    assert str(raised.value) == says


def test_an_unknown_env_backend_names_brax_backends_and_playground_physics_flag():
    with pytest.raises(ConfigError) as raised:
        validate(TrainConfig(env="brax/ant", env_backend="mjxx"))
    assert str(raised.value) == (
        "unknown --env-backend 'mjxx'; Brax's backends are generalized, mjx, positional and "
        "spring (Playground's physics is --impl warp or jax)"
    )


def test_typed_flags_that_change_nothing_are_named_with_the_reason():
    from td3_jax.config.schema import idle_flags

    ou = TrainConfig(exploration="ou")
    assert idle_flags(ou, {"expl_noise", "ou_sigma"}) == [
        "--expl-noise does nothing with --exploration ou"
    ]
    plain = TrainConfig(critic="plain")
    assert idle_flags(plain, {"num_atoms", "v_max"}) == [
        "--num-atoms, --v-max do nothing with --critic plain"
    ]
    ddpg = TrainConfig(algo="ddpg", env="brax/ant")
    assert idle_flags(ddpg, {"policy_noise", "env_backend"}) == [
        "--policy-noise does nothing with --algo ddpg"
    ]
    assert idle_flags(TrainConfig(), {"env_backend"}) == [
        "--env-backend does nothing with --env gymnax/Pendulum-v1"
    ]
    assert idle_flags(TrainConfig(env="brax/ant"), {"critic_obs_key"}) == [
        "--critic-obs-key does nothing with --env brax/ant (its observations are one array, "
        "not a dict)"
    ]
    assert idle_flags(TrainConfig(), {"actor_obs_key"}) == [
        "--actor-obs-key does nothing with --env gymnax/Pendulum-v1 (its observations are one "
        "array, not a dict)"
    ]
    robot = TrainConfig(env="playground/T1JoystickFlatTerrain")  # (dict observations: used)
    assert idle_flags(robot, {"actor_obs_key", "critic_obs_key", "menagerie"}) == []
    assert idle_flags(TrainConfig(env="brax/ant"), {"menagerie"}) == [
        "--menagerie does nothing with --env brax/ant (it loads no robot)"
    ]
    # An option typed as None turns a preset's value off: not idle (`--preset g1
    # --max-weight-norm None`); a typed value beside its option off still is.
    assert idle_flags(TrainConfig(max_weight_norm=None), {"max_weight_norm"}) == []
    assert idle_flags(TrainConfig(lr_final_fraction=0.5), {"lr_final_fraction"}) == [
        "--lr-final-fraction does nothing with --lr-schedule constant"
    ]
    # The same values from a preset (not typed) say nothing; used flags say nothing.
    assert idle_flags(plain, set()) == []
    assert idle_flags(TrainConfig(critic="distributional"), {"v_max", "expl_noise"}) == []


@pytest.mark.parametrize(("args", "says"), [
    (["--sweep-actor-lr", "1e-3", "1e-3"],
     "--sweep-actor-lr lists 0.001 more than once: each value trains once"),
    (["--sweep-actor-lr", "1e-3", "3e-4", "--actor-lr", "3e-4"],
     "--actor-lr and --sweep-actor-lr both given: the swept values replace it"),
])  # fmt: skip
def test_a_sweep_that_repeats_a_value_or_a_swept_flag_is_one_line(args, says, tmp_path, capsys):
    from support import assert_one_line_error, main

    out = tmp_path / "run"
    code, _, err = main(["sweep", *args, "--out", str(out)], capsys)
    assert_one_line_error(code, err, says)
    assert not out.exists()


def test_playgrounds_physics_names_as_a_brax_backend_are_one_clear_error():
    """--env-backend jax/warp name Playground's physics (an alias of --impl): with a Brax
    environment they were Brax's own traceback; now one line naming Brax's backends."""
    for backend in ("jax", "warp"):
        cfg = TrainConfig(env="brax/inverted_pendulum", env_backend=backend)
        with pytest.raises(ConfigError, match=f"--env-backend {backend} is Playground's physics"
                                              r" \(--impl\); Brax's backends are generalized, "
                                              "mjx, positional and spring"):  # fmt: skip
            validate(cfg)
    validate(TrainConfig(env="brax/inverted_pendulum", env_backend="spring"))


def test_a_seed_whose_members_pass_the_largest_is_said_with_the_last_seed():
    """``--seed 4294967295 --seeds 2`` trains seeds 4294967295 and 4294967296, the second past
    JAX's 32 bits: the line names it (it said "and the 2 seeds from it")."""
    config.check_seed(4294967294, members=2)  # (4294967294 and 4294967295: fine)
    with pytest.raises(ConfigError) as refused:
        config.check_seed(4294967295, members=2)
    assert str(refused.value).startswith(
        "--seed 4294967295 and the seed after it (to 4294967296) must be in [0, 4294967295]"
    )
    with pytest.raises(ConfigError, match=r"^--seed 4294967290 and the 7 seeds after it \(to "):
        config.check_seed(4294967290, members=8)


def test_warp_physics_splits_over_devices_when_both_batches_divide():
    """MuJoCo Warp on two devices: each steps its own training and evaluation environments,
    so --eval-envs must divide too (JAX physics needs only --num-envs to)."""
    warp = dataclasses.replace(preset("t1"), impl="warp")
    assert warp.num_envs % 2 == 0 and warp.eval_envs % 2 == 0
    assert validate(warp, devices=2) == warp
    odd = dataclasses.replace(warp, eval_envs=129)
    with pytest.raises(ConfigError, match=r"^--eval-envs \(129\) must be divisible by the "
                                          r"number of devices \(2\)$"):  # fmt: skip
        validate(odd, devices=2)
    assert validate(dataclasses.replace(odd, impl="jax"), devices=2).eval_envs == 129
