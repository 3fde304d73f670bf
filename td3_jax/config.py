"""The training configuration, its validation and the named presets."""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Literal

from td3_jax.actor_critic import AgentOptions
from td3_jax.envs import menagerie
from td3_jax.envs.base import EnvOptions
from td3_jax.noise import OUParams
from td3_jax.td3 import DDPGConfig, TD3Config


class ConfigError(ValueError):
    """A setting that cannot work; the CLI prints it as one line and exits with code 2."""


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Everything one training run needs. Sizes are static; the run compiles once for them.

    An *iteration* is ``steps_per_iter`` vectorised environment steps (each one step in every one
    of ``num_envs`` environments, so ``num_envs * steps_per_iter`` transitions) followed by
    ``updates_per_iter`` gradient updates on batches of ``batch_size``.
    """

    env: str = "gymnax/Pendulum-v1"
    """Environment as SOURCE/NAME: brax/ant, playground/CheetahRun, gymnax/Pendulum-v1, ..."""
    algo: Literal["td3", "ddpg"] = "td3"
    """Algorithm."""
    seed: int = 0
    """Random seed of the run (of its first member with --seeds K)."""
    seeds: int = 1
    """Independent seeds (seed, seed+1, ...) trained side by side in one compiled program."""
    num_envs: int = 16
    """Environments stepped in parallel."""
    total_steps: int = 20_000
    """Environment steps (summed over environments); rounded up to whole evaluation chunks."""
    steps_per_iter: int = 1
    """Vectorised environment steps per iteration."""
    updates_per_iter: int = 8
    """Gradient updates per iteration (after warm-up)."""
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
    """Environment steps between evaluations (one compiled chunk); also the checkpoint period."""
    eval_envs: int = 16
    """Episodes per evaluation (one per environment, deterministic policy)."""
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
    """Playground locomotion: the task's push perturbations on or off (default: the task's)."""
    actor_obs_key: str = "state"
    """Key of a dict observation (Playground locomotion) that the actor acts on."""
    critic_obs_key: str = "privileged_state"
    """Key of a dict observation that the critics learn from (the actor's key: symmetric)."""
    normalize_obs: bool = True
    """Normalise observations with running statistics kept in the train state."""
    exploration: Literal["gaussian", "ou"] = "gaussian"
    """Exploration noise: gaussian (std expl_noise) or ou (Ornstein-Uhlenbeck)."""
    expl_noise: float = 0.1
    """Gaussian exploration std, as a fraction of the action range."""
    ou_theta: float = 0.15
    """OU mean reversion."""
    ou_sigma: float = 0.3
    """OU initial sigma."""
    ou_min_sigma: float | None = None
    """OU final sigma, reached linearly over ou_decay_period steps per environment; default:
    ou_sigma (no decay, as in the seed)."""
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
    """LayerNorm after every hidden layer of actor and critics (before the ReLU)."""
    precision: Literal["float32", "bfloat16"] = "float32"
    """Matmul precision of the networks; bfloat16 keeps parameters, optimiser states and losses
    in float32."""
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
    weight_decay: float = 0.0
    """Decoupled (AdamW) weight decay of actor and critics, as in optax.adamw (FastTD3: 0.1)."""
    max_grad_norm: float | None = None
    """Clip gradients to this global norm before Adam; default: no clipping."""
    lr_schedule: Literal["constant", "cosine"] = "constant"
    """Learning-rate schedule: constant, or cosine from the learning rate to 0 over the run's
    gradient updates (so --total-steps cannot change on --resume)."""
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
    """TD3 target smoothing noise std."""
    noise_clip: float = 0.5
    """TD3 target smoothing noise clip."""
    policy_freq: int = 2
    """TD3 actor and target update period (in updates)."""
    keep_checkpoints: int = 3
    """Checkpoints kept on disk (the newest ones)."""
    checkpoint_every: int = 1
    """Evaluations between checkpoints (the last chunk is always checkpointed)."""
    early_evaluation: bool = True
    """In a fresh run, evaluate once more after the first eighth of the first chunk when that
    has 64 iterations or more (the same compiled program runs both parts), so a first return
    shows soon after compiling."""

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
        when that has at least 64 iterations (shorter chunks report soon anyway), else 0."""
        split = self.early_evaluation and self.iters_per_chunk >= 64
        return self.iters_per_chunk // 8 if split else 0

    @property
    def steps_per_chunk(self) -> int:
        """Environment steps of one member in one chunk (between two evaluations)."""
        return self.iters_per_chunk * self.env_steps_per_iter

    @property
    def num_chunks(self) -> int:
        return max(
            1, math.ceil(self.total_steps / (self.iters_per_chunk * self.env_steps_per_iter))
        )

    @property
    def replay_capacity(self) -> int:
        """Transitions the replay ring holds: ``buffer_size``, or the run's own length where
        that is smaller (the ring then never wraps, so a resume that extends the run grows it
        exactly: :func:`td3_jax.training.grow_ring`)."""
        return min(self.buffer_size, self.run_steps)

    @property
    def run_steps(self) -> int:
        """Environment steps the run takes: ``total_steps`` rounded up to whole chunks."""
        return self.num_chunks * self.iters_per_chunk * self.env_steps_per_iter

    def agent_config(self) -> TD3Config | DDPGConfig:
        """The agent's config: these settings where given, the algorithm's defaults otherwise."""
        given = {
            k: v
            for k, v in dict(
                hidden_sizes=self.hidden_sizes,
                actor_lr=self.actor_lr,
                critic_lr=self.critic_lr,
                tau=self.tau,
                discount=self.discount,
            ).items()
            if v is not None
        }
        if self.algo == "ddpg":
            return DDPGConfig(**given)
        return TD3Config(
            policy_noise=self.policy_noise,
            noise_clip=self.noise_clip,
            policy_freq=self.policy_freq,
            **given,
        )

    @property
    def total_updates(self) -> int:
        """Gradient updates the run takes: ``updates_per_iter`` in every iteration from the
        first whose collected steps reach ``warmup_steps`` (at least 1)."""
        iters = self.num_chunks * self.iters_per_chunk
        first = max(1, math.ceil(self.warmup_steps / self.env_steps_per_iter))
        return max(1, (iters - first + 1) * self.updates_per_iter)

    @property
    def per_env_noise(self) -> bool:
        """Whether exploration stds are drawn per environment (expl_noise_min/max given)."""
        return self.expl_noise_min is not None

    def agent_options(self) -> AgentOptions:
        """The agent's static options (:class:`~td3_jax.actor_critic.AgentOptions`)."""
        distributional = self.critic == "distributional"
        auto_q = "min" if distributional else "first"
        return AgentOptions(
            num_atoms=self.num_atoms if distributional else 0,
            actor_hidden_sizes=self.actor_hidden_sizes,
            critic_hidden_sizes=self.critic_hidden_sizes,
            layer_norm=self.layer_norm,
            precision=self.precision,
            target_actor=self.target_actor,
            actor_q=auto_q if self.actor_q == "auto" else self.actor_q,
            lr_schedule=self.lr_schedule,
            schedule_updates=self.total_updates if self.lr_schedule == "cosine" else None,
            clip_grads=self.max_grad_norm is not None,
        )

    def agent_settings(self) -> dict[str, float | None]:
        """The agent's float options, beside :meth:`agent_config`'s (traced, sweepable)."""
        return dict(weight_decay=self.weight_decay, max_grad_norm=self.max_grad_norm,
                    v_min=self.v_min, v_max=self.v_max)  # fmt: skip


    def env_options(self, members: int = 1) -> EnvOptions:
        """The environment options of these settings (Playground's), for ``members`` members
        stepped together (all of their environments share MuJoCo Warp's contact buffer)."""
        return EnvOptions(
            menagerie=self.menagerie,
            domain_randomization=self.domain_randomization,
            pushes=None if self.pushes == "default" else self.pushes == "on",
            actor_obs_key=self.actor_obs_key,
            critic_obs_key=self.critic_obs_key,
            impl=self.impl or ("warp" if self.env_backend == "warp" else None),
            worlds=members * self.num_envs,  # not eval_envs: it may change on resume
            nconmax=self.nconmax,
            njmax=self.njmax,
        )

    def ou_params(self) -> OUParams:
        return OUParams(
            theta=self.ou_theta,
            max_sigma=self.ou_sigma,
            min_sigma=self.ou_sigma if self.ou_min_sigma is None else self.ou_min_sigma,
            decay_period=float(self.ou_decay_period),
        )


_POSITIVE = (
    "num_envs", "seeds", "total_steps", "steps_per_iter", "batch_size", "buffer_size",
    "eval_every", "eval_envs", "policy_freq", "n_step", "keep_checkpoints", "checkpoint_every",
    "replay_shards",
)  # fmt: skip
_NON_NEGATIVE = ("warmup_steps", "updates_per_iter")
_FLOATS = ("actor_lr", "critic_lr", "tau", "discount", "expl_noise", "policy_noise", "noise_clip",
           "ou_theta", "ou_sigma", "ou_min_sigma", "expl_noise_min", "expl_noise_max",
           "weight_decay", "max_grad_norm")  # fmt: skip
_SIGNED_FLOATS = ("v_min", "v_max")
_CHOICES = {
    "critic": ("plain", "distributional"),
    "actor_q": ("auto", "first", "min", "mean"),
    "precision": ("float32", "bfloat16"),
    "lr_schedule": ("constant", "cosine"),
}
_BACKENDS = ("generalized", "jax", "mjx", "positional", "spring", "warp")


def flag(name: str) -> str:
    """The command-line flag of a config field: ``total_steps -> --total-steps``."""
    return f"--{name.replace('_', '-')}"


def as_flag(name: str, value: Any) -> str:
    """A field and its value as command-line text (``--no-`` for false booleans)."""
    if isinstance(value, bool):
        return flag(name) if value else f"--no-{flag(name)[2:]}"
    if isinstance(value, tuple | list):
        return f"{flag(name)} {' '.join(map(str, value))}"
    return f"{flag(name)} {value}"


def validate(cfg: TrainConfig) -> TrainConfig:
    """Raises :class:`ConfigError` with one clear sentence for a setting that cannot work."""
    _check_counts(cfg)
    _check_floats(cfg)
    _check_replay(cfg)
    _check_options(cfg)
    if cfg.algo not in ("td3", "ddpg"):
        raise ConfigError(f"unknown algorithm {cfg.algo!r}; choose td3 or ddpg")
    if cfg.env_backend not in _BACKENDS:
        raise ConfigError(f"unknown --env-backend {cfg.env_backend!r}; "
                          f"choose one of {', '.join(_BACKENDS)}")  # fmt: skip
    for name in ("hidden_sizes", "actor_hidden_sizes", "critic_hidden_sizes"):
        sizes = getattr(cfg, name)
        if sizes is not None and (len(sizes) == 0 or min(sizes) <= 0):
            raise ConfigError(f"{flag(name)} must be positive integers, got {sizes}")
    if cfg.impl not in (None, "warp", "jax"):
        raise ConfigError(f"unknown --impl {cfg.impl!r}; choose warp or jax")
    physics_flags = [flag(n) for n in ("impl", "nconmax", "njmax") if getattr(cfg, n) is not None]
    if physics_flags and not cfg.env.startswith("playground/"):
        raise ConfigError(f"{', '.join(physics_flags)} apply to Playground tasks, not {cfg.env}")
    for name in ("nconmax", "njmax"):
        if getattr(cfg, name) is not None and getattr(cfg, name) <= 0:
            raise ConfigError(f"{flag(name)} must be positive, got {getattr(cfg, name)}")
    if cfg.pushes not in ("default", "on", "off"):
        raise ConfigError(f"--pushes must be default, on or off, got {cfg.pushes!r}")
    for name in ("actor_obs_key", "critic_obs_key"):
        if not getattr(cfg, name):
            raise ConfigError(f"{flag(name)} must name an observation key")
    return cfg


def _check_options(cfg: TrainConfig) -> None:
    """The FastTD3-class options: known choices, a support, a pair of exploration bounds."""
    for name, allowed in _CHOICES.items():
        if getattr(cfg, name) not in allowed:
            raise ConfigError(f"unknown {flag(name)} {getattr(cfg, name)!r}; choose one of "
                              f"{', '.join(allowed)}")  # fmt: skip
    if cfg.num_atoms < 2:
        raise ConfigError(f"--num-atoms must be at least 2, got {cfg.num_atoms}")
    if not cfg.v_min < cfg.v_max:
        raise ConfigError(f"--v-min ({cfg.v_min}) must be below --v-max ({cfg.v_max})")
    if cfg.max_grad_norm is not None and cfg.max_grad_norm <= 0:
        raise ConfigError(f"--max-grad-norm must be positive, got {cfg.max_grad_norm}")
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


def _check_floats(cfg: TrainConfig) -> None:
    """Finite floats (NaN and infinities are refused before anything compiles), in range."""
    for name in _FLOATS:
        value = getattr(cfg, name)
        if value is not None and not math.isfinite(value):
            raise ConfigError(f"{flag(name)} must be a finite number, got {value}")
        if value is not None and value < 0:
            raise ConfigError(f"{flag(name)} must not be negative, got {value}")
    for name in _SIGNED_FLOATS:
        if not math.isfinite(getattr(cfg, name)):
            raise ConfigError(f"{flag(name)} must be a finite number, got {getattr(cfg, name)}")
    if not 0.0 <= cfg.discount <= 1.0:
        raise ConfigError(f"--discount must be in [0, 1], got {cfg.discount}")
    if cfg.tau is not None and not 0.0 < cfg.tau <= 1.0:
        raise ConfigError(f"--tau must be in (0, 1], got {cfg.tau}")


def _check_replay(cfg: TrainConfig) -> None:
    capacity = cfg.replay_capacity
    if cfg.env_steps_per_iter > capacity:
        raise ConfigError(f"one iteration adds {cfg.env_steps_per_iter} transitions but the "
                          f"replay buffer holds only {capacity}")  # fmt: skip
    if cfg.batch_size > cfg.run_steps:
        raise ConfigError(
            f"--batch-size {cfg.batch_size} is larger than the {cfg.run_steps} transitions the "
            f"run collects (--total-steps {cfg.total_steps}): it would never update"
        )
    if cfg.batch_size > capacity:
        raise ConfigError(f"--batch-size {cfg.batch_size} is larger than the replay buffer "
                          f"({capacity} transitions)")  # fmt: skip
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
    total_steps=20_000_000,
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
    precision="bfloat16",
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
# (-7 on G1) and costs those 15 s.
_HUMANOID_JOYSTICK = dict(
    _PLAYGROUND_LOCOMOTION,
    num_envs=4096,
    updates_per_iter=8,
    eval_envs=128,
    eval_every=4_096_000,
    early_evaluation=False,
    buffer_size=8_388_608,
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
        _GPU_LOCOMOTION, env="brax/humanoid", total_steps=30_000_000, hidden_sizes=(512, 256)
    ),
    # MuJoCo Playground's DM Control CheetahRun (pure-JAX MJX implementation), same settings.
    "cheetah-run": dict(_GPU_LOCOMOTION, env="playground/CheetahRun"),
    # Playground humanoids (see _PLAYGROUND_LOCOMOTION): Booster T1 and Unitree G1 joysticks.
    "t1": dict(_HUMANOID_JOYSTICK, env="playground/T1JoystickFlatTerrain"),
    # G1 on Warp: 128 constraints per environment, not Playground's 90 (random warm-up actions
    # reached 94 on an H100, benchmarks/warp_buffers.py; T1 stays under its 80 at 59).
    "g1": dict(_HUMANOID_JOYSTICK, env="playground/G1JoystickFlatTerrain", njmax=128),
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
    """The config of a named preset (the defaults for ``None``)."""
    if name is None:
        return TrainConfig()
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; known: {', '.join(PRESETS)}")
    return TrainConfig(**PRESETS[name])
