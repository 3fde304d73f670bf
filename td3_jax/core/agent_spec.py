"""The agent's static structure (:class:`AgentSpec`, :class:`AgentOptions`) and its float
settings (:class:`AgentHyperparams`), with the choices each option takes.

A spec is hashable and fixes shapes (a changed spec is a new compiled program); hyperparameters
are a pytree of scalars that may be traced, so a sweep over them is a ``jax.vmap``.
"""

from __future__ import annotations

import dataclasses

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from flax import struct

METRIC_NAMES = ("critic_loss", "actor_loss", "actor_updated", "q_mean", "target_mean")


#: Adam's direction (b1 0.9, b2 0.999, eps 1e-8), one shared instance so that specs compare equal.
ADAM = optax.scale_by_adam()


#: Choices of :attr:`AgentOptions.precision`, :attr:`~AgentOptions.actor_q` and
#: :attr:`~AgentOptions.lr_schedule`.
PRECISIONS = {"float32": None, "bfloat16": jnp.bfloat16}
ACTOR_Q = ("first", "min", "mean")
LR_SCHEDULES = ("constant", "cosine")
#: Choices of :attr:`AgentOptions.target_update` and :attr:`~AgentOptions.c51_target_head`.
TARGET_UPDATES = ("with_actor", "every_update")
C51_TARGET_HEADS = ("unprojected", "projected")
#: Choices of :attr:`AgentOptions.actor_network` and :attr:`~AgentOptions.critic_network`.
NETWORKS = ("mlp", "residual")


@dataclasses.dataclass(frozen=True)
class AgentOptions:
    """Static options beyond plain TD3/DDPG (FastTD3's recipe), each off by default.

    Attributes:
      num_atoms: 0 for plain critics; otherwise C51 critics with this many atoms (>= 2) on the
        support ``[v_min, v_max]`` of :class:`AgentHyperparams`
        (:mod:`td3_jax.core.distributional`).
      actor_hidden_sizes, critic_hidden_sizes: the actor's and the critics' hidden widths
        (``None``: the ``hidden_sizes`` given to :func:`make_spec`).
      layer_norm: LayerNorm after every hidden layer (before the ReLU) of actor and critics.
      precision: ``float32`` or ``bfloat16`` matmuls (parameters, optimiser states and losses
        stay float32).
      target_actor: keep a Polyak-averaged target actor for the target action; ``False`` uses
        the online actor (plus smoothing noise) and keeps no target actor (FastTD3).
      actor_q: what the actor maximises: ``first`` (critic head 0, the TD3 paper), ``min`` (the
        lower head per sample) or ``mean`` (the heads' mean), see
        :func:`td3_jax.core.losses.reduce_heads`.
      lr_schedule: ``constant`` or ``cosine`` (from the learning rate down to 0 over
        ``schedule_updates`` updates, then 0).
      schedule_updates: the cosine schedule's length in updates (required with cosine).
      clip_grads: clip gradients to the global norm ``max_grad_norm`` of
        :class:`AgentHyperparams` before Adam.
      bound_weights: after every optimiser step, scale each unit's incoming weights (a column
        of every Dense kernel, actor and critics) down to the norm ``max_weight_norm`` of
        :class:`AgentHyperparams` where they exceed it (:func:`bound_weight_norms`).
      critic_feature_norm: the critics' hidden features projected onto the sphere of radius
        ``sqrt(width)`` after every ReLU, or every residual block
        (:func:`td3_jax.core.networks.sphere_features`); the actor, which export writes out, is
        unchanged.
      critic_network: ``mlp`` (the plain ReLU network) or ``residual``
        (:class:`td3_jax.core.networks.ResidualMLP`, FlashSAC's layout: one block per entry of the
        critics' hidden sizes, which must be equal).
      actor_network: the same choice for the actor (FlashSAC's actor: residual, ``128 128``).
      target_update: when the target critics are Polyak-averaged: ``with_actor`` (in the
        delayed actor step, every ``policy_freq`` updates, the TD3 paper) or ``every_update``
        (after every critic step, FastTD3). A target actor always moves with the actor.
      c51_target_head: how a C51 target picks the target head per sample: ``unprojected`` (the
        lower mean of the next-state distributions, then projected) or ``projected`` (project
        every head's moved distribution, take the one with the lower mean on the support,
        FastTD3). They differ where ``r + discount * z`` leaves ``[v_min, v_max]``.
    """

    num_atoms: int = 0
    actor_hidden_sizes: tuple[int, ...] | None = None
    critic_hidden_sizes: tuple[int, ...] | None = None
    layer_norm: bool = False
    precision: str = "float32"
    target_actor: bool = True
    actor_q: str = "first"
    lr_schedule: str = "constant"
    schedule_updates: int | None = None
    clip_grads: bool = False
    bound_weights: bool = False
    critic_feature_norm: bool = False
    critic_network: str = "mlp"
    actor_network: str = "mlp"
    target_update: str = "with_actor"
    c51_target_head: str = "unprojected"


