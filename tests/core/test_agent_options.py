"""The agent options beyond plain TD3 (FastTD3's and FlashSAC's), each shown to change exactly
what it should.

AdamW, gradient clipping and the cosine schedule against optax's own ``adamw``,
``clip_by_global_norm`` and ``cosine_decay_schedule`` on the same gradients; LayerNorm against
a NumPy forward pass; bf16 against float32; the actor objectives and the missing target actor
against hand computations from the shared forward passes. Tiny networks, few compiles.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from td3_jax.cli import app as cli
from td3_jax.common.errors import Td3JaxError
from td3_jax.config.build import agent_options, agent_settings
from td3_jax.config.presets import preset
from td3_jax.config.schema import ConfigError, TrainConfig, validate
from td3_jax.core import actor_critic as ac
from td3_jax.core import losses
from td3_jax.core.types import Transition

OBS, ACT, BATCH, HIDDEN = 3, 2, 8, (8, 8)


@functools.cache
def spec_of(num_critics=2, **options):
    return ac.make_spec(
        HIDDEN,
        OBS,
        ACT,
        num_critics=num_critics,
        target_smoothing=True,
        policy_freq=1,
        options=ac.AgentOptions(**options),
    )


def hparams(**kw):
    values = dict(
        discount=0.9, tau=0.3, actor_lr=3e-3, critic_lr=5e-3, policy_noise=0.2, noise_clip=0.5
    )
    return ac.hyperparams(type("C", (), values)(), **kw)


def init(spec, seed=0):
    return jax.jit(functools.partial(ac.init, spec))(jax.random.key(seed))


def make_batch(seed):
    rng = np.random.default_rng(seed)
    f32 = np.float32
    return Transition(
        obs=rng.normal(size=(BATCH, OBS)).astype(f32),
        action=rng.uniform(-1, 1, (BATCH, ACT)).astype(f32),
        reward=rng.normal(size=(BATCH,)).astype(f32),
        next_obs=rng.normal(size=(BATCH, OBS)).astype(f32),
        done=(rng.uniform(size=(BATCH,)) < 0.3).astype(f32),
    )


def random_grads(params, seed, scale):
    leaves, tree = jax.tree.flatten(params)
    rng = np.random.default_rng(seed)
    return jax.tree.unflatten(tree, [jnp.float32(scale * rng.normal(size=x.shape)) for x in leaves])


def assert_trees_close(a, b, atol=1e-6, rtol=1e-5):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), atol=atol, rtol=rtol)


# --------------------------------------------------------------------------------------------
# the optimiser: AdamW, clipping, cosine schedule against optax
# --------------------------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnums=0)
def descend_steps(spec, hp, params, grads_seq, lr):
    """``descend`` over a sequence of gradients (leaves ``[steps, ...]``), scheduled lr."""

    def step(carry, xs):
        params, opt_state = carry
        grads, i = xs
        rate = ac.learning_rate(spec, lr, i)
        return ac.descend(spec, hp, params, grads, opt_state, rate), None

    steps = jax.tree.leaves(grads_seq)[0].shape[0]
    opt_state = spec.optimizer.init(params)
    (params, _), _ = jax.lax.scan(step, (params, opt_state), (grads_seq, jnp.arange(steps)))
    return params


def optax_steps(transform, params, grads_seq):
    state = transform.init(params)
    for i in range(jax.tree.leaves(grads_seq)[0].shape[0]):
        grads = jax.tree.map(lambda g, i=i: g[i], grads_seq)
        updates, state = transform.update(grads, state, params)
        params = optax.apply_updates(params, updates)
    return params


CASES = {
    "adam": (dict(), dict(weight_decay=0.0), lambda lr: optax.adam(lr)),
    "adamw": (dict(), dict(weight_decay=0.1), lambda lr: optax.adamw(lr, weight_decay=0.1)),
    "adamw+clip": (
        dict(clip_grads=True),
        dict(weight_decay=0.3, max_grad_norm=0.5),
        lambda lr: optax.chain(optax.clip_by_global_norm(0.5), optax.adamw(lr, weight_decay=0.3)),
    ),
    "cosine": (
        dict(lr_schedule="cosine", schedule_updates=4),
        dict(weight_decay=0.1),
        lambda lr: optax.adamw(optax.cosine_decay_schedule(lr, 4), weight_decay=0.1),
    ),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_descend_matches_optax_on_the_same_gradients(case):
    options, settings, transform = CASES[case]
    spec, hp, lr = spec_of(**options), hparams(**settings), 0.05
    params = init(spec).actor_params
    # Six steps of large gradients (the clipping bound is far below their norms).
    grads_seq = jax.tree.map(
        lambda *g: jnp.stack(g), *[random_grads(params, s, 3.0) for s in range(6)]
    )
    ours = descend_steps(spec, hp, params, grads_seq, jnp.float32(lr))
    assert_trees_close(ours, optax_steps(transform(lr), params, grads_seq))
    if case != "adam":  # and the option really changes the result
        plain = descend_steps(spec_of(), hparams(), params, grads_seq, jnp.float32(lr))
        assert any(
            not np.allclose(a, b)
            for a, b in zip(jax.tree.leaves(ours), jax.tree.leaves(plain), strict=True)
        )


def test_the_gradient_bound_is_ignored_unless_clipping_is_on():
    spec, lr = spec_of(), jnp.float32(0.05)
    params = init(spec).actor_params
    grads = jax.tree.map(lambda g: g[None], random_grads(params, 1, 3.0))
    a = descend_steps(spec, hparams(max_grad_norm=1e-3), params, grads, lr)
    b = descend_steps(spec, hparams(), params, grads, lr)
    assert_trees_close(a, b, atol=0, rtol=0)


def np_bound_columns(kernel, max_norm):
    """Each column (a unit's incoming weights, axis -2) scaled down to ``max_norm``, float64."""
    k = np.asarray(kernel, np.float64)
    norms = np.sqrt((k**2).sum(axis=-2, keepdims=True))
    return k * np.where(norms > max_norm, max_norm / norms, 1.0)


def test_bounded_weights_match_numpy_after_each_step():
    """Adam steps on large gradients, then every kernel column (actor ``[in, out]`` and the
    critics' stacked ``[heads, in, out]``) above the bound is scaled down to it; biases are
    not bounded; the plain step is the same without the bound."""
    spec, lr, bound = spec_of(bound_weights=True), jnp.float32(0.5), 0.8
    state = init(spec)
    for params in (state.actor_params, state.critic_params):
        grads = random_grads(params, 2, 3.0)
        plain = descend_steps(
            spec_of(), hparams(), params, jax.tree.map(lambda g: g[None], grads), lr
        )
        ours = descend_steps(spec, hparams(max_weight_norm=bound), params,
                             jax.tree.map(lambda g: g[None], grads), lr)  # fmt: skip
        for (path, got), want in zip(jax.tree_util.tree_leaves_with_path(ours),
                                     jax.tree.leaves(plain), strict=True):  # fmt: skip
            if jax.tree_util.keystr(path).endswith("['kernel']"):
                want = np_bound_columns(want, bound)
                assert np.sqrt((np.asarray(got) ** 2).sum(-2)).max() <= bound + 1e-5
            np.testing.assert_allclose(np.asarray(got), want, atol=1e-6, rtol=1e-5)
        assert any(
            not np.allclose(a, b)
            for a, b in zip(jax.tree.leaves(ours), jax.tree.leaves(plain), strict=True)
        )
    # The bound unset (inf) leaves every weight alone.
    loose = descend_steps(spec, hparams(), params, jax.tree.map(lambda g: g[None], grads), lr)
    assert_trees_close(loose, plain, atol=0, rtol=0)


def test_critic_feature_norm_against_numpy():
    """Two critics whose hidden features (after each ReLU) are scaled to norm sqrt(width),
    recomputed in NumPy from their parameters; the actor's parameters and outputs are those of
    the plain spec."""
    spec = spec_of(critic_feature_norm=True)
    state = init(spec)
    batch = make_batch(3)
    got = np.asarray(spec.critic.apply(state.critic_params, batch.obs, batch.action))
    layers = state.critic_params["params"]["VmapCritic_0"]["MLP_0"]
    x0 = np.concatenate([batch.obs, batch.action], axis=-1).astype(np.float64)
    for head in range(2):
        x = x0
        for i in range(len(HIDDEN)):
            h = x @ np.asarray(layers[f"Dense_{i}"]["kernel"][head], np.float64)
            h = np.maximum(h + np.asarray(layers[f"Dense_{i}"]["bias"][head]), 0.0)
            x = h * np.sqrt(h.shape[-1]) / np.linalg.norm(h, axis=-1, keepdims=True)
        last = layers[f"Dense_{len(HIDDEN)}"]
        want = x @ np.asarray(last["kernel"][head], np.float64) + np.asarray(last["bias"][head])
        np.testing.assert_allclose(got[head], want[:, 0], atol=1e-5)
    plain = init(spec_of())
    assert_trees_close(state.actor_params, plain.actor_params, atol=0, rtol=0)
    plain_q = spec_of().critic.apply(state.critic_params, batch.obs, batch.action)
    assert not np.allclose(np.asarray(plain_q), got)


def np_layer_norm(x, scale, bias, eps=1e-6):
    mean = x.mean(-1, keepdims=True)
    var = ((x - mean) ** 2).mean(-1, keepdims=True)
    return (x - mean) / np.sqrt(var + eps) * scale + bias


def np_residual_critic(layers, head, x, blocks, feature_norm):
    """FlashSAC's layout (LayerNorm for its BatchNorm) in NumPy from one head's parameters."""
    p = lambda kind, i, name: np.asarray(layers[f"{kind}_{i}"][name][head], np.float64)
    dense = lambda i, z: z @ p("Dense", i, "kernel") + p("Dense", i, "bias")
    norm = lambda i, z: np_layer_norm(z, p("LayerNorm", i, "scale"), p("LayerNorm", i, "bias"))
    h = dense(0, x)
    for b in range(blocks):
        y = np.maximum(norm(2 * b, dense(2 * b + 1, h)), 0.0)
        h = h + np.maximum(norm(2 * b + 1, dense(2 * b + 2, y)), 0.0)
        if feature_norm:
            h = h * np.sqrt(h.shape[-1]) / np.linalg.norm(h, axis=-1, keepdims=True)
    rms = np.sqrt((h**2).mean(-1, keepdims=True) + 1e-6)
    return dense(2 * blocks + 1, h / rms * p("RMSNorm", 0, "scale"))


@pytest.mark.parametrize("feature_norm", [False, True])
def test_residual_critic_against_numpy(feature_norm):
    """Two residual C51 critics of two blocks of width 8 (8 -> 32 -> 8), every parameter
    redrawn (LayerNorm and RMSNorm scales and biases too, so each is shown used), against the
    NumPy forward pass; the layout names what the docstring says; the actor is the plain
    spec's."""
    spec = spec_of(critic_network="residual", num_atoms=5, critic_feature_norm=feature_norm)
    state = init(spec)
    params = random_grads(state.critic_params, 3, 0.5)  # (any tree of normal draws)
    layers = params["params"]["VmapDistributionalCritic_0"]["ResidualMLP_0"]
    shapes = {k: {n: v.shape for n, v in layer.items()} for k, layer in layers.items()}
    assert shapes == {
        "Dense_0": {"kernel": (2, OBS + ACT, 8), "bias": (2, 8)},
        "Dense_1": {"kernel": (2, 8, 32), "bias": (2, 32)},
        "LayerNorm_0": {"scale": (2, 32), "bias": (2, 32)},
        "Dense_2": {"kernel": (2, 32, 8), "bias": (2, 8)},
        "LayerNorm_1": {"scale": (2, 8), "bias": (2, 8)},
        "Dense_3": {"kernel": (2, 8, 32), "bias": (2, 32)},
        "LayerNorm_2": {"scale": (2, 32), "bias": (2, 32)},
        "Dense_4": {"kernel": (2, 32, 8), "bias": (2, 8)},
        "LayerNorm_3": {"scale": (2, 8), "bias": (2, 8)},
        "RMSNorm_0": {"scale": (2, 8)},
        "Dense_5": {"kernel": (2, 8, 5), "bias": (2, 5)},
    }
    batch = make_batch(4)
    got = np.asarray(spec.critic.apply(params, batch.obs, batch.action))
    x = np.concatenate([batch.obs, batch.action], axis=-1).astype(np.float64)
    for head in range(2):
        want = np_residual_critic(layers, head, x, 2, feature_norm)
        np.testing.assert_allclose(got[head], want, atol=2e-5, rtol=2e-5)
    assert_trees_close(state.actor_params, init(spec_of(num_atoms=5)).actor_params, atol=0, rtol=0)


def test_a_plain_residual_critic_in_bfloat16():
    """Plain (one-value) residual critics: ``q[2, batch]``, the NumPy forward pass's single
    output in float32; in bfloat16 the matmuls run in bf16, parameters and outputs stay
    float32 and the values stay close to float32's."""
    spec32 = spec_of(critic_network="residual")
    spec16 = spec_of(critic_network="residual", precision="bfloat16")
    state = init(spec16)
    params = random_grads(state.critic_params, 5, 0.5)
    layers = params["params"]["VmapCritic_0"]["ResidualMLP_0"]
    batch = make_batch(6)
    q32 = np.asarray(spec32.critic.apply(params, batch.obs, batch.action))
    x = np.concatenate([batch.obs, batch.action], axis=-1).astype(np.float64)
    for head in range(2):
        want = np_residual_critic(layers, head, x, 2, False)[:, 0]
        np.testing.assert_allclose(q32[head], want, atol=2e-5, rtol=2e-5)
    q16 = spec16.critic.apply(params, batch.obs, batch.action)
    assert q16.dtype == jnp.float32 and float_dtypes(state) == {np.dtype(np.float32)}
    jaxpr = str(jax.make_jaxpr(spec16.critic.apply)(params, batch.obs, batch.action))
    assert all(":bf16[" in line for line in jaxpr.splitlines() if "dot_general" in line)
    np.testing.assert_allclose(q16, q32, atol=0.1, rtol=0.05)
    assert not np.array_equal(q16, q32)


def test_residual_actor_against_numpy():
    """A residual actor of two blocks of width 8 (``--actor-network residual``), every
    parameter redrawn, against the NumPy forward pass then ``max_action * tanh``; one actor step
    moves every one of its parameters (each gets a gradient); the critics are the plain spec's."""
    spec = spec_of(actor_network="residual")
    state = init(spec)
    params = random_grads(state.actor_params, 4, 0.5)
    layers = params["params"]["ResidualMLP_0"]
    assert sorted(layers) == ["Dense_0", "Dense_1", "Dense_2", "Dense_3", "Dense_4", "Dense_5",
                              "LayerNorm_0", "LayerNorm_1", "LayerNorm_2", "LayerNorm_3",
                              "RMSNorm_0"]  # fmt: skip
    assert layers["Dense_1"]["kernel"].shape == (8, 32) and layers["Dense_5"]["bias"].shape == (
        ACT,
    )
    batch = make_batch(7)
    got = np.asarray(spec.actor.apply(params, batch.obs))
    with_head = jax.tree.map(lambda a: np.asarray(a)[None], layers)  # (the critics' helper)
    want = np.tanh(np_residual_critic(with_head, 0, batch.obs.astype(np.float64), 2, False))
    np.testing.assert_allclose(got, want, atol=2e-5, rtol=2e-5)
    assert_trees_close(state.critic_params, init(spec_of()).critic_params, atol=0, rtol=0)
    stepped, _ = jax.jit(functools.partial(ac.actor_step, spec, hparams()))(state, batch)
    for before, after in zip(jax.tree.leaves(state.actor_params),
                             jax.tree.leaves(stepped.actor_params), strict=True):  # fmt: skip
        assert not np.allclose(np.asarray(before), np.asarray(after))


def test_a_residual_actor_needs_blocks_of_one_width():
    """Unequal actor widths are refused by the library and by the config (naming the flag that
    set them and an example); the option reaches the agent's options; the critics may stay
    plain and of several widths."""
    with pytest.raises(ValueError, match="one width"):
        ac.make_spec((8, 4), OBS, ACT, num_critics=2, target_smoothing=True, policy_freq=1,
                     options=ac.AgentOptions(actor_network="residual"))  # fmt: skip
    with pytest.raises(ConfigError, match=r"--actor-network residual: --actor-hidden-sizes: "
                       r".*not 64 32; give one, e.g. --actor-hidden-sizes 128 128"):  # fmt: skip
        validate(TrainConfig(actor_network="residual", actor_hidden_sizes=(64, 32)))
    with pytest.raises(ConfigError, match=r"--actor-network residual: --hidden-sizes: .*64 32"):
        validate(TrainConfig(actor_network="residual", hidden_sizes=(64, 32)))
    cfg = validate(TrainConfig(actor_network="residual", hidden_sizes=(64, 32),
                               actor_hidden_sizes=(16, 16)))  # fmt: skip
    assert (agent_options(cfg).actor_network, agent_options(cfg).critic_network) == (
        "residual",
        "mlp",
    )
    assert agent_options(TrainConfig()).actor_network == "mlp"
    with pytest.raises(ConfigError, match="actor-network"):
        validate(TrainConfig(actor_network="resnet"))


def test_a_residual_critic_needs_blocks_of_one_width():
    """Unequal widths are refused by the library (ValueError) and the config (ConfigError
    naming the flag that set them); a plain critic takes them; the config's option reaches
    the agent's options."""
    with pytest.raises(ValueError, match="one width"):
        ac.make_spec((8, 4), OBS, ACT, num_critics=2, target_smoothing=True, policy_freq=1,
                     options=ac.AgentOptions(critic_network="residual"))  # fmt: skip
    with pytest.raises(ConfigError, match=r"--critic-hidden-sizes: .* one width.*not 64 32"):
        validate(TrainConfig(critic_network="residual", critic_hidden_sizes=(64, 32)))
    with pytest.raises(ConfigError, match=r"--hidden-sizes: .* one width.*not 64 32"):
        validate(TrainConfig(critic_network="residual", hidden_sizes=(64, 32)))
    # None: the algorithm's own sizes (TD3 400 300, DDPG 256 256)
    with pytest.raises(ConfigError, match=r"--algo td3's default.*not 400 300"):
        validate(TrainConfig(critic_network="residual", hidden_sizes=None))
    validate(TrainConfig(critic_network="residual", hidden_sizes=None, algo="ddpg"))
    residual = TrainConfig(critic_network="residual", hidden_sizes=(64, 32),
                           critic_hidden_sizes=(16, 16))  # fmt: skip
    assert agent_options(validate(residual)).critic_network == "residual"
    assert agent_options(TrainConfig()).critic_network == "mlp"
    with pytest.raises(ConfigError, match="critic-network"):
        validate(TrainConfig(critic_network="resnet"))
    with pytest.raises(ConfigError, match=r"--hidden-sizes must be positive integers, got 0$"):
        validate(TrainConfig(hidden_sizes=(0,)))
    with pytest.raises(ConfigError, match=r"--critic-hidden-sizes must be .*, got no values$"):
        validate(TrainConfig(critic_hidden_sizes=()))


def test_cosine_learning_rate_by_hand():
    spec = spec_of(lr_schedule="cosine", schedule_updates=10)
    for step, expected in (
        (0, 1.0),
        (5, 0.5),
        (10, 0.0),
        (25, 0.0),
        (2, 0.5 * (1 + np.cos(0.2 * np.pi))),
    ):
        got = ac.learning_rate(spec, jnp.float32(2.0), jnp.int32(step))
        np.testing.assert_allclose(float(got), 2.0 * expected, atol=1e-6)
    assert float(ac.learning_rate(spec_of(), jnp.float32(2.0), jnp.int32(7))) == 2.0


def test_cosine_learning_rate_with_a_floor_by_hand():
    # FlashSAC's schedule: from lr to half of it. Half-way: 0.75 lr; at and past the end: 0.5 lr.
    spec = spec_of(lr_schedule="cosine", schedule_updates=10)
    half = jnp.float32(0.5)
    for step, expected in ((0, 1.0), (5, 0.75), (10, 0.5), (25, 0.5),
                           (2, 0.5 + 0.5 * 0.5 * (1 + np.cos(0.2 * np.pi)))):  # fmt: skip
        got = ac.learning_rate(spec, jnp.float32(2.0), jnp.int32(step), half)
        np.testing.assert_allclose(float(got), 2.0 * expected, atol=1e-6)
    floors = jnp.asarray([0.0, 0.25, 1.0])  # traced: a sweep's members, one vmap
    at_end = jax.vmap(lambda f: ac.learning_rate(spec, jnp.float32(2.0), jnp.int32(10), f))
    np.testing.assert_allclose(at_end(floors), [0.0, 0.5, 2.0], atol=1e-6)


def test_updates_past_a_cosine_schedule_with_its_floor_at_one_are_those_of_a_constant_rate():
    # A schedule of 1 update: from the second update on it sits at its floor, lr * f; with f
    # = 1 every update (actor and critics) equals the constant schedule's, with f = 0 none
    # learns past the first.
    cosine, constant = spec_of(lr_schedule="cosine", schedule_updates=1), spec_of()
    update = lambda spec, hp, state, seed: jax.jit(ac.update, static_argnums=0)(
        spec, hp, state, make_batch(seed), jax.random.key(seed)
    )[0]
    runs = {}
    for name, spec, hp in (("floor 1", cosine, hparams(lr_final_fraction=1.0)),
                           ("constant", constant, hparams()),
                           ("floor 0", cosine, hparams(lr_final_fraction=0.0))):  # fmt: skip
        state = update(spec, hp, init(constant), 1)
        runs[name] = (state, update(spec, hp, state, 2))
    assert_trees_close(runs["floor 1"][1].critic_params, runs["constant"][1].critic_params)
    assert_trees_close(runs["floor 1"][1].actor_params, runs["constant"][1].actor_params)
    first, second = runs["floor 0"]
    assert_trees_close(first.critic_params, second.critic_params, atol=0, rtol=0)


def test_a_floor_outside_zero_to_one_or_without_a_cosine_schedule_is_refused():
    with pytest.raises(ConfigError, match=r"^--lr-final-fraction must be in \[0, 1\]"):
        validate(TrainConfig(lr_schedule="cosine", lr_final_fraction=1.5))
    with pytest.raises(ConfigError, match=r"^--lr-final-fraction must be in \[0, 1\], got -0.1"):
        validate(TrainConfig(lr_schedule="cosine", lr_final_fraction=-0.1))
    with pytest.raises(ConfigError, match="applies to --lr-schedule cosine"):
        validate(TrainConfig(lr_final_fraction=0.5))
    assert validate(TrainConfig(lr_schedule="cosine", lr_final_fraction=0.5))


# --------------------------------------------------------------------------------------------
# networks: widths, LayerNorm, bf16
# --------------------------------------------------------------------------------------------


def test_separate_actor_and_critic_widths():
    spec = spec_of(actor_hidden_sizes=(4,), critic_hidden_sizes=(6, 5))
    state = jax.eval_shape(functools.partial(ac.init, spec), jax.random.key(0))
    actor = sorted(x.shape for x in jax.tree.leaves(state.actor_params))
    critic = sorted(x.shape for x in jax.tree.leaves(state.critic_params))
    assert actor == sorted([(OBS, 4), (4,), (4, ACT), (ACT,)])
    assert critic == sorted([(2, OBS + ACT, 6), (2, 6), (2, 6, 5), (2, 5), (2, 5, 1), (2, 1)])


def np_layer_norm_mlp(layers, x, eps=1e-6):
    """ReLU(LayerNorm(Dense)) hidden layers, then a Dense output (float64)."""
    x = np.asarray(x, np.float64)
    for i in range(len(layers) // 2):
        dense, norm = layers[f"Dense_{i}"], layers[f"LayerNorm_{i}"]
        h = x @ np.asarray(dense["kernel"], np.float64) + np.asarray(dense["bias"])
        h = (h - h.mean(-1, keepdims=True)) / np.sqrt(h.var(-1, keepdims=True) + eps)
        x = np.maximum(h * np.asarray(norm["scale"]) + np.asarray(norm["bias"]), 0.0)
    last = layers[f"Dense_{len(layers) // 2}"]
    return x @ np.asarray(last["kernel"], np.float64) + np.asarray(last["bias"])


def test_layer_norm_actor_against_numpy_and_absent_by_default():
    spec = spec_of(layer_norm=True)
    params = init(spec).actor_params
    layers = params["params"]["MLP_0"]
    # Non-trivial LayerNorm parameters, so scale and bias are exercised.
    layers = {
        k: (
            {n: v + 0.3 * (i + 1) for i, (n, v) in enumerate(p.items())}
            if k.startswith("LayerNorm")
            else p
        )
        for k, p in layers.items()
    }
    params = {"params": {"MLP_0": layers}}
    obs = np.random.default_rng(0).normal(size=(5, OBS)).astype(np.float32)
    expected = np.tanh(np_layer_norm_mlp(layers, obs))
    np.testing.assert_allclose(np.asarray(spec.actor.apply(params, obs)), expected, atol=1e-5)
    assert sorted(layers) == ["Dense_0", "Dense_1", "Dense_2", "LayerNorm_0", "LayerNorm_1"]
    plain = init(spec_of()).critic_params
    assert not any(
        "LayerNorm" in jax.tree_util.keystr(p)
        for p, _ in jax.tree_util.tree_leaves_with_path(plain)
    )


def float_dtypes(tree):
    return {x.dtype for x in jax.tree.leaves(tree) if jnp.issubdtype(x.dtype, jnp.floating)}


def test_bfloat16_matmuls_with_float32_parameters_and_outputs():
    spec16, spec32 = spec_of(precision="bfloat16"), spec_of()
    state = init(spec16)
    assert float_dtypes(state) == {np.dtype(np.float32)}
    batch = make_batch(0)
    q16 = spec16.critic.apply(state.critic_params, batch.obs, batch.action)
    q32 = spec32.critic.apply(state.critic_params, batch.obs, batch.action)
    assert (
        q16.dtype == jnp.float32
        and spec16.actor.apply(state.actor_params, batch.obs).dtype == jnp.float32
    )
    np.testing.assert_allclose(q16, q32, atol=0.05, rtol=0.05)
    assert not np.array_equal(q16, q32)  # really computed in bf16
    jaxpr = str(jax.make_jaxpr(spec16.critic.apply)(state.critic_params, batch.obs, batch.action))
    matmuls = [line for line in jaxpr.splitlines() if "dot_general" in line]
    assert matmuls and all(":bf16[" in line for line in matmuls)
    new, _ = jax.jit(ac.update, static_argnums=0)(
        spec16, hparams(), state, batch, jax.random.key(0)
    )
    assert float_dtypes(new) == {np.dtype(np.float32)}


# --------------------------------------------------------------------------------------------
# no target actor, actor objectives
# --------------------------------------------------------------------------------------------


def test_without_a_target_actor_the_target_uses_the_online_actor():
    spec, hp = spec_of(target_actor=False), hparams()
    state = init(spec)
    assert state.target_actor_params is None
    batch, key = make_batch(3), jax.random.key(4)
    # Targets differ from the online critic, so that both are visible in the result.
    state = state.replace(
        target_critic_params=jax.tree.map(lambda x: x * 1.5 + 0.1, state.target_critic_params)
    )
    new, metrics = jax.jit(ac.update, static_argnums=0)(spec, hp, state, batch, key)
    # Hand target: the online actor's action plus clipped noise (same draw), min of target heads.
    pi = spec.actor.apply(state.actor_params, batch.next_obs)
    eps = jax.random.normal(key, pi.shape)
    a = jnp.clip(pi + jnp.clip(0.2 * eps, -0.5, 0.5), -1.0, 1.0)
    q = np.asarray(spec.critic.apply(state.target_critic_params, batch.next_obs, a))
    y = batch.reward + 0.9 * (1.0 - batch.done) * np.minimum(q[0], q[1])
    np.testing.assert_allclose(float(metrics["target_mean"]), y.mean(), rtol=1e-5, atol=1e-6)
    assert new.target_actor_params is None
    assert_trees_close(
        new.target_critic_params,
        jax.tree.map(lambda o, t: 0.3 * o + 0.7 * t, new.critic_params, state.target_critic_params),
    )


@pytest.mark.parametrize(
    "how, reduce", [("first", lambda q: q[0]), ("min", np.min), ("mean", np.mean)]
)
def test_actor_objective(how, reduce):
    spec, hp = spec_of(actor_q=how), hparams()
    state, batch = init(spec, 1), make_batch(5)
    loss = losses.actor_loss(state.actor_params, state.critic_params, spec, hp, batch)
    q = np.asarray(
        spec.critic.apply(
            state.critic_params, batch.obs, spec.actor.apply(state.actor_params, batch.obs)
        )
    )
    expected = -np.mean(reduce(q, axis=0) if how != "first" else q[0])
    np.testing.assert_allclose(float(loss), expected, rtol=1e-5)
    assert q[0].mean() != pytest.approx(np.min(q, 0).mean())  # the choices differ here


def test_distributional_actor_objective_is_on_the_critics_means():
    spec, hp = spec_of(num_atoms=7, actor_q="mean"), hparams(v_min=-1.0, v_max=5.0)
    state, batch = init(spec, 2), make_batch(6)
    action = spec.actor.apply(state.actor_params, batch.obs)
    logits = np.asarray(spec.critic.apply(state.critic_params, batch.obs, action), np.float64)
    p = np.exp(logits) / np.exp(logits).sum(-1, keepdims=True)
    expected = -np.mean(p @ np.linspace(-1.0, 5.0, 7))
    loss = losses.actor_loss(state.actor_params, state.critic_params, spec, hp, batch)
    np.testing.assert_allclose(float(loss), expected, rtol=1e-5)


def test_float_options_are_vmappable_like_the_other_hyperparameters():
    spec = spec_of(num_atoms=5, clip_grads=True)
    state, batch, key = init(spec), make_batch(7), jax.random.key(8)
    settings = [
        dict(weight_decay=0.0, v_max=2.0, max_grad_norm=0.1),
        dict(weight_decay=0.2, v_max=6.0, max_grad_norm=10.0),
    ]
    each = [hparams(**s) for s in settings]
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *each)
    update = jax.jit(ac.update, static_argnums=0)
    swept, _ = jax.jit(jax.vmap(functools.partial(ac.update, spec), in_axes=(0, None, None, None)))(
        stacked, state, batch, key
    )
    for j, hp in enumerate(each):
        single, _ = update(spec, hp, state, batch, key)
        assert_trees_close(jax.tree.map(lambda x, j=j: x[j], swept), single)


@pytest.mark.parametrize("rule", ["with_actor", "every_update"])
def test_target_critics_follow_their_update_rule(rule):
    """Four updates with ``policy_freq=2``: the target critics, recomputed in NumPy from the
    online critics after each update, move on every update (FastTD3) or only on updates 2 and
    4 (the TD3 paper), by ``tau`` each time; a target actor moves on 2 and 4 either way."""
    spec = ac.make_spec(HIDDEN, OBS, ACT, num_critics=2, target_smoothing=True, policy_freq=2,
                        options=ac.AgentOptions(target_update=rule))  # fmt: skip
    hp, tau = hparams(), 0.3
    state = init(spec)
    target = jax.tree.map(np.asarray, state.target_critic_params)
    target_actor = jax.tree.map(np.asarray, state.target_actor_params)
    update = jax.jit(ac.update, static_argnums=0)
    for k in (1, 2, 3, 4):
        state, _ = update(spec, hp, state, make_batch(k), jax.random.key(k))
        polyak = lambda t, p: (1 - tau) * t + tau * np.asarray(p)
        if rule == "every_update" or k % 2 == 0:
            target = jax.tree.map(polyak, target, state.critic_params)
        if k % 2 == 0:
            target_actor = jax.tree.map(polyak, target_actor, state.actor_params)
        assert_trees_close(state.target_critic_params, target)
        assert_trees_close(state.target_actor_params, target_actor)


@pytest.mark.parametrize(
    "options, message",
    [
        (dict(num_atoms=1), "num_atoms"),
        (dict(precision="float16"), "precision"),
        (dict(actor_q="max"), "actor_q"),
        (dict(lr_schedule="linear"), "lr_schedule"),
        (dict(target_update="sometimes"), "target_update"),
        (dict(c51_target_head="best"), "c51_target_head"),
        (dict(actor_hidden_sizes=(0,)), "hidden_sizes"),
    ],
)
def test_impossible_options_are_refused(options, message):
    """Refused as td3-jax's own ConfigError, which is also a ValueError."""
    with pytest.raises(ConfigError, match=message) as err:
        spec_of(**options)
    assert isinstance(err.value, Td3JaxError) and isinstance(err.value, ValueError)


def test_the_python_agents_impossible_settings_are_td3_jaxs_errors():
    """``tj.td3`` with an impossible size or hyperparameter: one ConfigError (errors.md: every
    failure td3-jax foresees is a Td3JaxError), not a bare ValueError."""
    import td3_jax as tj

    with pytest.raises(ConfigError, match="observation_size must be a positive integer"):
        tj.td3(tj.TD3Config(), observation_size=0, action_size=2)
    with pytest.raises(ConfigError, match="tau must be finite"):
        tj.td3(tj.TD3Config(tau=-1.0), observation_size=3, action_size=2)


def test_impossible_float_options_are_refused():
    with pytest.raises(ValueError, match="v_min must be below v_max"):
        hparams(v_min=1.0, v_max=1.0)
    with pytest.raises(ValueError, match="weight_decay"):
        hparams(weight_decay=-0.1)
    with pytest.raises(ValueError, match="max_grad_norm"):
        hparams(max_grad_norm=0.0)


# --------------------------------------------------------------------------------------------
# the training config and the command line
# --------------------------------------------------------------------------------------------


def test_defaults_leave_every_option_off():
    cfg = TrainConfig()
    assert agent_options(cfg) == ac.AgentOptions()
    s = agent_settings(cfg)
    assert s["weight_decay"] == 0.0 and s["max_grad_norm"] is None and not cfg.per_env_noise


def test_config_maps_to_agent_options():
    cfg = TrainConfig(
        critic="distributional",
        num_atoms=51,
        layer_norm=True,
        precision="bfloat16",
        target_actor=False,
        lr_schedule="cosine",
        max_grad_norm=1.0,
        actor_hidden_sizes=(512, 256, 128),
        critic_hidden_sizes=(1024, 512, 256),
    )
    options = agent_options(cfg)
    assert options == ac.AgentOptions(
        num_atoms=51,
        actor_hidden_sizes=(512, 256, 128),
        critic_hidden_sizes=(1024, 512, 256),
        layer_norm=True,
        precision="bfloat16",
        target_actor=False,
        actor_q="min",
        lr_schedule="cosine",
        schedule_updates=cfg.total_updates,
        clip_grads=True,
    )
    # 20k steps of 16 envs: 1250 iterations, learning from iteration 125 (2000 warm-up steps).
    assert cfg.total_updates == (1250 - 125 + 1) * 8
    assert agent_options(dataclasses.replace(cfg, actor_q="mean")).actor_q == "mean"
    assert agent_options(TrainConfig(actor_q="auto")).actor_q == "first"
    bounded = TrainConfig(max_weight_norm=2.0, critic_feature_norm=True)
    assert agent_options(bounded).bound_weights and agent_options(bounded).critic_feature_norm
    assert agent_settings(bounded)["max_weight_norm"] == 2.0
    assert not agent_options(TrainConfig()).bound_weights
    fasttd3 = TrainConfig(target_update="every_update", c51_target_head="projected")
    assert agent_options(fasttd3).target_update == "every_update"
    assert agent_options(fasttd3).c51_target_head == "projected"


@pytest.mark.parametrize("name", ["t1", "g1", "go1"])
def test_presets_that_follow_fasttd3_use_its_target_rules(name):
    options = agent_options(preset(name))
    assert (options.target_update, options.c51_target_head) == ("every_update", "projected")
    paper = agent_options(preset("td3-classic"))
    assert (paper.target_update, paper.c51_target_head) == ("with_actor", "unprojected")


@pytest.mark.parametrize(
    "fields, message",
    [
        (dict(expl_noise_min=0.1), "go together"),
        (dict(expl_noise_min=0.5, expl_noise_max=0.1), "must not exceed"),
        (dict(expl_noise_min=0.1, expl_noise_max=0.2, exploration="ou"), "gaussian"),
        (dict(v_min=3.0, v_max=3.0), "--v-min"),
        (dict(num_atoms=1), "--num-atoms"),
        (dict(max_grad_norm=0.0), "--max-grad-norm"),
        (dict(max_weight_norm=0.0), "--max-weight-norm"),
        (dict(max_weight_norm=float("nan")), "--max-weight-norm"),
        (dict(weight_decay=-1.0), "--weight-decay"),
        (dict(critic_hidden_sizes=()), "--critic-hidden-sizes"),
        (dict(v_max=float("inf")), "--v-max"),
    ],
)
def test_bad_option_settings_are_one_clear_error(fields, message):
    with pytest.raises(ConfigError, match=message):
        validate(TrainConfig(**fields))


NEW_FLAGS = (
    "--critic",
    "--num-atoms",
    "--v-min",
    "--v-max",
    "--actor-q",
    "--target-actor",
    "--no-target-actor",
    "--weight-decay",
    "--max-grad-norm",
    "--lr-schedule",
    "--layer-norm",
    "--actor-hidden-sizes",
    "--critic-hidden-sizes",
    "--precision",
    "--expl-noise-min",
    "--expl-noise-max",
)


def test_train_help_documents_each_option_and_its_default(capsys):
    with pytest.raises(SystemExit) as exit_:
        cli.main(["train", "--help"])
    assert exit_.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    for flag in NEW_FLAGS:
        assert flag in text, flag
    for default in ("plain", "101", "-10.0", "float32", "constant", "auto"):
        assert f"(default: {default})" in text, default


@pytest.mark.runs
def test_a_run_with_every_option_trains_checkpoints_and_resumes(tmp_path):
    """The command with all options on (the cosine schedule checked apart: it cannot be
    extended): finite metrics, config.json keeps them, and --resume restores the state
    (per-environment draws included) and goes on."""
    from td3_jax.runner.logger import read_metrics
    from td3_jax.runner.rundir import load_config

    out = tmp_path / "run"
    flags = (
        "--env gymnax/Pendulum-v1 --hidden-sizes 8 8 --num-envs 2 --steps-per-iter 3 "
        "--updates-per-iter 2 --batch-size 4 --buffer-size 64 --warmup-steps 6 "
        "--eval-every 12 --total-steps 24 --eval-envs 2 --episode-length 10 --n-step 2 "
        "--critic distributional --num-atoms 11 --v-min -50 --v-max 5 --actor-q mean "
        "--no-target-actor --weight-decay 0.1 --max-grad-norm 1.0 "
        "--layer-norm --actor-hidden-sizes 8 4 --critic-hidden-sizes 16 8 "
        "--precision bfloat16 --expl-noise-min 0.01 --expl-noise-max 0.4"
    ).split()
    common = ["--out", str(out), "--quiet", "--compile-cache", "off"]
    cli.main(["train", *flags, *common])
    cfg = load_config(out)
    assert cfg.critic == "distributional" and cfg.critic_hidden_sizes == (16, 8)
    assert cfg.precision == "bfloat16" and cfg.expl_noise_max == 0.4 and not cfg.target_actor
    cli.main(["train", "--resume", "--total-steps", "36", *common])
    records = read_metrics(out / "metrics.jsonl")
    assert [r["env_steps"] for r in records] == [12, 24, 36]
    assert all(
        np.isfinite(r["critic_loss"]) and np.isfinite(r["eval_return_mean"]) for r in records
    )


def test_a_cosine_run_cannot_be_extended_on_resume(tmp_path, capsys):
    # The schedule's length is the run's number of updates: a longer run would restart the
    # decay from a higher rate, so --total-steps may not change.
    out = tmp_path / "run"
    flags = ("--env gymnax/Pendulum-v1 --hidden-sizes 8 --num-envs 2 --updates-per-iter 1 "
             "--batch-size 4 --buffer-size 64 --warmup-steps 4 --eval-every 8 --total-steps 8 "
             "--eval-envs 2 --episode-length 8 --lr-schedule cosine").split()  # fmt: skip
    common = ["--out", str(out), "--quiet", "--compile-cache", "off"]
    cli.main(["train", *flags, *common])
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["train", "--resume", "--total-steps", "16", *common])
    assert exit_info.value.code == 2
    assert "--total-steps cannot change on --resume with --lr-schedule cosine" in (
        capsys.readouterr().err
    )
