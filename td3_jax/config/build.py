"""The one adapter from a :class:`~td3_jax.config.schema.TrainConfig` (every setting of a run, as
the CLI takes them) to what the training program takes.

The program (:mod:`td3_jax.core.training`, :mod:`td3_jax.core.population`,
:mod:`td3_jax.runner.sharding`) never sees a config: it takes an environment, a static
:class:`~td3_jax.core.training.TrainSpec` and the traced
:class:`~td3_jax.core.training.Hyperparams`. This module makes them, and is where each setting is
mapped onto them (``--critic distributional`` onto the agent's atoms, ``--ou-min-sigma`` onto the OU
decay, ``--seeds`` and ``--sweep-*`` onto members, ...):

* the agent: :func:`agent_config`, :func:`agent_options`, :func:`agent_settings`,
  :func:`agent_spec`;
* the environment: :func:`env_options`, :func:`make_env`, :func:`bind_environment`;
* the program of one run: :func:`make_spec`, :func:`hyperparams` (with :func:`ou_params`),
  and the whole run as a function of a key, :func:`make_train` (or :func:`make_trainer`, the
  steps with spec and hyperparameters bound);
* a population: :func:`members` (seeds times sweep values), :func:`member_hyperparams` and
  :func:`make_population`.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
import re
import warnings
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from td3_jax import envs
from td3_jax.common.errors import ConfigError, outside_stacklevel
from td3_jax.common.keywords import fields_meant, parameters_named
from td3_jax.config.schema import (
    SWEEPABLE,
    SWITCHED_ON_BY_THEIR_FLAG,
    TrainConfig,
    check_is_config,
    eval_every_within_run,
    flag,
    flag_pattern,
    unused_settings,
    validate,
)
from td3_jax.core import actor_critic as ac
from td3_jax.core import population as pop
from td3_jax.core import replay, training
from td3_jax.core.noise import OUParams
from td3_jax.core.td3 import DDPGConfig, TD3Config
from td3_jax.core.types import Agent, Metrics, PRNGKey, Transition

__all__ = [
    "Trainer",
    "agent_config",
    "agent_options",
    "agent_settings",
    "agent_spec",
    "bind_environment",
    "env_options",
    "hyperparams",
    "make_env",
    "make_population",
    "make_spec",
    "make_train",
    "make_trainer",
    "member_hyperparams",
    "members",
    "ou_params",
    "validated",
]

#: The settings that a part of the program takes as they are, by their own names (the
#: functions below map the others): fields of AgentOptions, keyword arguments of
#: actor_critic.hyperparams, fields of EnvOptions and of TrainSpec.
_AGENT_OPTIONS = ("actor_hidden_sizes", "critic_hidden_sizes", "layer_norm", "precision",
                  "target_actor", "target_update", "c51_target_head", "lr_schedule",
                  "critic_feature_norm", "critic_network", "actor_network")  # fmt: skip
_AGENT_SETTINGS = ("weight_decay", "max_grad_norm", "max_weight_norm", "v_min", "v_max",
                   "lr_final_fraction")  # fmt: skip
_ENV_OPTIONS = ("menagerie", "domain_randomization", "actor_obs_key", "critic_obs_key",
                "nconmax", "njmax")  # fmt: skip
_SPEC_SETTINGS = ("num_envs", "batch_size", "replay_capacity", "replay_shards", "n_step",
                  "steps_per_iter", "updates_per_iter", "iters_per_chunk", "warmup_steps",
                  "eval_envs", "normalize_obs", "exploration", "per_env_noise",
                  "scale_rewards", "eval_in_chunk")  # fmt: skip


def _as_given(cfg: TrainConfig, names: tuple[str, ...]) -> dict[str, Any]:
    """``{name: value}`` of the settings ``names`` of ``cfg`` (each a property or field)."""
    return {name: getattr(cfg, name) for name in names}


# --------------------------------------------------------------------------------------------
# the agent
# --------------------------------------------------------------------------------------------


def agent_config(cfg: TrainConfig) -> TD3Config | DDPGConfig:
    """The agent's config of ``cfg.algo``: ``cfg``'s settings where given, the algorithm's
    defaults otherwise (``None`` hidden sizes, learning rates or tau)."""
    given = dict(hidden_sizes=cfg.hidden_sizes, actor_lr=cfg.actor_lr, critic_lr=cfg.critic_lr,
                 tau=cfg.tau, discount=cfg.discount)  # fmt: skip
    given = {k: v for k, v in given.items() if v is not None}
    if cfg.algo == "ddpg":
        return DDPGConfig(**given)
    return TD3Config(policy_noise=cfg.policy_noise, noise_clip=cfg.noise_clip,
                     policy_freq=cfg.policy_freq, **given)  # fmt: skip


def agent_options(cfg: TrainConfig) -> ac.AgentOptions:
    """The agent's static options of ``cfg`` (:class:`~td3_jax.core.actor_critic.AgentOptions`;
    ``--actor-q auto``: the first critic's Q for plain critics, the lower one for
    distributional ones)."""
    distributional = cfg.critic == "distributional"
    auto_q = "min" if distributional else "first"
    return ac.AgentOptions(
        num_atoms=cfg.num_atoms if distributional else 0,
        actor_q=auto_q if cfg.actor_q == "auto" else cfg.actor_q,
        schedule_updates=cfg.total_updates if cfg.lr_schedule == "cosine" else None,
        clip_grads=cfg.max_grad_norm is not None,
        bound_weights=cfg.max_weight_norm is not None,
        **_as_given(cfg, _AGENT_OPTIONS),
    )


def agent_settings(cfg: TrainConfig) -> dict[str, float | None]:
    """The agent's float options beside :func:`agent_config`'s (traced, sweepable): keyword
    arguments of :func:`td3_jax.core.actor_critic.hyperparams`."""
    return _as_given(cfg, _AGENT_SETTINGS)


def agent_spec(cfg: TrainConfig, env: envs.Environment) -> ac.AgentSpec:
    """The agent structure of ``cfg.algo`` for ``env``'s sizes (TD3: two smoothed critics and a
    delayed actor; DDPG: one critic, no delay)."""
    is_td3 = cfg.algo == "td3"
    return ac.make_spec(
        agent_config(cfg).hidden_sizes,
        env.observation_size,
        env.action_size,
        num_critics=2 if is_td3 else 1,
        target_smoothing=is_td3,
        policy_freq=cfg.policy_freq if is_td3 else 1,
        options=agent_options(cfg),
        critic_observation_size=env.critic_observation_size,
    )


# --------------------------------------------------------------------------------------------
# the environment
# --------------------------------------------------------------------------------------------


def env_options(cfg: TrainConfig, members: int = 1) -> envs.EnvOptions:
    """The environment options of ``cfg`` (Playground's), for ``members`` members stepped
    together (all of their environments share MuJoCo Warp's contact buffer)."""
    return envs.EnvOptions(
        pushes=None if cfg.pushes == "default" else cfg.pushes == "on",
        impl=cfg.impl or ("warp" if cfg.env_backend == "warp" else None),
        worlds=members * _worlds(cfg),
        **_as_given(cfg, _ENV_OPTIONS),
    )


def _worlds(cfg: TrainConfig) -> int:
    """Environments one member steps together: the training ones, and the evaluation ones
    where they are stepped inside the chunk (a separate evaluation steps fewer)."""
    return cfg.num_envs + (cfg.eval_envs if cfg.eval_in_chunk else 0)


def make_env(cfg: TrainConfig, members: int = 1, env: Any = None) -> envs.Environment:
    """The environment of ``cfg`` (with its :func:`env_options`), for ``members`` members
    stepped together (MuJoCo Warp sizes its shared contact buffer so).

    ``env``: the environment to use instead of ``cfg.env``'s: an
    :class:`~td3_jax.envs.Environment` (used as it is), an object of your own or a factory
    ``module.path:function`` (:func:`td3_jax.envs.make`, with ``cfg``'s episode length).
    """
    if isinstance(env, envs.Environment):
        return env
    options = env_options(cfg, members)
    return envs.make(cfg.env if env is None else env, backend=cfg.env_backend,
                     episode_length=cfg.episode_length, options=options)  # fmt: skip


def bind_environment(cfg: TrainConfig, env: Any) -> tuple[TrainConfig, envs.Environment | None]:
    """``(cfg, environment)`` of a run handed ``env`` beside ``cfg``. ``None``: ``cfg``'s own
    (made later); a name or factory string becomes ``cfg.env`` (made later); an object is made
    and checked now, and ``cfg.env`` becomes what config.json records for it,
    ``object/<name>`` (:func:`td3_jax.envs.object_label`)."""
    if env is None:
        return cfg, None
    if isinstance(env, str):
        return dataclasses.replace(cfg, env=env), None
    made = make_env(cfg, env=env)
    return dataclasses.replace(cfg, env=envs.object_label(made)), made


# --------------------------------------------------------------------------------------------
# the program of one run
# --------------------------------------------------------------------------------------------


def make_spec(
    cfg: TrainConfig,
    env: Any = None,
    axis_name: str | None = None,
    env_groups: int = 1,
    members: int = 1,
    mesh: Any = None,
) -> training.TrainSpec:
    """The static spec of ``cfg`` (the environment is made for ``members`` members if not
    given; ``env`` may also be an object of your own or a factory string: :func:`make_env`).

    ``env_groups``: environments are reset within groups of this many contiguous environments
    (with the batch split over D devices, D keeps every reset on its device); with replay
    slices that the groups divide, the slices are the groups. Results do not depend on it.
    ``mesh``: the device mesh (axis ``"data"``) the batch is split over, for physics that
    XLA cannot split itself (MuJoCo Warp: :func:`td3_jax.envs.per_device.over_devices`);
    ``None``: one device, or physics XLA splits. Such a split turns JAX's Shardy partitioner
    off for the process (:func:`td3_jax.envs.per_device.over_devices`).
    """
    env = make_env(cfg, members, env)
    if mesh is not None:
        env = envs.over_devices(env, mesh)
    shards = cfg.replay_shards
    groups = shards if shards % env_groups == 0 else env_groups
    if cfg.eval_in_chunk:
        _check_eval_in_chunk(cfg, env.episode_length, groups)
    return training.TrainSpec(
        env=env,
        agent=agent_spec(cfg, env),
        reset_groups=groups,
        axis_name=axis_name,
        **_as_given(cfg, _SPEC_SETTINGS),
    )


def _check_eval_in_chunk(cfg: TrainConfig, length: int, reset_groups: int) -> None:
    """Raises :class:`ConfigError` where the evaluation worlds cannot be stepped in the chunk:
    a chunk shorter than an episode of ``length`` steps (its round would not finish in it), or
    evaluation worlds that the environment groups (replay slices, devices) do not divide."""
    per_iter, num_envs = cfg.steps_per_iter, cfg.num_envs
    steps = cfg.iters_per_chunk * per_iter
    if steps < length:
        enough = -(-length // per_iter) * per_iter * num_envs
        raise ConfigError(
            f"--eval-in-chunk needs chunks of at least one episode ({length} steps per "
            f"environment), but --eval-every {steps * num_envs} is {steps} steps per "
            f"environment ({num_envs} environments): use --eval-every {enough} or more, "
            "or --no-eval-in-chunk (an evaluation after each chunk, which takes an episode's "
            "steps of its own)"
        )
    for groups, what in ((cfg.replay_shards, "--replay-shards"),
                         (reset_groups, "the replay slices or devices")):  # fmt: skip
        if cfg.eval_envs % groups:
            raise ConfigError(f"--eval-envs ({cfg.eval_envs}) must be divisible by {groups} "
                              f"({what}) with --eval-in-chunk")  # fmt: skip


def ou_params(cfg: TrainConfig) -> OUParams:
    """The Ornstein-Uhlenbeck parameters of ``cfg`` (``ou_min_sigma`` defaults to
    ``ou_sigma``: no decay)."""
    return OUParams(
        theta=cfg.ou_theta,
        max_sigma=cfg.ou_sigma,
        min_sigma=cfg.ou_sigma if cfg.ou_min_sigma is None else cfg.ou_min_sigma,
        decay_period=float(cfg.ou_decay_period),
    )


def hyperparams(cfg: TrainConfig) -> training.Hyperparams:
    """The traced float settings of ``cfg`` (float32 scalars)."""
    f32 = lambda x: jnp.asarray(x, jnp.float32)
    return training.Hyperparams(
        agent=ac.hyperparams(agent_config(cfg), **agent_settings(cfg)),
        expl_noise=f32(cfg.expl_noise),
        ou=jax.tree.map(f32, ou_params(cfg)),
        expl_noise_min=f32(cfg.expl_noise_min or 0.0),
        expl_noise_max=f32(cfg.expl_noise_max or 0.0),
        return_bound=f32(cfg.return_bound or 1.0),
    )


@parameters_named
def make_train(
    cfg: TrainConfig, env: Any = None, axis_name: str | None = None
) -> Callable[[PRNGKey], tuple[training.TrainState, Metrics]]:
    """The whole run of ``cfg`` as one pure function ``train(key) -> (final_state, metrics)``
    (:func:`td3_jax.core.training.make_train` of its spec, hyperparameters and chunk count).

    ``metrics`` has a leading axis of ``cfg.num_chunks`` (one entry per evaluation) and holds
    the chunk metrics plus ``eval_returns [num_chunks, eval_envs]``. ``jax.vmap(train)(keys)``
    trains one independent agent per key in one program (the purejaxrl shape)::

        train = jax.jit(jax.vmap(make_train(TrainConfig(...))))
        states, metrics = train(jax.random.split(jax.random.PRNGKey(0), 8))

    ``make_train(cfg)(key_for_seed(s))`` runs the chunks and evaluations of
    ``td3-jax train --seed s`` (same keys) where ``eval_every`` is whole iterations and whole
    chunks of it make ``total_steps``. Otherwise it runs ``cfg.num_chunks`` whole chunks of
    ``cfg.iters_per_chunk`` iterations (``eval_every`` rounded down; ``cfg.chunked_steps`` env
    steps), where the command rounds ``eval_every`` as
    :func:`~td3_jax.config.schema.eval_every_within_run` says and ends its last chunk at
    ``cfg.run_steps``: a warning says so where the steps differ. Unlike the command it writes
    nothing and cannot be resumed, and ``cfg.seeds`` is not used (a warning where it asks for
    more than one).
    Vmapping with ``jax.vmap(train, axis_name=name)`` and ``axis_name=name`` here keeps the
    reset and warm-up branches as real branches. ``env``: the environment instead
    of ``cfg.env``'s, e.g. an object of your own (:func:`make_env`). ``cfg`` is validated
    first (:func:`~td3_jax.config.schema.validate`: a setting that cannot work is a ConfigError, as
    on the command line).
    """
    spec = make_spec(validated(cfg, env), env, axis_name)
    if cfg.seeds > 1:  # (the command line and td3_jax.train run them; this, one per key)
        warnings.warn(f"make_train trains one agent per key: seeds={cfg.seeds} is for "
                      "td3_jax.train and the command line; jax.vmap the function over keys "
                      "for several", UserWarning, stacklevel=outside_stacklevel())  # fmt: skip
    ran = eval_every_within_run(cfg).run_steps  # (what the command line runs)
    if cfg.chunked_steps != ran:
        warnings.warn(f"make_train runs {cfg.num_chunks} whole chunks of {cfg.iters_per_chunk} "
                      f"iterations: {cfg.chunked_steps} env steps per key, where the command "
                      f"line stops at {ran} (total_steps={cfg.total_steps}); an eval_every "
                      "of whole iterations whose whole chunks make total_steps runs the same",
                      UserWarning, stacklevel=outside_stacklevel())  # fmt: skip
    return training.make_train(spec, hyperparams(cfg), cfg.num_chunks)


def validated(cfg: TrainConfig, env: Any = None, devices: int = 1) -> TrainConfig:
    """:func:`~td3_jax.config.schema.validate` of ``cfg`` on ``devices`` devices, the name of
    its environment checked first (a misspelt name is said before any size); returns ``cfg``.
    ``env``: an environment object given instead of ``cfg.env``'s, whose name is then not
    checked (a config :func:`bind_environment` made names it ``object/...``, which passes)."""
    if env is None:
        envs.check_name(check_is_config(cfg).env)
    return validate(cfg, devices)


class Trainer(NamedTuple):
    """The steps of one configuration with its spec and hyperparameters bound (an adapter for
    library users and tests; the functions of :mod:`td3_jax.core.training` are the program).

    Attributes:
      init: ``init(key) -> TrainState``.
      chunk: ``chunk(state) -> (state, metrics)``: ``config.iters_per_chunk`` iterations.
      evaluate: ``evaluate(state, key) -> returns[eval_envs]``.
      sample: ``sample(buffer, key) -> Transition [batch_size, ...]``: one training batch as
        the updates draw it (n-step folded; observations not yet normalised).
    """

    config: TrainConfig
    spec: training.TrainSpec
    hyperparams: training.Hyperparams
    env: envs.Environment
    agent: Agent
    init: Callable[[PRNGKey], training.TrainState]
    chunk: Callable[[training.TrainState], tuple[training.TrainState, Metrics]]
    evaluate: Callable[[training.TrainState, PRNGKey], jax.Array]
    sample: Callable[[replay.ReplayBuffer, PRNGKey], Transition]


def make_trainer(
    cfg: TrainConfig,
    env: Any = None,
    axis_name: str | None = None,
    env_groups: int = 1,
) -> Trainer:
    """:class:`Trainer` of ``cfg``: :mod:`td3_jax.core.training`'s steps with ``spec`` and ``hp``
    bound (``cfg`` validated first: a setting that cannot work is a ConfigError here too)."""
    spec = make_spec(validated(cfg, env), env, axis_name, env_groups)
    hp = hyperparams(cfg)
    return Trainer(
        config=cfg,
        spec=spec,
        hyperparams=hp,
        env=spec.env,
        agent=ac.actor_critic(spec.agent, hp.agent, agent_config(cfg), axis_name),
        init=functools.partial(training.init, spec),
        chunk=functools.partial(training.chunk, spec, hp),
        evaluate=functools.partial(training.evaluate, spec),
        sample=functools.partial(training.sample_batch, spec, hp),
    )


# --------------------------------------------------------------------------------------------
# a population: seeds times sweep values
# --------------------------------------------------------------------------------------------


def _sweep_lists(sweep: dict[str, Sequence[float]] | None) -> dict[str, list[float]]:
    """``sweep``'s values as lists; a single number (not a list of them) is a ConfigError."""
    lists = {}
    for name, values in (sweep or {}).items():
        if isinstance(values, (int, float, str)):
            shown = f"{{{name!r}: [{values!r}, ...]}}; got {{{name!r}: {values!r}}}"
            raise ConfigError(f"sweep values are a list for each setting, e.g. {shown}")
        lists[name] = list(values)
    return lists


def members(cfg: TrainConfig, sweep: dict[str, Sequence[float]] | None = None) -> list[pop.Member]:
    """Every combination of the swept values, times ``cfg.seeds`` seeds from ``cfg.seed``.

    ``sweep``: ``{setting: values}`` of :data:`~td3_jax.config.schema.SWEEPABLE` settings. Raises a
    one-line :class:`ConfigError` for a setting that cannot be swept or changes nothing with
    ``cfg``, a non-finite value, or a combination ``cfg`` cannot run with (named by its
    ``--sweep-*`` flag)."""
    sweep = {k: v for k, v in _sweep_lists(sweep).items() if v}
    unknown = sorted(set(sweep) - set(SWEEPABLE))
    if unknown:
        guesses = [(name, fields_meant(name, SWEEPABLE)) for name in unknown]
        said = [f"{name}: did you mean {' or '.join(meant[:4])}? " if len(unknown) > 1
                else f"did you mean {' or '.join(meant[:4])}? " for name, meant in guesses if meant]
        raise ConfigError(f"cannot sweep {unknown}; {''.join(said)}sweepable: "
                          f"{', '.join(SWEEPABLE)}")  # fmt: skip
    _check_sweep_does_something(cfg, sweep)
    bad = {n: v for n, values in sweep.items() for v in values if not math.isfinite(float(v))}
    if bad:
        raise ConfigError(
            "swept values must be finite numbers: "
            + ", ".join(f"--sweep-{n.replace('_', '-')} {v}" for n, v in bad.items())
        )
    names = sorted(sweep)
    combos = list(itertools.product(*(sweep[n] for n in names))) or [()]
    _validate_combinations(cfg, names, combos)
    return [
        pop.Member(seed=cfg.seed + k, overrides=tuple(zip(names, map(float, combo), strict=True)))
        for combo in combos
        for k in range(cfg.seeds)
    ]


def _check_sweep_does_something(cfg: TrainConfig, sweep: dict[str, list[float]]) -> None:
    """Refuses sweeping a setting that ``cfg`` does not use (:func:`unused_settings`: a DDPG
    run's smoothing noise, an OU run's Gaussian scale, an option left off, ...)."""
    unused = unused_settings(cfg)
    idle = sorted(name for name in sweep if name in unused)
    if {"expl_noise_max", "expl_noise_min"} <= set(idle):  # (one pair, one hint)
        idle.remove("expl_noise_max")
    if idle:
        raise ConfigError("sweeping " + "; ".join(
            f"{name} changes nothing with {unused[name]}{_switch_on_hint(name, sweep, cfg)}"
            for name in idle))  # fmt: skip


def _switch_on_hint(name: str, sweep: dict[str, list[float]], cfg: TrainConfig) -> str:
    """For a swept option left off that its own flag turns on: which flag to add, and that its
    value does not matter (each member takes the sweep's)."""
    if name not in SWITCHED_ON_BY_THEIR_FLAG or getattr(cfg, name) is not None:
        return ""
    if name in ("expl_noise_min", "expl_noise_max"):  # (they go together: per-env noise)
        return (": add --expl-noise-min and --expl-noise-max, which go together (each member "
                "takes the values swept)")  # fmt: skip
    return (
        f": add {flag(name)} with any value, e.g. {flag(name)} {sweep[name][0]:g} (each "
        "member takes its swept value)"
    )


def _validate_combinations(cfg: TrainConfig, names: list[str], combos: list[tuple]) -> None:
    """Validates ``cfg`` with each combination of swept values; an impossible one is named by
    its ``--sweep-*`` flag."""
    for combo in combos:
        try:
            validate(dataclasses.replace(cfg, **dict(zip(names, combo, strict=True))))
        except ConfigError as err:
            raise ConfigError(_sweep_flags(str(err), names)) from None


def _sweep_flags(message: str, names: Sequence[str]) -> str:
    """``message`` with each swept setting's flag (``--actor-lr``) as its sweep flag
    (``--sweep-actor-lr``)."""
    for name in names:
        message = re.sub(flag_pattern(name), "--sweep-" + flag(name)[2:], message)
    return message


def member_hyperparams(cfg: TrainConfig, population: list[pop.Member]) -> training.Hyperparams:
    """Every member's :func:`hyperparams` (``cfg`` with the member's overrides), stacked:
    numpy leaves ``[members]``, computed on the host (no accelerator compiles before the run's
    programs), once per distinct setting (members that differ only in their seed share it)."""
    settings = list(dict.fromkeys(m.overrides for m in population))
    where = {overrides: i for i, overrides in enumerate(settings)}
    index = np.array([where[m.overrides] for m in population])
    each = lambda: [hyperparams(dataclasses.replace(cfg, **dict(overrides)))
                    for overrides in settings]  # fmt: skip
    distinct = pop.on_host(lambda: jax.tree.map(lambda *xs: jnp.stack(xs), *each()))
    return jax.tree.map(lambda x: x[index], distinct)


def make_population(
    cfg: TrainConfig,
    population: list[pop.Member],
    devices: int = 1,
    env: envs.Environment | None = None,
    mesh: Any = None,
) -> pop.Population:
    """The batched training functions of ``population`` (all sharing ``cfg``'s shapes):
    :func:`td3_jax.core.population.make_population` of ``cfg``'s spec and the members' stacked
    hyperparameters.

    ``devices``: how many devices the environments will be split over; resets then gather and
    scatter within each device's environments (the numbers do not depend on it). ``env``:
    ``cfg``'s environment when already made (made here otherwise). ``mesh``: those devices
    (:func:`make_spec`).
    """
    spec = make_spec(cfg, env, env_groups=devices, members=len(population), mesh=mesh)
    return pop.make_population(spec, member_hyperparams(cfg, population), population)
