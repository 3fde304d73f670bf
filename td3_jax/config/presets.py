"""The named presets (``td3-jax presets``, ``--preset NAME``) and the settings a run without
one starts from: each preset is a dict of :class:`~td3_jax.config.schema.TrainConfig` fields, with
the measurements that chose its values beside it."""

from __future__ import annotations

import difflib

from td3_jax.config.schema import ConfigError, TrainConfig
from td3_jax.envs import menagerie

# Shared by the GPU presets (measured on one H200, brax/ant unless noted, 90 s budgets with
# compile, single seeds; benchmarks/results/2026-11-21-tuning and BENCHMARKS.md):
# * num_envs 4096: MJX ant steps 1.52M/s at 4096 envs against 0.55M/s at 1024; 2048 envs learnt
#   more slowly per second (2882 against 3706 at 90 s), 8192 envs with batch 16384 no faster.
# * n_step 3: the largest single gain (3706 against 1919 for 1-step at 90 s; 5-step 3148).
# * 16 updates of batch 8192 per iteration (a replay ratio of 32 sampled rows per new
#   transition): 4037 at 92 s against 3706 with 8; 32 updates of 4096 were slower (2939).
# * expl_noise 0.2: faster early on ant (2417 against 2258 near 58 s) and better on humanoid
#   (5313 against 4843 at 90 s) and halfcheetah.
# * networks 256-256, Adam 3e-4, tau 0.005 (0.01 and 0.02 were not better), discount 0.99
#   (0.97 was worse), a 409,600-step (100-iteration) random warm-up, a 4M-transition ring.
_GPU_LOCOMOTION = dict(
    algo="td3",
    num_envs=4096,
    total_steps=13 * 1_638_400,  # 21.3M: the whole chunks that 20M ran as (13 evaluations)
    updates_per_iter=16,
    batch_size=8192,
    n_step=3,
    expl_noise=0.2,
    warmup_steps=409_600,
    eval_every=1_638_400,
    eval_envs=128,
    buffer_size=4_000_000,
    hidden_sizes=(256, 256),
    actor_lr=3e-4,
    critic_lr=3e-4,
)

# MuJoCo Playground locomotion (humanoids), from FastTD3's published recipe (Seo et al. 2025;
# its hyperparams.py MuJoCoPlaygroundArgs and T1/G1 joystick entries; ../shared/anchors): 1024
# environments, batch 32768, 2 updates per vectorised step, gamma 0.97, tau 0.1, Adam 3e-4,
# target smoothing noise 0.001 (clip 0.5), 1-step targets, learning from 10 steps per
# environment, a ring of 10,240 steps per environment, 100k steps per environment, pushes and
# domain randomisation off, the actor on 'state' and the critics on 'privileged_state'; two C51
# critics (101 atoms on [-10, 10]) with the actor on the lower mean, AdamW with weight decay
# 0.1, per-environment exploration scales drawn from [0.001, 0.4], critics 1024-512-256 and
# actor 512-256-128, the online actor (no target actor) for target actions, bf16 matmuls.
# With these settings (BENCHMARKS.md, 2026-11-22 session 3, one H200, compile included):
# T1 33.6 at 428 s and 34.7 at 491 s (FastTD3's published 30-minute 33.8); G1 7.7 at 481 s,
# bound by the physics rate at 1024 envs (24.7k env steps/s). Go1 keeps these (with its own
# changes below); the humanoids' presets change their size (_HUMANOID_JOYSTICK).
_PLAYGROUND_LOCOMOTION = dict(
    algo="td3",
    num_envs=1024,
    total_steps=102_400_000,
    updates_per_iter=2,
    batch_size=32_768,
    buffer_size=10_485_760,
    warmup_steps=10_240,
    eval_every=1_024_000,
    eval_envs=256,
    discount=0.97,
    tau=0.1,
    actor_lr=3e-4,
    critic_lr=3e-4,
    policy_noise=0.001,
    noise_clip=0.5,
    expl_noise=0.2,
    expl_noise_min=0.001,
    expl_noise_max=0.4,
    hidden_sizes=(1024, 512, 256),
    actor_hidden_sizes=(512, 256, 128),
    critic_hidden_sizes=(1024, 512, 256),
    critic="distributional",
    num_atoms=101,
    v_min=-10.0,
    v_max=10.0,
    weight_decay=0.1,
    target_actor=False,
    # FastTD3's rules: target critics averaged after every critic update, and the C51 target
    # head chosen by the lower mean of the projected distributions.
    target_update="every_update",
    c51_target_head="projected",
    precision="bfloat16",
    # cuBLAS for the matmuls (XLA's Triton GEMM off): 1.23x the C51 update and, with the C51
    # projection by run sums, 1.28x the T1 and G1 loops on an H100 (about 1.12x of it from
    # cuBLAS; BENCHMARKS.md, 2026-11-25 sixth session). A speed setting: the same
    # computation, rounded differently.
    matmuls="cublas",
    pushes="off",
    domain_randomization=False,
    # A checkpoint holds the whole train state, the replay ring included: 15-19 GB here (G1's
    # ring of 8.4M transitions is 15.5 GB), so one is kept (two on disk while the next is
    # written) rather than three.
    keep_checkpoints=1,
)

