"""The C51 critic against an independent NumPy reference.

The reference projects with FastTD3's floor/ceil rule (mass split between the atoms below and
above each moved atom, all of it on the atom it lands on exactly), written with explicit loops;
the library sums runs of atoms by prefix sums. The full update is re-derived by hand: the target
action with the same noise draw, the lower-mean head per sample, the projected target, the
summed per-head cross-entropy, hand-written float64 Adam with decoupled weight decay, the actor
on the lower critic mean, Polyak averaging. Only forward passes and ``jax.grad`` are shared.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from td3_jax.core import actor_critic as ac
from td3_jax.core import distributional, losses
from td3_jax.core.types import Transition

OBS, ACT, BATCH, HIDDEN = 3, 2, 8, (8, 8)


def np_project(probs, target_z, v_min, v_max):
    """FastTD3's projection (floor/ceil neighbours), one atom at a time, float64."""
    probs, target_z = np.asarray(probs, np.float64), np.asarray(target_z, np.float64)
    rows, n = probs.shape
    b = (np.clip(target_z, v_min, v_max) - v_min) / ((v_max - v_min) / (n - 1))
    out = np.zeros_like(probs)
    for i in range(rows):
        for j in range(n):
            low, up = int(np.floor(b[i, j])), int(np.ceil(b[i, j]))
            if low == up:  # landed exactly on an atom
                out[i, low] += probs[i, j]
            else:
                out[i, low] += probs[i, j] * (up - b[i, j])
                out[i, up] += probs[i, j] * (b[i, j] - low)
    return out


def np_softmax(x):
    x = np.asarray(x, np.float64)
    e = np.exp(x - x.max(-1, keepdims=True))
    return e / e.sum(-1, keepdims=True)


# --------------------------------------------------------------------------------------------
# the projection
# --------------------------------------------------------------------------------------------


def test_projection_by_hand_exact_hits_and_clamping():
    """Support -2..2 (5 atoms, spacing 1): exact hits, half-way splits, both clamps."""
    z = np.array([-2.0, -1.0, 0.0, 1.0, 2.0])
    one_hot = np.eye(5)
    # Each row: the whole mass on one atom j, moved to r + 0.5 * z_j.
    cases = [
        (0.0, 2, [0, 0, 1, 0, 0]),  # 0 + 0.5 * 0 = 0: exactly atom 2
        (0.0, 4, [0, 0, 0, 1, 0]),  # 0.5 * 2 = 1: exactly atom 3
        (0.0, 3, [0, 0, 0.5, 0.5, 0]),  # 0.5: half-way between atoms 2 and 3
        (0.25, 3, [0, 0, 0.25, 0.75, 0]),  # 0.75
        (5.0, 0, [0, 0, 0, 0, 1]),  # 4: clamped to v_max
        (-5.0, 4, [1, 0, 0, 0, 0]),  # -4: clamped to v_min
        (-2.0, 2, [1, 0, 0, 0, 0]),  # exactly v_min
        (2.0, 2, [0, 0, 0, 0, 1]),  # exactly v_max
    ]
    probs = np.stack([one_hot[j] for _, j, _ in cases]).astype(np.float32)
    target_z = np.stack([r + 0.5 * z for r, _, _ in cases]).astype(np.float32)
    expected = np.array([e for _, _, e in cases], np.float64)
    got = np.asarray(jax.jit(distributional.project)(probs, target_z, -2.0, 2.0))
    np.testing.assert_allclose(got, expected, atol=1e-6)
    np.testing.assert_allclose(np_project(probs, target_z, -2.0, 2.0), expected, atol=1e-12)