@dataclasses.dataclass(frozen=True)
class AgentSpec:
    """The static structure of an actor-critic agent.

    Attributes:
      actor: ``obs [..., obs_size] -> action [..., action_size]`` in ``[-max_action, max_action]``.
      critic: ``(obs, action) -> q [num_critics, ...]``.
      observation_size, action_size: input and output sizes.
      policy_freq: the actor and the targets are updated every ``policy_freq`` updates.
      target_smoothing: TD3's clipped noise on the target action (off for DDPG).
      optimizer: the optimiser's direction (Adam's moments); the learning rate is applied from
        :class:`AgentHyperparams` at every step.
      options: the :class:`AgentOptions` the agent was built with.
      critic_observation_size: the critics' input size when they see another observation than
        the actor (``Transition.critic_obs``, an asymmetric actor-critic); ``None``: ``obs``.
    """

    actor: nn.Module
    critic: nn.Module
    observation_size: int
    action_size: int
    policy_freq: int = 2
    target_smoothing: bool = True
    optimizer: optax.GradientTransformation = ADAM
    options: AgentOptions = AgentOptions()
    critic_observation_size: int | None = None

    @property
    def num_critics(self) -> int:
        return self.critic.num_critics

    @property
    def distributional(self) -> bool:
        """Whether the critics are C51 critics (logits over atoms)."""
        return self.options.num_atoms > 0


@struct.dataclass
class AgentHyperparams:
    """The agent's float settings, scalars that may be traced (vmapped in sweeps).

    ``weight_decay``: decoupled (AdamW) weight decay, 0 for none. ``max_grad_norm``: the global
    gradient norm bound (used when :attr:`AgentOptions.clip_grads`). ``max_weight_norm``: the
    bound on each unit's incoming weight norm (used when :attr:`AgentOptions.bound_weights`).
    ``v_min``, ``v_max``: the C51 support (used by distributional critics).
    ``lr_final_fraction``: where a cosine schedule ends, as a fraction of the learning rate
    (used with ``AgentOptions.lr_schedule == "cosine"``).
    """

    discount: jax.Array
    tau: jax.Array
    actor_lr: jax.Array
    critic_lr: jax.Array
    policy_noise: jax.Array
    noise_clip: jax.Array
    weight_decay: jax.Array = 0.0
    max_grad_norm: jax.Array = float("inf")
    max_weight_norm: jax.Array = float("inf")
    v_min: jax.Array = -10.0
    v_max: jax.Array = 10.0
    lr_final_fraction: jax.Array = 0.0


__all__ = [
    "ACTOR_Q",
    "ADAM",
    "C51_TARGET_HEADS",
    "LR_SCHEDULES",
    "METRIC_NAMES",
    "NETWORKS",
    "PRECISIONS",
    "TARGET_UPDATES",
    "AgentHyperparams",
    "AgentOptions",
    "AgentSpec",
]