# T1 and G1: 4096 environments with 8 updates per vectorised step (FastTD3's ratio of updates
# to env steps, 2 per 1024, kept), 128 evaluation episodes every 4,096,000 steps (below) and a
# ring of 8,388,608 transitions (2048 steps per environment; warm-up and run length stay in
# steps, so per environment they are a quarter of FastTD3's). MJX steps 4096 humanoids far
# faster than 1024 (G1 39k against 24.7k env steps/s in the loop; T1 50k against 33k), and the
# 8 updates of 32768 fit beside them. Measured with these settings (evaluations every 2,048,000
# steps then), one run per task on one H200 (BENCHMARKS.md, 2026-11-22 session 4, compile
# included): G1 7.7 at 314 s, 12.3 at 365 s, 14.5 at 417 s (1024 envs: 3.3 at 399 s, 7.7 at
# 481 s); T1 27.4 at 320 s, 31.7 at 361 s, 34.2 at 402 s (1024 envs: 26.6 at 301 s, 29.6 at
# 364 s, 33.6 at 428 s). Other Playground humanoids start from `t1` (robot_preset); they were
# not measured with it.
# An evaluation (1000 steps of 128 environments, bound by the latency of each MJX step) takes
# 15.2 s on G1 while the loop trains at 55k env steps/s (BENCHMARKS.md, 2026-11-22 session 6):
# every 2,048,000 steps it cost 29% of the wall-clock, every 4,096,000 steps (about 75 s of
# training) it costs 17%. The early evaluation is off: after 512k steps it says nothing yet
# (-7 on G1) and costs those 15 s. On MuJoCo Warp an evaluation took 8-9 s (14-15%, the
# same latency bound), so the evaluation worlds are stepped inside the chunk
# (--eval-in-chunk: 128 more worlds beside 4096 training ones; training unchanged, tested):
# a chunk of 4.096M steps is 1000 iterations, one episode, so each record holds the round
# whose policy is that of the chunk's start.
_HUMANOID_JOYSTICK = dict(
    _PLAYGROUND_LOCOMOTION,
    num_envs=4096,
    updates_per_iter=8,
    eval_envs=128,
    eval_every=4_096_000,
    eval_in_chunk=True,
    early_evaluation=False,
    buffer_size=8_388_608,
)

# G1 on Warp: 128 constraints per environment, not Playground's 90 (random warm-up actions
# reached 94 on an H100, benchmarks/warp_buffers.py; T1 stays under its 80 at 59), and
# FlashSAC's critic layout (two residual blocks of width 256) with no AdamW decay, and bounded
# weights (see the g1 and g1-rough presets).
_G1 = dict(
    _HUMANOID_JOYSTICK,
    njmax=128,
    critic_network="residual",
    critic_hidden_sizes=(256, 256),
    weight_decay=0.0,
    max_weight_norm=1.0,
)