@pytest.mark.parametrize("num_atoms", [2, 5, 51])
def test_projection_matches_reference_on_random_distributions(num_atoms):
    rng = np.random.default_rng(num_atoms)
    probs = np_softmax(rng.normal(size=(64, num_atoms))).astype(np.float32)
    z = np.linspace(-3.0, 7.0, num_atoms)
    reward = rng.uniform(-6, 12, size=(64, 1))
    scale = rng.choice([0.0, 0.5, 0.97, 1.0], size=(64, 1))
    target_z = (reward + scale * z).astype(np.float32)
    # Some rows land exactly on atoms: reward an atom value and scale 0 or 1 on a grid.
    target_z[:4] = np.float32(z[None, :]) if num_atoms > 1 else target_z[:4]
    got = np.asarray(jax.jit(distributional.project)(probs, target_z, -3.0, 7.0))
    # float32 atom positions b in [0, 50] carry rounding up to ~4e-6 (the reference is float64)
    np.testing.assert_allclose(got, np_project(probs, target_z, -3.0, 7.0), atol=1e-5)
    np.testing.assert_allclose(got.sum(-1), 1.0, atol=1e-5)  # mass is conserved
    np.testing.assert_allclose(got[:4], probs[:4], atol=1e-6)  # identity when z maps to z


def test_projection_of_several_heads_onto_one_moved_support():
    """Heads ``[2, batch, atoms]`` against one moved support ``[batch, atoms]`` (as the C51
    target projects both critics' distributions): each head as projected alone, by the
    reference; rows with a zero slope (ended episodes) put all mass beside the reward."""
    rng = np.random.default_rng(7)
    probs = np_softmax(rng.normal(size=(2, 32, 101))).astype(np.float32)
    z = np.linspace(-10.0, 10.0, 101)
    reward = rng.uniform(-12, 12, size=(32, 1))
    slope = np.where(np.arange(32)[:, None] % 4 == 0, 0.0, 0.97)
    target_z = (reward + slope * z).astype(np.float32)
    got = np.asarray(jax.jit(distributional.project)(probs, target_z, -10.0, 10.0))
    for head in range(2):
        want = np_project(probs[head], target_z, -10.0, 10.0)
        np.testing.assert_allclose(got[head], want, atol=2e-5)
    ended = np.clip(reward[::4, 0], -10.0, 10.0)  # every atom moved to the clamped reward
    np.testing.assert_allclose(got[:, ::4] @ z, np.broadcast_to(ended, (2, 8)), atol=1e-4)


# --------------------------------------------------------------------------------------------
# target and loss through the agent
# --------------------------------------------------------------------------------------------


@functools.cache
def spec_of(num_atoms=5, **options):
    opts = ac.AgentOptions(num_atoms=num_atoms, actor_q=options.pop("actor_q", "min"), **options)
    return ac.make_spec(
        HIDDEN, OBS, ACT, num_critics=2, target_smoothing=True, policy_freq=2, options=opts
    )


def hparams(**kw):
    values = dict(
        discount=0.5,
        tau=0.3,
        actor_lr=3e-3,
        critic_lr=5e-3,
        policy_noise=0.2,
        noise_clip=0.5,
        v_min=-2.0,
        v_max=2.0,
    )
    values.update(kw)
    return ac.AgentHyperparams(**{k: jnp.float32(v) for k, v in values.items()})


def make_batch(seed, done=None, reward_scale=2.0):
    rng = np.random.default_rng(seed)
    f32 = np.float32
    return Transition(
        obs=rng.normal(size=(BATCH, OBS)).astype(f32),
        action=rng.uniform(-1, 1, (BATCH, ACT)).astype(f32),
        reward=(reward_scale * rng.normal(size=(BATCH,))).astype(f32),
        next_obs=rng.normal(size=(BATCH, OBS)).astype(f32),
        done=(rng.uniform(size=(BATCH,)) < 0.3).astype(f32) if done is None else done,
    )


@functools.cache
def _apply_fns(spec):
    return jax.jit(spec.actor.apply), jax.jit(spec.critic.apply)


