"""The named presets (``td3-jax presets``, ``--preset NAME``) and the settings a run without
one starts from.

Presets are data: each is a dict of :class:`~td3_jax.config.schema.TrainConfig` fields that
differ from TrainConfig's defaults, written as a shared base (:data:`GPU_LOCOMOTION`,
:data:`PLAYGROUND_LOCOMOTION`, :data:`HUMANOID_JOYSTICK`, :data:`G1`) plus the preset's own
overrides. Why each value is what it is, with the measurements, is in docs/benchmarks.md
(section "Why the presets are what they are"), which each comment below names.
"""

from __future__ import annotations

import difflib
import sys
from typing import Any

from td3_jax.config.schema import ConfigError, TrainConfig
from td3_jax.envs import menagerie

# docs/benchmarks.md#brax-locomotion-presets
GPU_LOCOMOTION: dict[str, Any] = dict(
    algo="td3",
    num_envs=4096,
    total_steps=13 * 1_638_400,  # 13 whole chunks of eval_every
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

# docs/benchmarks.md#playground-robot-presets (FastTD3's recipe)
PLAYGROUND_LOCOMOTION: dict[str, Any] = dict(
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
    target_update="every_update",
    c51_target_head="projected",
    precision="bfloat16",
    matmuls="cublas",
    pushes="off",
    domain_randomization=False,
    keep_checkpoints=1,
)

# docs/benchmarks.md#playground-robot-presets (4096 environments)
HUMANOID_JOYSTICK: dict[str, Any] = dict(
    PLAYGROUND_LOCOMOTION,
    num_envs=4096,
    updates_per_iter=8,
    eval_envs=128,
    eval_every=4_096_000,
    eval_in_chunk=True,
    early_evaluation=False,
    buffer_size=8_388_608,
)

# docs/benchmarks.md#g1-presets
G1: dict[str, Any] = dict(
    HUMANOID_JOYSTICK,
    njmax=128,
    critic_network="residual",
    critic_hidden_sizes=(256, 256),
    weight_decay=0.0,
    max_weight_norm=1.0,
)

_CURRENT: dict[str, dict[str, Any]] = {
    # docs/benchmarks.md#cpu-presets
    "ddpg-pendulum": dict(
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
    # docs/benchmarks.md#cpu-presets (the TD3 paper's recipe)
    "td3-classic": dict(
        algo="td3",
        num_envs=1,
        total_steps=1_000_000,
        updates_per_iter=1,
        batch_size=256,
        buffer_size=1_000_000,
        warmup_steps=25_000,
        eval_every=5_000,
        eval_envs=10,
        expl_noise=0.1,
        hidden_sizes=(256, 256),
        actor_lr=3e-4,
        critic_lr=3e-4,
        normalize_obs=False,
    ),
    # docs/benchmarks.md#cpu-presets (what `td3-jax train` runs with no flag)
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
    # docs/benchmarks.md#cpu-presets
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
    # docs/benchmarks.md#brax-locomotion-presets
    "ant": dict(GPU_LOCOMOTION, env="brax/ant"),
    "halfcheetah": dict(
        GPU_LOCOMOTION, env="brax/halfcheetah", num_envs=1024, updates_per_iter=32
    ),
    "humanoid": dict(
        GPU_LOCOMOTION, env="brax/humanoid", total_steps=19 * 1_638_400, hidden_sizes=(512, 256)
    ),
    "cheetah-run": dict(GPU_LOCOMOTION, env="playground/CheetahRun"),
    # docs/benchmarks.md#t1-flat and #t1-rough
    "t1": dict(HUMANOID_JOYSTICK, env="playground/T1JoystickFlatTerrain"),
    "t1-rough": dict(HUMANOID_JOYSTICK, env="playground/T1JoystickRoughTerrain", njmax=128),
    # docs/benchmarks.md#g1-flat and #g1-rough
    "g1": dict(G1, env="playground/G1JoystickFlatTerrain"),
    "g1-rough": dict(G1, env="playground/G1JoystickRoughTerrain"),
    # docs/benchmarks.md#go1-preset (FastTD3's Go1 entries)
    "go1": dict(
        PLAYGROUND_LOCOMOTION,
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

#: Former preset names and the preset each now names: ``--preset OLD`` still runs it, with one
#: line on stderr saying so (:func:`preset`).
RENAMED: dict[str, str] = {"seed-ddpg-pendulum": "ddpg-pendulum"}

#: The names of the presets (former names left out: :data:`RENAMED`).
NAMES: tuple[str, ...] = tuple(_CURRENT)

#: Every preset by name, its former names included (the same settings), so that a command
#: line that offers these names as its choices takes the former ones too.
PRESETS: dict[str, dict[str, Any]] = {
    **_CURRENT, **{old: _CURRENT[new] for old, new in RENAMED.items()}
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
        return TrainConfig(**{**GPU_LOCOMOTION, "env": env})
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


def renamed_note(name: str) -> str | None:
    """The line saying that ``name`` is a former preset name and what it is called now
    (``None`` for any other name)."""
    if name not in RENAMED:
        return None
    return (f"td3-jax: preset {name!r} was renamed {RENAMED[name]!r} (the old name still "
            "works)")  # fmt: skip


def preset(name: str | None) -> TrainConfig:
    """The config of a named preset (the defaults for ``None``); a former name (:data:`RENAMED`)
    gives its preset and prints :func:`renamed_note` on stderr; a :class:`ConfigError` for an
    unknown name gives the closest names, else every one."""
    if name is None:
        return TrainConfig()
    if name not in PRESETS:
        close = difflib.get_close_matches(name, list(NAMES), n=2, cutoff=0.6)
        if close:
            raise ConfigError(f"unknown preset {name!r}; did you mean {' or '.join(close)}? "
                              "(`td3-jax presets` lists them with their settings)")  # fmt: skip
        raise ConfigError(f"unknown preset {name!r}; known: {', '.join(NAMES)}")
    note = renamed_note(name)
    if note:
        print(note, file=sys.stderr, flush=True)
    return TrainConfig(**PRESETS[name])


__all__ = [
    "ENV_PRESETS",
    "G1",
    "GPU_LOCOMOTION",
    "HUMANOID_JOYSTICK",
    "NAMES",
    "PLAYGROUND_LOCOMOTION",
    "PRESETS",
    "RENAMED",
    "device_defaults",
    "env_preset",
    "preset",
    "renamed_note",
    "robot_preset",
]
