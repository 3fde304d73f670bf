"""The training configuration (:class:`TrainConfig`, every setting of a run) and its
validation (:func:`validate`, for the devices the run spans); the named presets are in
:mod:`td3_jax.config.presets`, and what the program makes of a config (its environment, spec and
traced floats) in :mod:`td3_jax.config.build`."""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import numbers
import re
import types
import typing
from typing import Any, Literal

import numpy as np

from td3_jax.common.errors import ConfigError
from td3_jax.common.keywords import keywords_named


@keywords_named
@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Everything one training run needs. Sizes are static; the run compiles once for them.

    An *iteration* is ``steps_per_iter`` vectorised environment steps (each one step in every one
    of ``num_envs`` environments, so ``num_envs * steps_per_iter`` transitions) followed by
    ``updates_per_iter`` gradient updates on batches of ``batch_size``.
    """

    env: str = "gymnax/Pendulum-v1"
    """Environment as SOURCE/NAME (brax/ant, playground/CheetahRun, gymnax/Pendulum-v1, ...;
    `td3-jax envs` lists them), or your own as module.path:function (a function returning the
    environment; see docs/guides/own-environment.md)."""
    algo: Literal["td3", "ddpg"] = "td3"
    """Algorithm."""
    seed: int = 0
    """Random seed of the run (of its first member with --seeds K)."""
    seeds: int = 1
    """Independent seeds (seed, seed+1, ...) trained side by side in one compiled program."""
    num_envs: int = 16
    """Environments stepped in parallel."""
    total_steps: int = 20_000
    """Environment steps (summed over environments); the run ends here, rounded up to a whole
    iteration (its last chunk is shortened; with --eval-in-chunk it is a whole chunk, which an
    evaluation round needs)."""
    steps_per_iter: int = 1
    """Vectorised environment steps per iteration."""
    updates_per_iter: int = 8
    """Gradient updates per iteration (after warm-up); 0 collects without learning (warned)."""
    batch_size: int = 256
    """Transitions per gradient update."""
    buffer_size: int = 100_000
    """Replay capacity in transitions (a ring: the oldest are overwritten once it is full),
    capped at the run's own length (a ring never holds more rows than the run collects); a
    --resume that extends the run grows the ring to fit, with the numbers of a straight run."""
    replay_shards: int = 1
    """Split the replay ring into this many slices, each filled by its own group of environments
    and giving batch_size/replay_shards rows of every batch (stratified uniform sampling). With a
    multiple of the device count, inserts and sampling stay on each device."""
    warmup_steps: int = 2_000
    """Environment steps with uniform random actions and no updates at the start."""
    eval_every: int = 4_000
    """Environment steps between evaluations: the length of one compiled chunk (a checkpoint
    follows every --checkpoint-every chunks). It runs as whole iterations of --num-envs x
    --steps-per-iter env steps: rounded down (to one iteration at least), or, in a fresh run
    (`td3-jax train`, `td3_jax.train`), up where whole chunks of that length run fewer steps
    past --total-steps; the run prints the value it uses. A fresh run also lowers it to
    --total-steps where it is longer (not with --eval-in-chunk, whose chunk must hold a whole
    episode)."""
    eval_envs: int = 16
    """Episodes per evaluation (one per environment, deterministic policy)."""
    eval_in_chunk: bool = False
    """Step the evaluation environments inside the training chunk, in the same physics call
    as the training ones, instead of evaluating after it: eval_envs/num_envs more physics
    instead of a whole episode of sequential steps (seconds per evaluation on MuJoCo Warp);
    training is unchanged. Each record then holds the evaluation of the policy at its chunk's
    start (eval_policy_env_steps). Needs --eval-every of at least episode length x num_envs;
    --eval-envs cannot change on --resume."""
    episode_length: int | None = None
    """Time limit in steps; default: the environment's own (1000 for Brax/Playground)."""
    env_backend: str = "mjx"
    """Brax's physics backend (mjx, generalized, positional, spring); Playground's is --impl."""
    impl: Literal["warp", "jax"] | None = None
    """Physics of Playground tasks: MuJoCo Warp (warp: an NVIDIA GPU and pip install
    'td3-jax[warp]') or MJX's JAX implementation (jax); default: warp where it can run, else
    jax (said in one line, recorded in config.json)."""
    nconmax: int | None = None
    """MuJoCo Warp: contacts kept per environment (its contact buffer holds this many for every
    environment stepped together); default: the task's own. A run whose buffer fills stops and
    names this flag."""
    njmax: int | None = None
    """MuJoCo Warp: constraints kept per environment; default: the task's own. A run whose
    buffer fills stops and names this flag."""
    menagerie: str | None = None
    """MuJoCo Menagerie root holding the robot folders of Playground's locomotion tasks
    (DIR/booster_t1, ...); default: $MENAGERIE_ROOT, then the envpool asset packages, then
    Playground's own copy. Never downloaded."""
    domain_randomization: bool = False
    """Playground locomotion: the task's own domain randomiser draws each environment's physics
    (friction, masses, gains, ...) at every reset."""
    pushes: Literal["default", "on", "off"] = "default"
    """Playground locomotion: the task's push perturbations on or off; 'default' keeps the
    task's own setting."""
    actor_obs_key: str = "state"
    """Key of a dict observation (Playground locomotion) that the actor acts on."""
    critic_obs_key: str = "privileged_state"
    """Key of a dict observation that the critics learn from (the actor's key: symmetric)."""
    normalize_obs: bool = True
    """Normalise observations with running statistics kept in the train state."""
    exploration: Literal["gaussian", "ou"] = "gaussian"
    """Exploration noise: gaussian (std expl_noise) or ou (Ornstein-Uhlenbeck)."""
    expl_noise: float = 0.1
    """Gaussian exploration std in the agent's actions, [-1, 1] (each environment's bounds
    rescaled): a fraction of half the action range (0.1 on actions in [-2, 2]: a std of 0.2)."""
    ou_theta: float = 0.15
    """OU mean reversion."""
    ou_sigma: float = 0.3
    """OU initial sigma."""
    ou_min_sigma: float | None = None
    """OU final sigma, reached linearly over ou_decay_period steps per environment; default:
    ou_sigma (no decay)."""
    ou_decay_period: int = 100_000
    """OU decay period in steps."""
    expl_noise_min: float | None = None
    """With expl_noise_max: Gaussian exploration with a std per environment, drawn uniformly
    from [expl_noise_min, expl_noise_max] at the start and again whenever that environment's
    episode ends (FastTD3: 0.001 to 0.4); replaces expl_noise. Default: off."""
    expl_noise_max: float | None = None
    """Upper end of the per-environment exploration std (see expl_noise_min). Default: off."""
    hidden_sizes: tuple[int, ...] | None = (256, 256)
    """Hidden widths of actor and critics (the TD3 paper used 400 300); None: the algorithm's
    own default (TD3Config 400 300, DDPGConfig 256 256)."""
    actor_hidden_sizes: tuple[int, ...] | None = None
    """Hidden widths of the actor alone (FastTD3: 512 256 128); default: hidden_sizes."""
    critic_hidden_sizes: tuple[int, ...] | None = None
    """Hidden widths of each critic alone (FastTD3: 1024 512 256); default: hidden_sizes."""
    layer_norm: bool = False
    """LayerNorm after every hidden layer of actor and critics (before the ReLU); a residual
    network (--critic-network or --actor-network residual) has its own in every block either
    way."""
    precision: Literal["float32", "bfloat16"] = "float32"
    """Matmul precision of the networks; bfloat16 keeps parameters, optimiser states and losses
    in float32."""
    matmuls: Literal["auto", "cublas"] = "auto"
    """How a GPU runs the programs' matrix products: auto, as XLA chooses (mostly its Triton
    kernels); cublas, through cuBLAS (XLA's Triton GEMM emitter off): 1.23x the update of
    FastTD3's C51 networks and about 1.12x the T1 and G1 training loops (the robot presets'
    choice), about 10% slower with the ant preset's small networks. No effect on a CPU; an
    XLA_FLAGS that sets xla_gpu_enable_triton_gemm itself wins; may change on --resume."""
    critic: Literal["plain", "distributional"] = "plain"
    """Critic type: plain (a Q-value, MSE to the TD target) or distributional (C51: a
    distribution over num_atoms values in [v_min, v_max], cross-entropy to the projected
    target distribution of the target critic with the lower mean)."""
    num_atoms: int = 101
    """Atoms of the distributional critic's support."""
    v_min: float = -10.0
    """Lowest value of the distributional critic's support (returns below are clamped)."""
    v_max: float = 10.0
    """Highest value of the distributional critic's support (returns above are clamped)."""
    actor_q: Literal["auto", "first", "min", "mean"] = "auto"
    """What the actor maximises: the first critic (the TD3 paper), the lower of the critics'
    Q (per sample), or their mean; auto: first for plain critics, min for distributional ones
    (FastTD3)."""
    target_actor: bool = True
    """Keep a Polyak-averaged target actor for the target action; --no-target-actor uses the
    online actor plus smoothing noise, as FastTD3 does."""
    target_update: Literal["with_actor", "every_update"] = "with_actor"
    """When the target critics are Polyak-averaged (by tau): with_actor, in the delayed actor
    step every policy_freq updates (the TD3 paper); every_update, after every critic update
    (FastTD3)."""
    c51_target_head: Literal["unprojected", "projected"] = "unprojected"
    """Distributional critic: which target head a sample bootstraps from. unprojected: the
    lower mean of the next-state distributions, then projected; projected: every head's target
    projected onto the support, then the lower projected mean (FastTD3)."""
    weight_decay: float = 0.0
    """Decoupled (AdamW) weight decay of actor and critics, as in optax.adamw (FastTD3: 0.1)."""
    max_grad_norm: float | None = None
    """Clip gradients to this global norm before Adam; default: no clipping."""
    max_weight_norm: float | None = None
    """After every optimiser step, scale each unit's incoming weights (a column of every Dense
    kernel, actor and critics) down to this norm where they exceed it; default: unbounded
    (None turns a preset's bound off). The g1 and g1-rough presets use 1 (about the units'
    initial norm): 3 seeds at 53.2M steps, G1 flat 39.4, 39.2, 39.5 against 39.1, 38.8, 39.5
    without it; G1 rough 34.9, 34.1, 33.9 against 35.0, 34.0, 33.5, faster early."""
    return_bound: float | None = None
    """Divide the rewards the critics learn from by the running statistics of each training
    environment's discounted return (FlashSAC's reward normalisation): by max(std of the
    returns, largest |return| / return_bound), so the targets keep about unit spread and stay
    within about ±return_bound (FlashSAC: 5, with --v-min -5 --v-max 5). Evaluation returns
    are the environment's own. Default: off."""
    critic_feature_norm: bool = False
    """Project the critics' hidden features onto the sphere of radius sqrt(width) after every
    ReLU (with --critic-network residual: after every block; bounded features, as
    SimbaV2/FlashSAC); the actor is unchanged. On G1 flat (the g1 preset, 3 seeds at 50M
    steps) it ended at 39.7, 37.0 and 39.3 (IQM 39.0; without: 39.1), so no preset uses it."""
    critic_network: Literal["mlp", "residual"] = "mlp"
    """The critics' network: mlp (ReLU layers of --critic-hidden-sizes, with --layer-norm if
    given) or residual (FlashSAC's layout: an input layer, then a residual block per entry of
    --critic-hidden-sizes, which must be equal (256 256: two blocks of width 256, each
    width -> 4 x width -> width with LayerNorm and ReLU after each layer), then RMSNorm and the
    output layer; LayerNorm stands where FlashSAC's blocks have BatchNorm, and the input is not
    batch-normalised as FlashSAC's is). A block has about 8 x width^2 weights: 256 256 is about
    1M per critic, 15x the plain 256 256 (on a CPU try 64 64). The actor is unchanged. The
    g1 and g1-rough presets use it: higher returns on G1, with the loop about 0.7x as fast on
    G1 flat (72-75K env steps/s against 102-108K; docs/benchmarks.md, G1 flat and G1 presets)."""
    actor_network: Literal["mlp", "residual"] = "mlp"
    """The actor's network: mlp (ReLU layers of --actor-hidden-sizes, with --layer-norm if given)
    or residual (the layout of --critic-network residual, a block per entry of
    --actor-hidden-sizes, which must be equal; FlashSAC's actor is 128 128). Export writes
    both."""
    lr_schedule: Literal["constant", "cosine"] = "constant"
    """Learning-rate schedule: constant, or cosine from the learning rate to
    --lr-final-fraction of it (default 0) over the run's gradient updates (so --total-steps
    cannot change on --resume)."""
    lr_final_fraction: float = 0.0
    """Where the cosine schedule ends, as a fraction of the learning rate (FlashSAC: 0.5, from
    3e-4 to 1.5e-4); default 0: to 0."""
    actor_lr: float | None = None
    """Actor Adam learning rate; default: the algorithm's (TD3 1e-3, DDPG 1e-4)."""
    critic_lr: float | None = None
    """Critic Adam learning rate; default 1e-3."""
    discount: float = 0.99
    """Discount factor."""
    n_step: int = 1
    """Steps of the TD target: rewards of up to n steps of one episode, summed with discounts,
    then bootstrapped with discount**k after k steps (read from the replay ring at sampling)."""
    tau: float | None = None
    """Polyak rate of the targets; default: the algorithm's (TD3 0.005, DDPG 0.01)."""
    policy_noise: float = 0.2
    """TD3 target smoothing noise std, in the agent's [-1, 1] actions (as expl_noise)."""
    noise_clip: float = 0.5
    """TD3 target smoothing noise clip, in the agent's [-1, 1] actions."""
    policy_freq: int = 2
    """TD3 actor and target update period (in updates)."""
    keep_checkpoints: int = 3
    """Checkpoints kept on disk (the newest ones)."""
    checkpoint_every: int = 1
    """Evaluations between checkpoints (the last chunk is always checkpointed). A Ctrl-C
    that stops the run mid-chunk resumes from the last checkpoint (the chunks after it are
    lost); a SIGTERM, or the run's time budget, finishes the chunk and checkpoints it."""
    early_evaluation: bool = True
    """In a fresh run, evaluate once more after the first eighth of the first chunk when that
    has 64 iterations or more (the same compiled program runs both parts), so a first return
    shows soon after compiling."""
    wandb: bool = False
    """Mirror the run to Weights & Biases (pip install 'td3-jax[wandb]'): every metrics.jsonl
    record against env steps, config.json as its config, curve.png at the end."""
    wandb_project: str = "td3-jax"
    """W&B project."""
    wandb_entity: str | None = None
    """W&B entity (user or team); default: your W&B default entity."""
    wandb_name: str | None = None
    """W&B run name; default: the name of the run directory (--out)."""
    wandb_mode: Literal["online", "offline"] | None = None
    """online (needs `wandb login` or WANDB_API_KEY) or offline (no network: written to
    OUT/wandb/, uploaded later with `wandb sync`); default: $WANDB_MODE, else online."""

    def __post_init__(self) -> None:
        for name, kind in field_types().items():
            value = getattr(self, name)
            plain = _normalized(_checked(name, value, kind), kind)
            if plain is not value:
                object.__setattr__(self, name, plain)

    # Derived quantities --------------------------------------------------------------------
    @property
    def env_steps_per_iter(self) -> int:
        return self.num_envs * self.steps_per_iter

    @property
    def iters_per_chunk(self) -> int:
        return max(1, self.eval_every // self.env_steps_per_iter)

    @property
    def early_iterations(self) -> int:
        """Iterations before the early evaluation of a fresh run: an eighth of the first chunk
        when that has at least 64 iterations (shorter chunks report soon anyway), else 0 (also
        with eval_in_chunk: no round would have finished yet)."""
        split = self.early_evaluation and self.iters_per_chunk >= 64 and not self.eval_in_chunk
        return self.iters_per_chunk // 8 if split else 0

    @property
    def steps_per_chunk(self) -> int:
        """Environment steps of one member in one chunk (between two evaluations)."""
        return self.iters_per_chunk * self.env_steps_per_iter

    @property
    def num_chunks(self) -> int:
        """Chunks of the run (evaluations after the early one), the last one possibly short."""
        return max(
            1, math.ceil(self.total_steps / (self.iters_per_chunk * self.env_steps_per_iter))
        )

    @property
    def replay_capacity(self) -> int:
        """Transitions the replay ring holds: ``buffer_size``, or :attr:`chunked_steps` where
        that is smaller (the ring then never wraps, so a resume that extends the run grows it
        exactly: :func:`td3_jax.core.replay.resize_slices`; a run that ends inside its last
        chunk leaves the rest empty, so its numbers are those of the whole chunks' run)."""
        return min(self.buffer_size, self.chunked_steps)

    @property
    def run_iterations(self) -> int:
        """Iterations the run takes: ``total_steps`` rounded up to a whole iteration (the last
        chunk is shortened to end there), or to whole chunks with ``eval_in_chunk`` (an
        evaluation round needs its whole chunk: a shortened one would leave the run's last
        round unfinished, and a resume that extends the run would start its next round
        elsewhere than a straight run does)."""
        whole_chunks = self.num_chunks * self.iters_per_chunk
        if self.eval_in_chunk:
            return whole_chunks
        return min(whole_chunks, max(1, -(-self.total_steps // self.env_steps_per_iter)))

    @property
    def run_steps(self) -> int:
        """Environment steps the run takes (per member): :attr:`run_iterations` of
        ``env_steps_per_iter``."""
        return self.run_iterations * self.env_steps_per_iter

    @property
    def chunked_steps(self) -> int:
        """Environment steps of :attr:`num_chunks` whole chunks: what
        :func:`td3_jax.config.build.make_train` runs (and the replay ring is sized for)."""
        return self.num_chunks * self.iters_per_chunk * self.env_steps_per_iter

    @property
    def total_updates(self) -> int:
        """Gradient updates the run takes: ``updates_per_iter`` in every iteration from the
        first whose collected steps reach ``warmup_steps`` (at least 1)."""
        first = max(1, math.ceil(self.warmup_steps / self.env_steps_per_iter))
        return max(1, (self.run_iterations - first + 1) * self.updates_per_iter)

    @property
    def scale_rewards(self) -> bool:
        """Whether the learner's rewards are scaled by return statistics (return_bound given)."""
        return self.return_bound is not None

    @property
    def per_env_noise(self) -> bool:
        """Whether exploration stds are drawn per environment (expl_noise_min/max given)."""
        return self.expl_noise_min is not None


_POSITIVE = (
    "num_envs", "seeds", "total_steps", "steps_per_iter", "batch_size", "buffer_size",
    "eval_every", "eval_envs", "policy_freq", "n_step", "keep_checkpoints", "checkpoint_every",
    "replay_shards",
)  # fmt: skip
_NON_NEGATIVE = ("warmup_steps", "updates_per_iter")
_FLOATS = ("actor_lr", "critic_lr", "tau", "discount", "expl_noise", "policy_noise", "noise_clip",
           "ou_theta", "ou_sigma", "ou_min_sigma", "expl_noise_min", "expl_noise_max",
           "weight_decay", "max_grad_norm", "max_weight_norm", "return_bound",
           "lr_final_fraction")  # fmt: skip
_SIGNED_FLOATS = ("v_min", "v_max")
@functools.cache
def _choices() -> dict[str, tuple[Any, ...]]:
    """Each field whose annotation is a Literal (or a Literal or None) and its choices, None
    left out (an optional one may also be None): what :func:`validate` checks them against."""
    choices = {}
    for name, kind in field_types().items():
        literals = [a for a in union_arms(kind) if typing.get_origin(a) is Literal]
        if literals:
            choices[name] = typing.get_args(literals[0])
    return choices
_BACKENDS = ("generalized", "jax", "mjx", "positional", "spring", "warp")
#: The settings of Weights & Biases (``--wandb``, ...): where the records are mirrored, never
#: what the run computes.
WANDB_SETTINGS = ("wandb", "wandb_project", "wandb_entity", "wandb_name", "wandb_mode")
#: Float settings a sweep may vary (traced values: each member of a population gets its own
#: inside one compiled program, :func:`td3_jax.config.build.members`).
SWEEPABLE = ("actor_lr", "critic_lr", "tau", "discount", "expl_noise", "policy_noise",
             "noise_clip", "ou_sigma", "ou_theta", "expl_noise_min", "expl_noise_max",
             "weight_decay", "max_grad_norm", "max_weight_norm", "v_min", "v_max",
             "return_bound", "lr_final_fraction")  # fmt: skip


#: The largest seed: JAX's keys hold 32 bits of it (4294967296 gives seed 0's key).
MAX_SEED = 2**32 - 1
#: The most env steps (per member) and gradient updates a run may take: both are counted in
#: int32 inside the compiled program (past it the count would wrap and learning stop).
MAX_COUNT = 2**31 - 1


#: Sweepable settings whose own flag turns an option on (None: off), so that flag is given
#: beside their sweep (``--return-bound 5 --sweep-return-bound 1 5``).
SWITCHED_ON_BY_THEIR_FLAG = ("max_grad_norm", "max_weight_norm", "return_bound",
                             "expl_noise_min", "expl_noise_max")  # fmt: skip


def unused_settings(cfg: TrainConfig) -> dict[str, str]:
    """The settings that change nothing with the rest of ``cfg`` (OU settings of a Gaussian
    exploration run, the C51 support of plain critics, an option left off, ...), each with
    what makes it so (``{"v_max": "--critic plain", ...}``): what a sweep of them is refused
    for and a typed flag of them is warned of."""
    groups = [
        (("ou_theta", "ou_sigma", "ou_min_sigma", "ou_decay_period"), cfg.exploration != "ou",
         f"--exploration {cfg.exploration}"),
        (("expl_noise",), cfg.exploration != "gaussian", f"--exploration {cfg.exploration}"),
        (("expl_noise",), cfg.per_env_noise, "--expl-noise-min/--expl-noise-max"),
        (("num_atoms", "v_min", "v_max", "c51_target_head"), cfg.critic != "distributional",
         f"--critic {cfg.critic}"),
        (("policy_noise", "noise_clip", "policy_freq"), cfg.algo == "ddpg", "--algo ddpg"),
        (("env_backend",), not cfg.env.startswith("brax/"), f"--env {cfg.env}"),
        (("actor_obs_key", "critic_obs_key"), cfg.env.startswith(("gymnax/", "brax/")),
         f"--env {cfg.env} (its observations are one array, not a dict)"),
        (("menagerie",), cfg.env.startswith(("gymnax/", "brax/")),
         f"--env {cfg.env} (it loads no robot)"),
        (("lr_final_fraction",), cfg.lr_schedule != "cosine", f"--lr-schedule {cfg.lr_schedule}"),
        *(((name,), getattr(cfg, name) is None, f"no {flag(name)} (that flag turns it on)")
          for name in SWITCHED_ON_BY_THEIR_FLAG),
    ]  # fmt: skip
    unused: dict[str, str] = {}
    for names, idle, because in groups:
        for name in names if idle else ():
            unused.setdefault(name, because)
    return unused


def idle_flags(cfg: TrainConfig, given: set[str]) -> list[str]:
    """Warnings for flags typed (``given``: the fields named on the command line) that change
    nothing with the rest of ``cfg`` (:func:`unused_settings`), one per reason: ``--v-min,
    --v-max do nothing with --critic plain``. An option typed as None (``--max-weight-norm
    None``) is turned off, which undoes a preset's value: not warned of."""
    typed: dict[str, list[str]] = {}
    for name, because in unused_settings(cfg).items():
        turned_off = name in SWITCHED_ON_BY_THEIR_FLAG and getattr(cfg, name) is None
        if name in given and not turned_off:
            typed.setdefault(because, []).append(flag(name))
    return [f"{', '.join(flags)} {'does' if len(flags) == 1 else 'do'} nothing with {because}"
            for because, flags in typed.items()]  # fmt: skip


def check_seed(seed: int, members: int = 1) -> None:
    """A :class:`ConfigError` unless ``seed .. seed + members - 1`` are all seeds JAX tells
    apart: in ``[0, MAX_SEED]`` (a larger one silently repeats a smaller one's run)."""
    if seed < 0 or seed + members - 1 > MAX_SEED:
        after = "seed" if members == 2 else f"{members - 1} seeds"
        last = f" and the {after} after it (to {seed + members - 1})" if members > 1 else ""
        raise ConfigError(f"--seed {seed}{last} must be in [0, {MAX_SEED}]: JAX's random "
                          "keys hold 32 bits of a seed")  # fmt: skip


def idle_wandb_flags(cfg: TrainConfig, given: set[str]) -> None:
    """A :class:`ConfigError` when W&B settings were typed (``given``: the fields named on the
    command line) for a run that does not log to W&B: they would do nothing. Settings carried
    from config.json on ``--resume --no-wandb`` are not typed, so not refused."""
    typed = sorted(flag(n) for n in given & set(WANDB_SETTINGS[1:]))
    if typed and not cfg.wandb:
        raise ConfigError(f"{', '.join(typed)} given without --wandb (add --wandb to log to "
                          "Weights & Biases)")  # fmt: skip


def value_fits(value: Any, kind: Any, *, choices: bool = True) -> bool:
    """Whether ``value`` is of a :class:`TrainConfig` field's annotated type ``kind``: a number
    for a float, a whole number (a whole float too: ``total_steps=1e6``) for an int, a list or
    tuple of whole numbers for a tuple, one of a union's types; one of a Literal's values
    (with ``choices=False`` any value there: :func:`validate` names the choices)."""
    if kind is Any:
        return True
    if typing.get_origin(kind) is Literal:
        return not choices or value in typing.get_args(kind)
    if typing.get_origin(kind) in (types.UnionType, typing.Union):
        return any(value_fits(value, arm, choices=choices) for arm in typing.get_args(kind))
    if typing.get_origin(kind) is tuple:
        return isinstance(value, tuple | list) and all(value_fits(v, int) for v in value)
    if kind is type(None):
        return value is None
    if isinstance(value, bool | np.bool_):
        return kind is bool
    if kind is int:
        whole = isinstance(value, float) and value.is_integer()
        return isinstance(value, numbers.Integral) or whole
    if kind is float:
        return isinstance(value, numbers.Real)
    return not isinstance(kind, type) or isinstance(value, kind)  # (Any, generics: not checked)


#: Each plain field type as a reader says it: (in Python's words, in JSON's).
_TYPE_WORDS = {int: ("a whole number", "an integer"), float: ("a number", "a number"),
               bool: ("True or False", "true or false"), str: ("a string", "a string")}  # fmt: skip


def union_arms(kind: Any) -> tuple[Any, ...]:
    """The types a union annotation allows (``kind`` alone for any other)."""
    union = typing.get_origin(kind) in (types.UnionType, typing.Union)
    return typing.get_args(kind) if union else (kind,)


def type_words(kind: Any, *, json_words: bool = False) -> str:
    """A field's annotated type ``kind`` as a reader says it: "a whole number or None" (in
    JSON's words, as config.json holds it: "an integer or null"), "one of "td3", "ddpg""."""
    arms = union_arms(kind)
    if len(arms) > 1:
        return " or ".join(type_words(arm, json_words=json_words) for arm in arms)
    if typing.get_origin(kind) is Literal:
        return "one of " + ", ".join(json.dumps(a) for a in typing.get_args(kind))
    if typing.get_origin(kind) is tuple:
        return "a list of integers" if json_words else "a tuple of whole numbers"
    if kind is type(None):
        return "null" if json_words else "None"
    words = _TYPE_WORDS.get(kind)
    return words[json_words] if words else getattr(kind, "__name__", str(kind))


def _checked(name: str, value: Any, kind: Any) -> Any:
    """``value`` of field ``name`` (a NumPy scalar as its Python value), or a
    :class:`ConfigError` where it is not of its annotated type ``kind``
    (``TrainConfig(total_steps="3000")``), before anything compares or computes with it; the
    values' ranges and choices are :func:`validate`'s."""
    value = value.item() if isinstance(value, np.generic) else value
    if not value_fits(value, kind, choices=False):
        raise ConfigError(f"TrainConfig.{name} must be {type_words(kind)}, got {value!r} "
                          f"({type(value).__name__})")  # fmt: skip
    return value


def _normalized(value: Any, kind: Any) -> Any:
    """``value`` (of type ``kind``, :func:`value_fits`) as a plain Python value of the field's
    own type: a NumPy scalar as its Python value, a whole float as an int for an int field, an
    int as a float for a float field, a list of sizes as a tuple of ints (so a config hashes,
    compares, shapes arrays and writes to JSON as one given in plain types does)."""
    arms = union_arms(kind)
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if isinstance(value, float) and int in arms and float not in arms:
        return int(value)
    if isinstance(value, numbers.Real) and float in arms and int not in arms:
        try:
            return value if isinstance(value, float) else float(value)
        except OverflowError:
            raise ConfigError(f"{value} is too large for a float setting") from None
    if isinstance(value, tuple | list) and any(typing.get_origin(a) is tuple for a in arms):
        return tuple(int(_normalized(v, int)) for v in value)
    return value


@functools.cache
def field_types() -> dict[str, Any]:
    """Each :class:`TrainConfig` field's annotated type (resolved once)."""
    return typing.get_type_hints(TrainConfig)


def flag(name: str) -> str:
    """The command-line flag of a config field: ``total_steps -> --total-steps``."""
    return f"--{name.replace('_', '-')}"


def flag_pattern(name: str) -> str:
    """A regular expression of a field's flag as a whole word: ``--critic`` matches in
    ``--critic c51``, not in ``--critic-network`` or ``--sweep-critic``."""
    return rf"(?<![\w-]){re.escape(flag(name))}(?![\w-])"


def as_flag(name: str, value: Any) -> str:
    """A field and its value as command-line text (``--no-`` for false booleans)."""
    if isinstance(value, bool):
        return flag(name) if value else f"--no-{flag(name)[2:]}"
    if isinstance(value, tuple | list):
        return f"{flag(name)} {' '.join(map(str, value))}"
    return f"{flag(name)} {value}"


def whole_iterations(steps: int, per_iter: int) -> tuple[int, int]:
    """``steps`` rounded down and up to whole iterations of ``per_iter`` env steps."""
    return steps // per_iter * per_iter, -(-steps // per_iter) * per_iter


def eval_every_within_run(cfg: TrainConfig) -> TrainConfig:
    """``cfg`` with ``eval_every`` lowered to ``total_steps`` (rounded up to whole iterations)
    where it is longer, so that a fresh run evaluates at its end instead of training a whole
    chunk past ``total_steps`` (``--total-steps 20000 --eval-every 100000`` trains 20000 steps,
    not 100000). An in-chunk evaluation keeps its chunk: a round of evaluation episodes must
    fit in one. An ``eval_every`` that is not whole iterations runs as the whole iterations
    below it, or above it where whole chunks of those would run fewer steps past
    ``total_steps`` (16 environments, ``--eval-every 3000 --total-steps 6000``: chunks of 3008
    steps, 2 of them, the second ending at 6000; not 3 of 2992; compared as
    :attr:`TrainConfig.chunked_steps`)."""
    per_iter = cfg.env_steps_per_iter  # (a chunk is whole iterations)
    if per_iter <= 0 or cfg.eval_every <= 0:
        return cfg  # (validate names the impossible setting)
    if not cfg.eval_in_chunk and cfg.eval_every > cfg.total_steps:
        return dataclasses.replace(cfg, eval_every=whole_iterations(cfg.total_steps, per_iter)[1])
    down, up = whole_iterations(cfg.eval_every, per_iter)
    if down in (0, up):  # (whole iterations already, or fewer steps than one: runs as one)
        return cfg
    rounded_up = dataclasses.replace(cfg, eval_every=up)
    return rounded_up if rounded_up.chunked_steps < cfg.chunked_steps else cfg


def rounding_note(cfg: TrainConfig, asked_eval_every: int | None = None) -> str | None:
    """The line saying that ``--eval-every`` runs as whole iterations and ``--total-steps`` as
    a whole iteration (whole chunks with ``--eval-in-chunk``: :attr:`TrainConfig.run_steps`),
    and that an ``asked_eval_every`` longer than the run was lowered to
    ``--total-steps`` (:func:`~td3_jax.config.schema.eval_every_within_run`); None when nothing
    changed."""
    notes = []
    asked = cfg.eval_every if asked_eval_every is None else asked_eval_every
    if asked != cfg.eval_every and asked > cfg.total_steps:
        notes.append(f"--eval-every {asked} is longer than --total-steps "
                     f"{cfg.total_steps}: evaluating at its end instead")  # fmt: skip
    elif cfg.steps_per_chunk != asked:
        notes.append(f"--eval-every {asked} runs as {cfg.steps_per_chunk} (whole "
                     f"iterations of {cfg.env_steps_per_iter} env steps)")  # fmt: skip
    runs = cfg.run_steps
    if runs != cfg.total_steps and cfg.eval_in_chunk:  # (a round needs its whole chunk)
        notes.append(f"--total-steps {cfg.total_steps} runs as {runs} (whole chunks of "
                     f"{cfg.steps_per_chunk} steps between evaluations, as --eval-in-chunk "
                     "needs; --eval-every sets them, down to one evaluation episode's "
                     "iterations; --no-eval-in-chunk ends the run at --total-steps)")  # fmt: skip
    elif runs != cfg.total_steps:
        notes.append(f"--total-steps {cfg.total_steps} runs as {runs} (a whole iteration of "
                     f"{cfg.env_steps_per_iter} env steps)")  # fmt: skip
    return "; ".join(notes) or None


def check_is_config(cfg: Any) -> TrainConfig:
    """``cfg``, where it is a :class:`TrainConfig`; anything else (a dict of settings, a
    preset's name) is a ``TypeError`` that says how to make one."""
    if isinstance(cfg, TrainConfig):
        return cfg
    shown = repr(cfg) if len(repr(cfg)) <= 60 else repr(cfg)[:57] + "..."
    make = ("TrainConfig(**settings) makes one of a dict" if isinstance(cfg, dict)
            else "make one with TrainConfig(env=..., ...)")  # fmt: skip
    raise TypeError(f"cfg must be a td3_jax.TrainConfig, got {shown} ({type(cfg).__name__}); "
                    f"{make}")  # fmt: skip


def validate(cfg: TrainConfig, devices: int = 1) -> TrainConfig:
    """Raises :class:`ConfigError` with one clear sentence for a setting that cannot work, on
    its own or on ``devices`` devices (the run's mesh: its global sizes split over them);
    returns ``cfg``. Anything but a :class:`TrainConfig` is a ``TypeError``
    (:func:`check_is_config`)."""
    check_is_config(cfg)
    _check_choices(cfg)  # (a misspelt choice is said before any size)
    _check_counts(cfg)
    _check_floats(cfg)
    _check_replay(cfg)
    _check_options(cfg)
    _check_wandb(cfg)
    _check_devices(cfg, devices)
    for name in ("hidden_sizes", "actor_hidden_sizes", "critic_hidden_sizes"):
        sizes = getattr(cfg, name)
        if sizes is not None and (len(sizes) == 0 or min(sizes) <= 0):
            shown = " ".join(map(str, sizes)) or "no values"
            raise ConfigError(f"{flag(name)} must be positive integers, got {shown}")
    _check_residual_networks(cfg)
    _check_environment(cfg)
    return cfg


def _check_residual_networks(cfg: TrainConfig) -> None:
    """A residual network's hidden sizes are one width, a block each (the sizes that give them:
    --actor-hidden-sizes or --critic-hidden-sizes, else --hidden-sizes, else the algorithm's
    default)."""
    for part in ("critic", "actor"):
        if getattr(cfg, f"{part}_network") == "residual":
            _check_residual_sizes(cfg, part)


def _check_residual_sizes(cfg: TrainConfig, part: str) -> None:
    """:func:`_check_residual_networks` for the ``part`` (``actor`` or ``critic``)."""
    # (lazy: jax and flax, which the rest of the schema does without, only with the option)
    from td3_jax.core.networks import residual_layout
    from td3_jax.core.td3 import DDPGConfig, TD3Config

    own = f"{part}_hidden_sizes"
    name = own if getattr(cfg, own) is not None else "hidden_sizes"
    sizes = getattr(cfg, name)
    if sizes is None:
        sizes = (DDPGConfig if cfg.algo == "ddpg" else TD3Config)().hidden_sizes
        name = f"hidden_sizes (--algo {cfg.algo}'s default)"
    example = "128 128" if part == "actor" else "256 256"
    try:
        residual_layout(sizes)
    except ValueError as err:
        raise ConfigError(f"--{part}-network residual: {flag(name)}: {err}; give one, e.g. "
                          f"{flag(own)} {example}") from err  # fmt: skip


def _check_environment(cfg: TrainConfig) -> None:
    """The environment's settings: a known backend and physics, Playground's flags only for
    Playground tasks, observation keys."""
    if cfg.env_backend not in _BACKENDS:
        raise ConfigError(f"unknown --env-backend {cfg.env_backend!r}; Brax's backends are "
                          "generalized, mjx, positional and spring (Playground's physics is "
                          "--impl warp or jax)")  # fmt: skip
    if cfg.env.startswith("brax/") and cfg.env_backend in ("jax", "warp"):
        raise ConfigError(f"--env-backend {cfg.env_backend} is Playground's physics (--impl); "
                          "Brax's backends are generalized, mjx, positional and "
                          "spring")  # fmt: skip
    physics_flags = [flag(n) for n in ("impl", "nconmax", "njmax") if getattr(cfg, n) is not None]
    if physics_flags and not cfg.env.startswith("playground/"):
        verb = "applies" if len(physics_flags) == 1 else "apply"
        raise ConfigError(f"{', '.join(physics_flags)} {verb} to Playground tasks, not {cfg.env}")
    for name in ("nconmax", "njmax"):
        if getattr(cfg, name) is not None and getattr(cfg, name) <= 0:
            raise ConfigError(f"{flag(name)} must be positive, got {getattr(cfg, name)}")
    for name in ("actor_obs_key", "critic_obs_key"):
        if not getattr(cfg, name):
            raise ConfigError(f"{flag(name)} must name an observation key")


def _check_devices(cfg: TrainConfig, devices: int) -> None:
    """Global sizes split evenly over ``devices`` (the evaluation environments too where the
    physics may be MuJoCo Warp's: each device steps its own)."""
    checks = [("--num-envs", cfg.num_envs)]
    if cfg.impl == "warp" or (cfg.impl is None and cfg.env.startswith("playground/")):
        checks.append(("--eval-envs", cfg.eval_envs))  # (Warp, the default where it runs)
    if cfg.replay_shards % devices:
        slice_rows = cfg.replay_capacity // cfg.replay_shards
        checks.append(("each replay slice (capacity / --replay-shards)", slice_rows))
    for name, value in checks:
        if value % devices:
            raise ConfigError(
                f"{name} ({value}) must be divisible by the number of devices ({devices})"
            )


def _check_wandb(cfg: TrainConfig) -> None:
    """The W&B settings: a project to log to and a known mode (whether W&B can run here is
    :func:`td3_jax.runner.tracking.check_ready`'s question)."""
    if cfg.wandb and not cfg.wandb_project:
        raise ConfigError("--wandb-project must name a W&B project")


def _check_choices(cfg: TrainConfig) -> None:
    """Every setting of a fixed set of choices (``--algo``, ``--exploration``, ...) is one."""
    for name, allowed in _choices().items():
        if not value_fits(getattr(cfg, name), field_types()[name]):
            raise ConfigError(f"unknown {flag(name)} {getattr(cfg, name)!r}; choose one of "
                              f"{', '.join(allowed)}")  # fmt: skip


def _check_options(cfg: TrainConfig) -> None:
    """The FastTD3-class options: a support, a pair of exploration bounds."""
    if cfg.num_atoms < 2:
        raise ConfigError(f"--num-atoms must be at least 2, got {cfg.num_atoms}")
    if not cfg.v_min < cfg.v_max:
        raise ConfigError(f"--v-min ({cfg.v_min}) must be below --v-max ({cfg.v_max})")
    low, high = cfg.expl_noise_min, cfg.expl_noise_max
    if (low is None) != (high is None):
        raise ConfigError("--expl-noise-min and --expl-noise-max go together: give both or neither")
    if low is not None and low > high:
        raise ConfigError(f"--expl-noise-min ({low}) must not exceed --expl-noise-max ({high})")
    if low is not None and cfg.exploration != "gaussian":
        raise ConfigError("--expl-noise-min/--expl-noise-max need --exploration gaussian")


def _check_counts(cfg: TrainConfig) -> None:
    for name in _POSITIVE:
        if getattr(cfg, name) <= 0:
            raise ConfigError(f"{flag(name)} must be positive, got {getattr(cfg, name)}")
    for name in _NON_NEGATIVE:
        if getattr(cfg, name) < 0:
            raise ConfigError(f"{flag(name)} must not be negative, got {getattr(cfg, name)}")
    if cfg.episode_length is not None and cfg.episode_length <= 0:
        raise ConfigError(f"--episode-length must be positive, got {cfg.episode_length}")
    check_seed(cfg.seed, cfg.seeds)
    if cfg.env_steps_per_iter > MAX_COUNT:  # (one iteration alone: name what makes it)
        raise ConfigError(f"one iteration of --num-envs {cfg.num_envs:,} x --steps-per-iter "
                          f"{cfg.steps_per_iter} is {cfg.env_steps_per_iter:,} env steps, more "
                          f"than the {MAX_COUNT:,} a run can count (int32 counters in the "
                          "compiled program)")  # fmt: skip
    if cfg.chunked_steps > MAX_COUNT:  # (make_train runs whole chunks: its counters too)
        runs = f" (run as {cfg.chunked_steps:,}: whole chunks)" * (
            cfg.chunked_steps != cfg.total_steps
        )
        raise ConfigError(f"--total-steps {cfg.total_steps:,}{runs} is more than the "
                          f"{MAX_COUNT:,} env steps a run can count (int32 counters in the "
                          "compiled program)")  # fmt: skip
    if cfg.total_updates > MAX_COUNT:
        raise ConfigError(f"the run would take {cfg.total_updates:,} gradient updates, more than "
                          f"the {MAX_COUNT:,} it can count: fewer --updates-per-iter or "
                          "--total-steps")  # fmt: skip


def _check_floats(cfg: TrainConfig) -> None:
    """Finite floats (NaN and infinities are refused before anything compiles), in range: each
    setting with a range of its own says that range, whichever side a value misses it."""
    for name in (*_FLOATS, *_SIGNED_FLOATS):
        value = getattr(cfg, name)
        if value is not None and not math.isfinite(value):
            raise ConfigError(f"{flag(name)} must be a finite number, got {value}")
    _check_ranges(cfg)
    for name in _FLOATS:
        value = getattr(cfg, name)
        if value is not None and value < 0:
            raise ConfigError(f"{flag(name)} must not be negative, got {value}")


def _check_ranges(cfg: TrainConfig) -> None:
    """The float settings with a range of their own (a bound, a fraction, a rate)."""
    for name in ("actor_lr", "critic_lr"):
        if getattr(cfg, name) == 0:
            network = name.partition("_")[0]
            raise ConfigError(f"{flag(name)} must be positive: at 0 the {network} never learns")
    for bound in ("max_grad_norm", "max_weight_norm", "return_bound"):
        if getattr(cfg, bound) is not None and getattr(cfg, bound) <= 0:
            raise ConfigError(f"{flag(bound)} must be positive, got {getattr(cfg, bound)}")
    if not 0.0 <= cfg.lr_final_fraction <= 1.0:
        raise ConfigError(f"--lr-final-fraction must be in [0, 1], got {cfg.lr_final_fraction}")
    if cfg.lr_final_fraction and cfg.lr_schedule != "cosine":
        raise ConfigError("--lr-final-fraction applies to --lr-schedule cosine")
    if not 0.0 <= cfg.discount <= 1.0:
        raise ConfigError(f"--discount must be in [0, 1], got {cfg.discount}")
    if cfg.tau is not None and not 0.0 < cfg.tau <= 1.0:
        raise ConfigError(f"--tau must be in (0, 1], got {cfg.tau}")


def _batch_advice(cfg: TrainConfig, longer_run: str) -> str:
    """``try --batch-size B or ...``: a batch that the run's ring holds (at most 256, a
    multiple of --replay-shards), or ``longer_run`` (empty: none) with a ring of one batch."""
    shards = cfg.replay_shards
    fitting = max(shards, min(256, cfg.replay_capacity, cfg.run_steps) // shards * shards)
    ring = "" if cfg.buffer_size >= cfg.batch_size else f"--buffer-size {cfg.batch_size} or more"
    bigger = " with ".join(part for part in (longer_run, ring) if part)
    return f"try --batch-size {fitting}" + (f", or {bigger}" if bigger else "")


def _ring_needs(cfg: TrainConfig) -> tuple[int, str]:
    """``(rows, why)``: the fewest rows the ring must hold, as a multiple of --replay-shards,
    and why where more than one iteration's transitions set it (a batch, or the rows an n-step
    target reads past its sample; ``""`` otherwise)."""
    window = (cfg.n_step - 1) * cfg.num_envs + 1
    needs = ((cfg.env_steps_per_iter, ""),  # (first among equals: no reason to give)
             (window, f", as {cfg.n_step}-step targets read {window - 1} stored rows past a "
                      "sample"),
             (cfg.batch_size, f", to hold a batch of {cfg.batch_size}"))  # fmt: skip
    least, why = max(needs, key=lambda need: need[0])
    return -(-least // cfg.replay_shards) * cfg.replay_shards, why


def _check_replay(cfg: TrainConfig) -> None:
    capacity = cfg.replay_capacity
    if cfg.env_steps_per_iter > capacity:
        least, why = _ring_needs(cfg)
        many = min(cfg.run_steps, 1000 * cfg.env_steps_per_iter) // cfg.replay_shards
        suggested = many * cfg.replay_shards
        varied = (f" (a ring of many iterations, e.g. --buffer-size {suggested}, samples more "
                  "varied batches)" if suggested > least else "")  # fmt: skip
        raise ConfigError(f"one iteration adds {cfg.env_steps_per_iter} transitions but the "
                          f"replay buffer holds only {capacity}: give --buffer-size {least} at "
                          f"least{why}{varied}")  # fmt: skip
    if cfg.updates_per_iter and cfg.batch_size > cfg.run_steps:  # (no updates: never sampled)
        raise ConfigError(
            f"--batch-size {cfg.batch_size} is larger than the {cfg.run_steps} transitions the "
            f"run collects (--total-steps {cfg.total_steps}): it would never update; "
            f"{_batch_advice(cfg, f'--total-steps {cfg.batch_size} or more')}"
        )
    if cfg.updates_per_iter and cfg.warmup_steps >= cfg.run_steps:
        raise ConfigError(
            f"--warmup-steps {cfg.warmup_steps} is not below the {cfg.run_steps} env steps the "
            f"run collects (--total-steps {cfg.total_steps}): it would end before it learns; "
            f"try --warmup-steps {cfg.run_steps // 2} or a longer --total-steps"
        )
    if cfg.batch_size > capacity:
        raise ConfigError(f"--batch-size {cfg.batch_size} is larger than the replay buffer "
                          f"({capacity} transitions); {_batch_advice(cfg, '')}")  # fmt: skip
    for name, value in (("--num-envs", cfg.num_envs), ("--batch-size", cfg.batch_size),
                        ("the replay capacity", capacity)):  # fmt: skip
        if value % cfg.replay_shards:
            raise ConfigError(
                f"{name} ({value}) must be divisible by --replay-shards ({cfg.replay_shards})"
            )
    if (cfg.n_step - 1) * cfg.num_envs >= capacity:
        raise ConfigError(
            f"--n-step {cfg.n_step} reads {cfg.n_step - 1} steps past a sampled transition, "
            f"{(cfg.n_step - 1) * cfg.num_envs} stored transitions, "
            f"more than the replay buffer holds ({capacity})"
        )


__all__ = [
    "MAX_COUNT",
    "MAX_SEED",
    "SWEEPABLE",
    "SWITCHED_ON_BY_THEIR_FLAG",
    "WANDB_SETTINGS",
    "TrainConfig",
    "as_flag",
    "check_is_config",
    "check_seed",
    "eval_every_within_run",
    "field_types",
    "flag",
    "idle_flags",
    "idle_wandb_flags",
    "rounding_note",
    "union_arms",
    "unused_settings",
    "validate",
    "value_fits",
    "whole_iterations",
]