def reference_target(
    spec, hp, actor_params, critic_params, batch, key, bootstrap, head="unprojected"
):
    """Target probabilities ``[batch, atoms]``; ``bootstrap [batch]`` = ``discount**k (1-term)``
    computed by the caller from k and the termination, not from the folded ``done``. ``head``:
    pick the lower-mean head before projecting (``unprojected``) or after (``projected``,
    FastTD3: both heads projected, their means on the support compared)."""
    actor, critic = _apply_fns(spec)
    pi = np.asarray(actor(actor_params, batch.next_obs), np.float64)
    eps = np.asarray(jax.random.normal(key, pi.shape), np.float64)
    a = np.clip(
        pi + np.clip(float(hp.policy_noise) * eps, -float(hp.noise_clip), float(hp.noise_clip)),
        -1.0,
        1.0,
    )
    logits = np.asarray(critic(critic_params, batch.next_obs, a.astype(np.float32)))
    n = logits.shape[-1]
    z = np.linspace(float(hp.v_min), float(hp.v_max), n)
    probs = np_softmax(logits)  # [2, batch, atoms]
    target_z = np.asarray(batch.reward, np.float64)[:, None] + bootstrap[:, None] * z
    if head == "projected":
        probs = np.stack([np_project(p, target_z, float(hp.v_min), float(hp.v_max)) for p in probs])
    means = probs @ z
    chosen = np.where((means[0] <= means[1])[:, None], probs[0], probs[1])
    if head == "projected":
        return chosen
    return np_project(chosen, target_z, float(hp.v_min), float(hp.v_max))


def wide_and_narrow_heads(critic_params):
    """Critic params whose head 0 puts its mass on the support's ends, slightly low, and head 1
    on its middle: with the atoms moved down (a negative reward), clamping at ``v_min`` lifts
    head 0's lower end, so the head with the lower mean changes once projected."""
    out = jax.tree.map(lambda w: 0.01 * w, critic_params)
    last = out["params"]["VmapDistributionalCritic_0"]["MLP_0"]["Dense_2"]
    last["bias"] = jnp.array([[4.1, 0.0, 0.0, 0.0, 4.0], [0.0, 0.0, 4.0, 0.0, 0.0]])
    return out


def test_the_two_target_head_rules_match_their_references_and_differ():
    """Rewards far outside ``[v_min, v_max]`` clamp the moved atoms: the head with the lower
    unprojected mean is then not always the one with the lower projected mean. Each rule
    matches its NumPy reference, and the two differ on some rows (else this test could not
    tell them apart)."""
    hp = hparams(discount=0.9)
    batch = make_batch(5, done=np.zeros(BATCH, np.float32), reward_scale=2.0)
    key = jax.random.key(4)
    targets = {}
    for head in ("unprojected", "projected"):
        spec = spec_of(c51_target_head=head)
        state = jax.jit(functools.partial(ac.init, spec))(jax.random.key(2))
        state = state.replace(critic_params=wide_and_narrow_heads(state.critic_params))
        targets[head] = np.asarray(jax.jit(losses.categorical_target, static_argnums=0)(
            spec, hp, state.actor_params, state.critic_params, batch, key))  # fmt: skip
        expected = reference_target(spec, hp, state.actor_params, state.critic_params, batch,
                                    key, np.full(BATCH, 0.9), head=head)  # fmt: skip
        np.testing.assert_allclose(targets[head], expected, atol=2e-6)
    differ = np.abs(targets["unprojected"] - targets["projected"]).max(axis=-1) > 1e-4
    assert 0 < differ.sum() < BATCH


def test_target_with_done_and_n_step_discounts_matches_reference():
    """Rows of 1-, 2- and 3-step transitions, some terminated: the folded ``done`` of
    :mod:`td3_jax.core.n_step` (``1 - discount**(k-1) (1 - term)``) must give ``discount**k``."""
    spec, hp = spec_of(), hparams(discount=0.9)
    state = jax.jit(functools.partial(ac.init, spec))(jax.random.key(0))
    steps = np.array([1, 2, 3, 1, 2, 3, 3, 1])
    terminated = np.array([0, 0, 0, 1, 1, 0, 1, 0], np.float64)
    done = (1.0 - 0.9 ** (steps - 1) * (1.0 - terminated)).astype(np.float32)
    batch = make_batch(1, done=done)
    key = jax.random.key(3)
    target = jax.jit(losses.categorical_target, static_argnums=0)(
        spec, hp, state.actor_params, state.critic_params, batch, key
    )
    expected = reference_target(
        spec,
        hp,
        state.actor_params,
        state.critic_params,
        batch,
        key,
        0.9**steps * (1.0 - terminated),
    )
    np.testing.assert_allclose(np.asarray(target), expected, atol=2e-6)
    # A terminated row's target sits at its reward alone, whatever the critics say: split
    # between the two atoms around the (clamped) reward, by hand.
    for row in (3, 4, 6):
        b = np.clip(float(batch.reward[row]), -2.0, 2.0) + 2.0
        low = int(np.floor(b))
        hand = np.zeros(5)
        hand[low] += 1.0 - (b - low)
        hand[min(low + 1, 4)] += b - low
        np.testing.assert_allclose(np.asarray(target[row]), hand, atol=1e-6)