PRESETS: dict[str, dict] = {
    # The seed DDPG tutorial's experiment: one Pendulum, OU noise, batch 128, 100 episodes of
    # 200 steps, one update per step from the moment the buffer holds a batch.
    "seed-ddpg-pendulum": dict(
        env="gymnax/Pendulum-v1",
        algo="ddpg",
        num_envs=1,
        total_steps=20_000,
        updates_per_iter=1,
        batch_size=128,
        buffer_size=50_000,
        warmup_steps=128,
        eval_every=2_000,
        eval_envs=10,
        exploration="ou",
        normalize_obs=False,
    ),
    # The TD3 paper: one environment, 25k-step random warm-up... scaled to its published recipe.
    "td3-classic": dict(
        algo="td3",
        num_envs=1,
        total_steps=1_000_000,
        updates_per_iter=1,
        batch_size=256,
        buffer_size=1_000_000,  # the whole run, as in the paper
        warmup_steps=25_000,
        eval_every=5_000,
        eval_envs=10,
        expl_noise=0.1,
        hidden_sizes=(256, 256),
        actor_lr=3e-4,
        critic_lr=3e-4,
        normalize_obs=False,
    ),
    # The default (TrainConfig's own values; what `td3-jax train` runs): TD3 on Pendulum with a
    # handful of environments, Adam 1e-3 (TD3's default), a 100k-transition ring (the run never
    # fills it, so it samples like an unbounded buffer; a checkpoint stays a few MB). 20k steps:
    # about a minute on 2 CPU cores; measured returns at 20k for seeds 0-4: -107, -158, -130,
    # -178, -120 (about -1450 at 4k; 40k steps end near -150 too).
    "pendulum": dict(
        env="gymnax/Pendulum-v1",
        algo="td3",
        num_envs=16,
        total_steps=20_000,
        updates_per_iter=8,
        batch_size=256,
        buffer_size=100_000,
        warmup_steps=2_000,
        eval_every=4_000,
        hidden_sizes=(256, 256),
    ),
    # Small MJX task that learns on a CPU in minutes, with the environment's own 1000-step
    # episodes (returns up to 1000; `td3-jax train --env brax/inverted_pendulum` uses it).
    # Measured on 2 CPU cores, seeds 0-2, 20k steps: 16 envs with 32 updates per iteration
    # reached 1000 on every seed from 16k steps on (2026-11-24, with the ring sized to the run:
    # per seed at 4k, 8k, 12k: 177/1000/51, 112/93/150, 455/47/549; earlier, with a 1M-row
    # ring, from 12k on). With 16 updates per iteration one seed of three
    # ended at 105 of 200 (200-step episodes), with 3-step targets one at 58; the former
    # 128-env setting (200-step episodes, 102k steps) reached 109 of 1000 after 20k steps.
    "inverted-pendulum": dict(
        env="brax/inverted_pendulum",
        algo="td3",
        num_envs=16,
        total_steps=20_480,
        updates_per_iter=32,
        batch_size=256,
        warmup_steps=1_024,
        eval_every=4_096,
        eval_envs=16,
        hidden_sizes=(64, 64),
        actor_lr=1e-3,
        critic_lr=1e-3,
    ),
    # GPU defaults for Brax locomotion with thousands of environments (see _GPU_LOCOMOTION).
    "ant": dict(_GPU_LOCOMOTION, env="brax/ant"),
    # MJX halfcheetah steps slowly (about 53k env steps/s at 4096 envs), so the run is bound by
    # environment steps: 1024 envs with 32 updates per iteration learn far more per second
    # (6078 at 101 s against 976 at 99 s with 4096 envs and 16 updates; 2774 with 1024 and 16).
    "halfcheetah": dict(
        _GPU_LOCOMOTION, env="brax/halfcheetah", num_envs=1024, updates_per_iter=32
    ),
    "humanoid": dict(
        _GPU_LOCOMOTION, env="brax/humanoid", total_steps=19 * 1_638_400, hidden_sizes=(512, 256)
    ),
    # MuJoCo Playground's DM Control CheetahRun (pure-JAX MJX implementation), same settings.
    "cheetah-run": dict(_GPU_LOCOMOTION, env="playground/CheetahRun"),
    # Playground humanoids (see _PLAYGROUND_LOCOMOTION): Booster T1 and Unitree G1 joysticks.
    "t1": dict(_HUMANOID_JOYSTICK, env="playground/T1JoystickFlatTerrain"),
    # G1 flat: FlashSAC's critic layout (two residual blocks of width 256, --critic-network
    # residual) and no weight decay (AdamW's decay 0, not 0.1), the two changes that lifted G1
    # at 53.2M env steps over 3 seeds each, and bounded weights (--max-weight-norm 1). The
    # residual critics with decay 0.1: 38.2, 37.3, 38.1 (IQM 38.0) against the plain
    # 1024-512-256 critics' 36.2, 36.4, 36.5 (IQM 36.4); then decay 0: 39.1, 38.8, 39.5 (IQM
    # 39.1; FlashSAC 39.9), every seed above its decay-0.1 run (BENCHMARKS.md, seventh to
    # fifteenth sessions). The residual critics cost speed: the loop runs at 73-78K env steps/s
    # against 102-108K on an H200, so FastTD3's final 31.4 comes at 525-630 s from launch on
    # fresh hosts (fourteenth and fifteenth sessions), and the curve may dip before it settles.
    # The plain critics (`--critic-network mlp --critic-hidden-sizes 1024 512 256`) are the
    # faster start. Bounded weights (every unit's incoming weights at most norm 1 after each
    # step, about their initial norm, as FlashSAC keeps its weights on the unit sphere): 39.4,
    # 39.2, 39.5 (IQM 39.4) on the same seeds against 39.1, 38.8, 39.5, each seed level or above
    # by 0.1-0.3 (no worse, within the evaluation's noise), and faster early (31.4 passed with
    # the policies of 16.4-20.5M steps against 20.5-28.7M; nineteenth session); None turns it
    # off (G1 rough: see g1-rough).
    "g1": dict(_G1, env="playground/G1JoystickFlatTerrain"),
    # Rough terrain (Playground's heightfield scenes, feet-only contacts), with 128 constraints
    # per environment as a margin on Warp. T1 rough is the flat preset unchanged: 34.8, 35.2,
    # 34.4 (IQM 34.8) at 53.2M env steps against FlashSAC's 34.6. G1 rough is the `g1` preset on
    # rough terrain. Its residual critics with decay 0.1 ended 34.1, 33.2, 33.1 (IQM 33.4)
    # against the plain critics' 29.0, 30.5, 30.9 (IQM 30.3); decay 0 then ended 35.0, 34.0,
    # 33.5 (IQM 34.1; FlashSAC 34.1), every seed above its decay-0.1 run, at 46-51K env steps/s
    # against the plain critics' 56-62K, but slower early (FastTD3's final 27.7 with the
    # policies of 24.6-36.9M steps). The weight bound then ended 34.9, 34.1, 33.9 (IQM 34.2; no
    # worse) and learned much faster early: 28.4-30.4 with the policies of 20.5M steps against
    # 16.9-19.0, so 27.7 passed with the policies of 20.5M steps against 24.6-36.9M (642-648 s
    # from launch against 784-1065 s, about 60 s of it a faster start-up; BENCHMARKS.md, seventh
    # to twentieth sessions). Not tuned further for rough terrain.
    "t1-rough": dict(_HUMANOID_JOYSTICK, env="playground/T1JoystickRoughTerrain", njmax=128),
    "g1-rough": dict(_G1, env="playground/G1JoystickRoughTerrain"),
    # Unitree Go1: FastTD3's Go1 entries change 8 updates per step, exploration scales in
    # [0.2, 0.8], smoothing noise 0.2, 50k steps per environment; its kicks keep the task's
    # default (off).
    "go1": dict(
        _PLAYGROUND_LOCOMOTION,
        env="playground/Go1JoystickFlatTerrain",
        total_steps=51_200_000,
        updates_per_iter=8,
        expl_noise=0.5,
        expl_noise_min=0.2,
        expl_noise_max=0.8,
        policy_noise=0.2,
        pushes="default",
    ),
}