def test_clipped_double_q_takes_the_head_with_the_lower_mean_per_sample():
    """Two heads whose logits differ only by a constant-free tilt: the lower-mean head is taken
    per sample, and swapping the heads changes nothing."""
    z = jnp.linspace(-2.0, 2.0, 5)
    up = jnp.array([0.0, 0.0, 0.0, 1.0, 2.0])  # mass towards high values
    down = up[::-1]
    probs = jax.nn.softmax(jnp.stack([jnp.stack([up, down]), jnp.stack([down, up])]), axis=-1)
    chosen = distributional.lower_mean_head(probs, z)  # heads x batch: (up, down), (down, up)
    np.testing.assert_allclose(chosen, jax.nn.softmax(jnp.stack([down, down]), -1), atol=1e-7)


def test_categorical_loss_is_the_summed_cross_entropy():
    spec = spec_of()
    state = jax.jit(functools.partial(ac.init, spec))(jax.random.key(1))
    batch = make_batch(2)
    target = np_softmax(np.random.default_rng(0).normal(size=(BATCH, 5)))
    loss, logits = losses.categorical_loss(state.critic_params, spec, batch, jnp.float32(target))
    log_p = np.log(np_softmax(logits))
    expected = sum(np.mean(-np.sum(target * log_p[h], -1)) for h in range(2))
    np.testing.assert_allclose(float(loss), expected, rtol=1e-5)
    assert logits.shape == (2, BATCH, 5)


# --------------------------------------------------------------------------------------------
# the whole update
# --------------------------------------------------------------------------------------------


def adam_decay_step(params, grads, opt, lr, wd):
    """Float64 Adam (b1 0.9, b2 0.999, eps 1e-8) with decoupled weight decay (AdamW)."""
    count = opt["count"] + 1
    g = jax.tree.map(lambda x: np.asarray(x, np.float64), grads)
    m = jax.tree.map(lambda m, g: 0.9 * m + 0.1 * g, opt["m"], g)
    v = jax.tree.map(lambda v, g: 0.999 * v + 0.001 * g * g, opt["v"], g)
    c1, c2 = 1 - 0.9**count, 1 - 0.999**count
    new = jax.tree.map(
        lambda p, m, v: p - lr * ((m / c1) / (np.sqrt(v / c2) + 1e-8) + wd * p), params, m, v
    )
    return new, {"m": m, "v": v, "count": count}


@functools.cache
def reference_grads(spec):
    z = lambda hp: jnp.linspace(hp["v_min"], hp["v_max"], 5)

    def critic_loss(critic, batch, target):
        log_p = jax.nn.log_softmax(spec.critic.apply(critic, batch.obs, batch.action), -1)
        return jnp.mean(-jnp.sum(target * log_p[0], -1)) + jnp.mean(-jnp.sum(target * log_p[1], -1))

    def actor_loss(actor, critic, obs, hp):
        p = jax.nn.softmax(spec.critic.apply(critic, obs, spec.actor.apply(actor, obs)), -1)
        q = p @ z(hp)
        return -jnp.mean(jnp.minimum(q[0], q[1]))

    return jax.jit(jax.grad(critic_loss)), jax.jit(jax.grad(actor_loss))