# The preset a run starts from when it names an environment but no --preset.
ENV_PRESETS: dict[str, str] = {
    "gymnax/Pendulum-v1": "pendulum",
    "brax/inverted_pendulum": "inverted-pendulum",
    "brax/ant": "ant",
    "brax/halfcheetah": "halfcheetah",
    "brax/humanoid": "humanoid",
    "playground/CheetahRun": "cheetah-run",
    "playground/T1JoystickFlatTerrain": "t1",
    "playground/G1JoystickFlatTerrain": "g1",
    "playground/T1JoystickRoughTerrain": "t1-rough",
    "playground/G1JoystickRoughTerrain": "g1-rough",
    "playground/Go1JoystickFlatTerrain": "go1",
}


def env_preset(env: str) -> str | None:
    """The name of the preset made for ``env`` (``None`` when there is none)."""
    return ENV_PRESETS.get(env)


def device_defaults(env: str, accelerator: bool) -> TrainConfig:
    """Settings for an environment without a preset, scaled to the device.

    On an accelerator (GPU/TPU) the GPU locomotion settings (4096 environments, 16 updates of
    batch 8192 per iteration, 3-step targets), for a Playground robot those of
    :func:`robot_preset`; on a CPU the defaults, a handful of environments
    (those of the ``pendulum`` preset).
    """
    robot = robot_preset(env)
    if accelerator and robot:
        return TrainConfig(**{**PRESETS[robot], "env": env})
    if accelerator:
        return TrainConfig(**{**_GPU_LOCOMOTION, "env": env})
    return TrainConfig(env=env)


def robot_preset(env: str) -> str | None:
    """The preset a Playground robot task without its own starts from on an accelerator:
    ``go1`` for the quadrupeds, ``t1`` for the humanoids (``None`` for other environments).
    Only T1, G1 and Go1 were measured with their presets; the others start from them untuned."""
    source, _, task = env.partition("/")
    if source != "playground":
        return None
    try:
        folder, _ = menagerie.robot(task)
    except KeyError:
        return None
    return "go1" if folder in menagerie.QUADRUPED_FOLDERS else "t1"


def preset(name: str | None) -> TrainConfig:
    """The config of a named preset (the defaults for ``None``); a :class:`ConfigError` for an
    unknown name gives the closest names, else every one."""
    if name is None:
        return TrainConfig()
    if name not in PRESETS:
        close = difflib.get_close_matches(name, list(PRESETS), n=2, cutoff=0.6)
        if close:
            raise ConfigError(f"unknown preset {name!r}; did you mean {' or '.join(close)}? "
                              "(`td3-jax presets` lists them with their settings)")  # fmt: skip
        raise ConfigError(f"unknown preset {name!r}; known: {', '.join(PRESETS)}")
    return TrainConfig(**PRESETS[name])


__all__ = [
    "ENV_PRESETS",
    "PRESETS",
    "device_defaults",
    "env_preset",
    "preset",
    "robot_preset",
]