def test_full_distributional_update_matches_reference():
    spec, hp = spec_of(), hparams(weight_decay=0.05)
    f64 = lambda t: jax.tree.map(lambda x: np.asarray(x, np.float64), t)
    f32 = lambda t: jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), t)
    state = jax.jit(functools.partial(ac.init, spec))(jax.random.key(5))
    ref = {
        k: f64(getattr(state, k))
        for k in ("actor_params", "critic_params", "target_actor_params", "target_critic_params")
    }
    zeros = lambda t: {
        "m": jax.tree.map(np.zeros_like, t),
        "v": jax.tree.map(np.zeros_like, t),
        "count": 0,
    }
    opt = {"actor": zeros(ref["actor_params"]), "critic": zeros(ref["critic_params"])}
    critic_grad, actor_grad = reference_grads(spec)
    update = jax.jit(ac.update, static_argnums=0)
    hp_dict = {"v_min": jnp.float32(-2.0), "v_max": jnp.float32(2.0)}
    for i in range(4):
        batch, key = make_batch(10 + i), jax.random.key(20 + i)
        state, metrics = update(spec, hp, state, batch, key)
        bootstrap = 0.5 * (1.0 - np.asarray(batch.done, np.float64))
        target = reference_target(
            spec,
            hp,
            f32(ref["target_actor_params"]),
            f32(ref["target_critic_params"]),
            batch,
            key,
            bootstrap,
        )
        g = critic_grad(f32(ref["critic_params"]), batch, jnp.float32(target))
        ref["critic_params"], opt["critic"] = adam_decay_step(
            ref["critic_params"], g, opt["critic"], 5e-3, 0.05
        )
        np.testing.assert_allclose(
            metrics["target_mean"], np.mean(target @ np.linspace(-2, 2, 5)), atol=1e-5
        )
        if (i + 1) % 2 == 0:
            g = actor_grad(f32(ref["actor_params"]), f32(ref["critic_params"]), batch.obs, hp_dict)
            ref["actor_params"], opt["actor"] = adam_decay_step(
                ref["actor_params"], g, opt["actor"], 3e-3, 0.05
            )
            for name in ("actor", "critic"):
                ref[f"target_{name}_params"] = jax.tree.map(
                    lambda o, t: 0.3 * o + 0.7 * t,
                    ref[f"{name}_params"],
                    ref[f"target_{name}_params"],
                )
        for name, expected in ref.items():
            got = getattr(state, name)
            for a, e in zip(jax.tree.leaves(got), jax.tree.leaves(expected), strict=True):
                np.testing.assert_allclose(np.asarray(a), e, atol=1e-5, rtol=1e-5, err_msg=name)
    assert int(state.step) == 4


def test_distributional_td3_learns_a_bandit():
    """One-step bandit, reward -(a - 0.5)^2, done = 1: the C51 agent's action goes to 0.5."""
    spec = ac.make_spec(
        (32, 32),
        1,
        1,
        num_critics=2,
        target_smoothing=True,
        policy_freq=2,
        options=ac.AgentOptions(num_atoms=21, actor_q="min"),
    )
    hp = hparams(actor_lr=5e-3, critic_lr=1e-2, discount=0.99, v_min=-3.0, v_max=1.0)

    @jax.jit
    def train(state, key):
        def body(state, key):
            k_act, k_upd = jax.random.split(key)
            action = jax.random.uniform(k_act, (64, 1), minval=-1.0, maxval=1.0)
            obs = jnp.ones((64, 1))
            reward = -((action[:, 0] - 0.5) ** 2)
            batch = Transition(obs, action, reward, obs, jnp.ones((64,)))
            return ac.update(spec, hp, state, batch, k_upd)[0], None

        return jax.lax.scan(body, state, jax.random.split(key, 600))[0]

    state = jax.jit(functools.partial(ac.init, spec))(jax.random.key(0))
    act = lambda s: float(spec.actor.apply(s.actor_params, jnp.ones((1, 1)))[0, 0])
    start = act(state)
    state = train(state, jax.random.key(1))
    assert abs(start - 0.5) > 0.2, start  # it really had to move
    assert abs(act(state) - 0.5) < 0.1, act(state)
