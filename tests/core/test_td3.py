"""TD3 / DDPG ``update`` against an independent reference implementation of the same math.

The reference below re-derives every step of the algorithm by hand: target policy smoothing
(with the very same ``jax.random.normal(key, shape)`` draw the agent makes), the clipped double-Q
target with its ``(1 - done)`` mask, the summed per-head MSE critic loss, a hand-written
bias-corrected Adam (float64 numpy), the delayed actor step on the freshly updated critic and
Polyak averaging of both targets. Only the network forward passes (``actor_apply`` /
``critic_apply``) and ``jax.grad`` are shared with the library.

Compilation dominates the run time on a CPU, so the jitted functions are cached per program
structure (algorithm, widths, ``policy_freq``) and the float hyperparameters are passed in as
traced config leaves (a documented feature of the configs) wherever a test varies them.
"""

from __future__ import annotations

import functools
import math
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import td3_jax as tj

OBS, ACT, BATCH = 3, 2, 8
EACH = 8  # number of single-transition updates vmapped by ``jitted_update_each``
HIDDEN = (16, 16)

ADAM_B1, ADAM_B2, ADAM_EPS = 0.9, 0.999, 1e-8


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------


def make_config(algo, **kwargs):
    kwargs.setdefault("hidden_sizes", HIDDEN)
    if algo == "td3":
        return tj.TD3Config(**kwargs)
    return tj.DDPGConfig(**kwargs)


def build(algo, config, obs_size=OBS, action_size=ACT):
    if algo == "td3":
        return tj.td3(config, obs_size, action_size)
    return tj.ddpg(config, obs_size, action_size)


@functools.cache
def jitted_init(algo):
    return jax.jit(build(algo, make_config(algo)).init)


def jitted_update(algo, policy_freq=2):
    """``update(config, state, batch, key)`` with the config's float fields traced.

    One compiled program per (algo, policy_freq) and batch shape, shared by all tests.
    """
    return _jitted_update(algo, policy_freq if algo == "td3" else 1)


@functools.cache
def _jitted_update(algo, policy_freq):
    del policy_freq  # part of the config's static structure; only the cache key here

    def update(config, state, batch, key):
        return build(algo, config).update(state, batch, key)

    return jax.jit(update)


@functools.cache
def jitted_update_each(algo):
    """One ``update`` per (batch, key) pair from the same state: ``vmap`` over both.

    Always called with ``EACH`` pairs of batch size 1 so that it compiles once per algo.
    """

    def update(config, state, batch, key):
        return build(algo, config).update(state, batch, key)

    return jax.jit(jax.vmap(update, in_axes=(None, None, 0, 0)))


def init_state(algo, seed):
    return jitted_init(algo)(jax.random.key(seed))


def make_batch(seed, batch_size=BATCH, obs_size=OBS, action_size=ACT, max_action=1.0):
    """A random batch (numpy RNG: no jax op-by-op compilation in the tests' setup)."""
    rng = np.random.default_rng(seed)
    f32 = np.float32
    return tj.Transition(
        obs=rng.normal(size=(batch_size, obs_size)).astype(f32),
        action=rng.uniform(-max_action, max_action, (batch_size, action_size)).astype(f32),
        reward=rng.normal(size=(batch_size,)).astype(f32),
        next_obs=rng.normal(size=(batch_size, obs_size)).astype(f32),
        done=(rng.uniform(size=(batch_size,)) < 0.3).astype(f32),
    )


def _is_key(x):
    return isinstance(x, jax.Array) and jnp.issubdtype(x.dtype, jax.dtypes.prng_key)


def stack(trees):
    return jax.tree.map(
        lambda *xs: jnp.stack(xs) if _is_key(xs[0]) else np.stack([np.asarray(x) for x in xs]),
        *trees,
    )


def index(tree, i):
    return jax.tree.map(lambda x: x[i] if _is_key(x) else np.asarray(x)[i], tree)


def assert_trees_close(actual, expected, atol=1e-5, rtol=1e-5, what=""):
    a_leaves, a_def = jax.tree.flatten(actual)
    e_leaves, e_def = jax.tree.flatten(expected)
    assert a_def == e_def, f"{what}: tree structures differ"
    for a, e in zip(a_leaves, e_leaves, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(e), atol=atol, rtol=rtol, err_msg=what)


def assert_trees_equal(actual, expected, what=""):
    assert_trees_close(actual, expected, atol=0.0, rtol=0.0, what=what)


def trees_differ(a, b, atol=1e-7):
    return any(
        not np.allclose(np.asarray(x), np.asarray(y), atol=atol, rtol=0.0)
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True)
    )


def find_mlp(params):
    """The ``{'Dense_0': ..., 'Dense_1': ..., ...}`` dict inside a flax parameter tree."""
    if isinstance(params, dict):
        if "Dense_0" in params:
            return params
        for value in params.values():
            found = find_mlp(value)
            if found is not None:
                return found
    return None


def with_mlp(params, layers):
    """A copy of ``params`` whose MLP layers are replaced by ``layers`` (same structure)."""
    if isinstance(params, dict):
        if "Dense_0" in params:
            return layers
        return {k: with_mlp(v, layers) for k, v in params.items()}
    return params


def probe_critic_params(critic_params, offsets, obs_size=OBS):
    """Critic params with ``Q_h(s, a) = a[0] + offsets[h]`` exactly (for ``a[0] > -10``).

    Layer 0 reads action dim 0 into unit 0 with bias +10 (so ReLU is the identity), layer 1
    copies unit 0, the output layer reads unit 0 with bias ``-10 + offset``.
    """
    mlp = jax.tree.map(lambda x: np.zeros(x.shape, np.float32), find_mlp(critic_params))
    for h, offset in enumerate(offsets):
        mlp["Dense_0"]["kernel"][h, obs_size, 0] = 1.0
        mlp["Dense_0"]["bias"][h, 0] = 10.0
        mlp["Dense_1"]["kernel"][h, 0, 0] = 1.0
        mlp["Dense_2"]["kernel"][h, 0, 0] = 1.0
        mlp["Dense_2"]["bias"][h, 0] = -10.0 + offset
    return with_mlp(critic_params, jax.tree.map(jnp.asarray, mlp))


def constant_actor_params(actor_params, raw_bias):
    """Actor params whose pre-tanh output is ``raw_bias`` for every observation."""
    mlp = jax.tree.map(lambda x: np.zeros(x.shape, np.float32), find_mlp(actor_params))
    mlp["Dense_2"]["bias"][:] = raw_bias
    return with_mlp(actor_params, jax.tree.map(jnp.asarray, mlp))


# --------------------------------------------------------------------------------------------
# the independent reference implementation
# --------------------------------------------------------------------------------------------


def to_f64(tree):
    return jax.tree.map(lambda x: np.asarray(x, np.float64), tree)


def to_f32(tree):
    return jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), tree)


def adam_init(params):
    zeros = jax.tree.map(np.zeros_like, params)
    return {"m": zeros, "v": zeros, "count": 0}


def adam_step(params, grads, opt, lr):
    """Hand-written bias-corrected Adam (b1=0.9, b2=0.999, eps=1e-8), in float64 numpy."""
    count = opt["count"] + 1
    grads = to_f64(grads)
    m = jax.tree.map(lambda m, g: ADAM_B1 * m + (1.0 - ADAM_B1) * g, opt["m"], grads)
    v = jax.tree.map(lambda v, g: ADAM_B2 * v + (1.0 - ADAM_B2) * g * g, opt["v"], grads)
    c1 = 1.0 - ADAM_B1**count
    c2 = 1.0 - ADAM_B2**count
    new_params = jax.tree.map(
        lambda p, m, v: p - lr * (m / c1) / (np.sqrt(v / c2) + ADAM_EPS), params, m, v
    )
    return new_params, {"m": m, "v": v, "count": count}


def polyak(online, target, tau):
    return jax.tree.map(lambda o, t: tau * o + (1.0 - tau) * t, online, target)


@functools.cache
def reference_fns(algo):
    """Jitted pieces of the reference; ``hp`` (a dict of floats) is traced."""
    smoothing = algo == "td3"

    def nets(max_action):
        agent = build(algo, make_config(algo, max_action=max_action))
        return agent.actor_apply, agent.critic_apply

    def target_fn(hp, target_actor, target_critic, batch, key):
        actor_apply, critic_apply = nets(hp["max_action"])
        next_action = actor_apply(target_actor, batch.next_obs)
        if smoothing:
            eps = jax.random.normal(key, next_action.shape)
            noise = jnp.clip(hp["policy_noise"] * eps, -hp["noise_clip"], hp["noise_clip"])
            next_action = jnp.clip(next_action + noise, -hp["max_action"], hp["max_action"])
        q_next = critic_apply(target_critic, batch.next_obs, next_action)
        if smoothing:
            assert q_next.shape[0] == 2
            q_min = jnp.minimum(q_next[0], q_next[1])
        else:
            assert q_next.shape[0] == 1
            q_min = q_next[0]
        return batch.reward + hp["discount"] * (1.0 - batch.done) * q_min

    def critic_loss(critic, batch, y):
        q = nets(1.0)[1](critic, batch.obs, batch.action)
        return sum(jnp.mean((q[h] - y) ** 2) for h in range(q.shape[0]))

    def actor_loss(actor, hp, critic, obs):
        actor_apply, critic_apply = nets(hp["max_action"])
        q = critic_apply(critic, obs, actor_apply(actor, obs))
        return -jnp.mean(q[0])

    return (
        jax.jit(target_fn),
        jax.jit(jax.value_and_grad(critic_loss)),
        jax.jit(jax.value_and_grad(actor_loss)),
    )


class Reference:
    """Plain re-implementation of TD3 (smoothing, two heads, delayed) and DDPG."""

    def __init__(self, algo, state, *, policy_freq, hp):
        self.target_fn, self.critic_vg, self.actor_vg = reference_fns(algo)
        self.policy_freq = policy_freq
        self.hp = hp
        self.traced_hp = {k: jnp.float32(v) for k, v in hp.items()}
        self.actor = to_f64(state.actor_params)
        self.critic = to_f64(state.critic_params)
        self.target_actor = to_f64(state.target_actor_params)
        self.target_critic = to_f64(state.target_critic_params)
        self.actor_opt = adam_init(self.actor)
        self.critic_opt = adam_init(self.critic)
        self.step = 0

    def update(self, batch, key):
        # y becomes a plain constant array here: no gradient can flow into it.
        y = np.asarray(
            self.target_fn(
                self.traced_hp, to_f32(self.target_actor), to_f32(self.target_critic), batch, key
            )
        )
        c_loss, c_grads = self.critic_vg(to_f32(self.critic), batch, jnp.asarray(y))
        self.critic, self.critic_opt = adam_step(
            self.critic, c_grads, self.critic_opt, self.hp["critic_lr"]
        )
        self.step += 1
        out = {
            "critic_loss": float(c_loss),
            "target_mean": float(np.mean(y)),
            "actor_updated": 0.0,
            "actor_loss": 0.0,
        }
        if self.step % self.policy_freq == 0:
            # The actor step sees the critic that was just updated above.
            a_loss, a_grads = self.actor_vg(
                to_f32(self.actor), self.traced_hp, to_f32(self.critic), batch.obs
            )
            self.actor, self.actor_opt = adam_step(
                self.actor, a_grads, self.actor_opt, self.hp["actor_lr"]
            )
            tau = self.hp["tau"]
            self.target_actor = polyak(self.actor, self.target_actor, tau)
            self.target_critic = polyak(self.critic, self.target_critic, tau)
            out["actor_updated"] = 1.0
            out["actor_loss"] = float(a_loss)
        return out

    def check_against(self, state, atol=1e-5, rtol=1e-5):
        assert int(state.step) == self.step
        assert_trees_close(state.critic_params, self.critic, atol, rtol, "critic")
        assert_trees_close(state.actor_params, self.actor, atol, rtol, "actor")
        assert_trees_close(state.target_critic_params, self.target_critic, atol, rtol, "t_crit")
        assert_trees_close(state.target_actor_params, self.target_actor, atol, rtol, "t_actor")


def run_against_reference(algo, hp, policy_freq, n_updates, seed):
    """``n_updates`` jitted updates, each checked against the reference (params, metrics)."""
    config = make_config(algo, **(dict(hp, policy_freq=policy_freq) if algo == "td3" else hp))
    update = jitted_update(algo, policy_freq)
    state = init_state(algo, seed)
    ref = Reference(algo, state, policy_freq=policy_freq, hp=hp)
    for i in range(n_updates):
        batch = make_batch(100 * seed + i, max_action=hp["max_action"])
        key = jax.random.key(1000 * seed + i)
        state, metrics = update(config, state, batch, key)
        expected = ref.update(batch, key)
        ref.check_against(state)
        assert float(metrics["actor_updated"]) == expected["actor_updated"]
        for name in ("critic_loss", "target_mean", "actor_loss"):
            np.testing.assert_allclose(
                metrics[name], expected[name], rtol=1e-5, atol=1e-5, err_msg=name
            )
    assert ref.step == n_updates


TD3_CASES = {
    # Large tau / learning rates, so that a wrong Polyak or Adam formula moves the params
    # well beyond the 1e-5 tolerance within a few steps.
    "pf2": dict(
        policy_freq=2, tau=0.3, actor_lr=3e-3, critic_lr=5e-3, discount=0.9,
        policy_noise=0.2, noise_clip=0.5, max_action=1.0,
    ),
    "pf3": dict(
        policy_freq=3, tau=0.25, actor_lr=2e-3, critic_lr=3e-3, discount=0.99,
        policy_noise=0.2, noise_clip=0.5, max_action=1.0,
    ),
    # Noise that is clipped often and target actions that hit the action bound often.
    "heavy_clipping": dict(
        policy_freq=2, tau=0.2, actor_lr=1e-3, critic_lr=1e-3, discount=0.95,
        policy_noise=1.5, noise_clip=0.3, max_action=2.0,
    ),
    "paper_defaults": dict(
        policy_freq=2, tau=0.005, actor_lr=1e-3, critic_lr=1e-3, discount=0.99,
        policy_noise=0.2, noise_clip=0.5, max_action=1.0,
    ),
}  # fmt: skip


@pytest.mark.parametrize("case", sorted(TD3_CASES))
def test_td3_updates_match_reference(case):
    hp = dict(TD3_CASES[case])
    policy_freq = hp.pop("policy_freq")
    run_against_reference("td3", hp, policy_freq, n_updates=6, seed=1 + len(case))


@pytest.mark.parametrize(
    "hp",
    [
        dict(tau=0.2, actor_lr=3e-3, critic_lr=5e-3, discount=0.9, max_action=1.0),
        # The DDPG defaults (tau 1e-2, actor 1e-4, critic 1e-3, discount 0.99).
        dict(tau=1e-2, actor_lr=1e-4, critic_lr=1e-3, discount=0.99, max_action=1.0),
    ],
)
def test_ddpg_updates_match_reference(hp):
    run_against_reference("ddpg", hp, policy_freq=1, n_updates=5, seed=int(hp["tau"] * 100))


# --------------------------------------------------------------------------------------------
# small hand-computed checks
# --------------------------------------------------------------------------------------------


def per_sample_targets(algo, config, state, batch, key):
    """``y`` for each transition separately (a batch of 1 each, all with the same key)."""
    assert batch.reward.shape[0] == EACH
    one = jax.tree.map(lambda x: np.asarray(x)[:, None], batch)
    keys = jnp.stack([key] * EACH)
    _, metrics = jitted_update_each(algo)(config, state, one, keys)
    return np.asarray(metrics["target_mean"])


def probe_state(algo, *, actor_raw_bias, offsets, seed=0):
    state = init_state(algo, seed)
    return state.replace(
        target_actor_params=constant_actor_params(state.target_actor_params, actor_raw_bias),
        target_critic_params=probe_critic_params(state.target_critic_params, offsets),
    )


def test_init_targets_equal_online_and_step_zero():
    state = init_state("td3", 0)
    assert_trees_equal(state.target_actor_params, state.actor_params)
    assert_trees_equal(state.target_critic_params, state.critic_params)
    assert int(state.step) == 0 and state.step.dtype == jnp.int32
    assert trees_differ(state.actor_params, init_state("td3", 1).actor_params)
    # The two critic heads are independent networks (different initialisation).
    agent = build("td3", make_config("td3"))
    q = jax.jit(agent.critic_apply)(state.critic_params, np.ones((4, OBS)), np.zeros((4, ACT)))
    assert q.shape == (2, 4)
    assert not np.allclose(q[0], q[1])


def test_clipped_double_q_target_by_hand():
    """``y = r + discount * (1 - done) * min(Q1', Q2')`` with hand-built target networks."""
    config = make_config("td3", discount=0.9, policy_noise=0.0)
    # target actor outputs a = tanh(atanh(0.4)) = 0.4; Q1' = a0 + 0.5, Q2' = a0 - 0.25.
    state = probe_state("td3", actor_raw_bias=math.atanh(0.4), offsets=(0.5, -0.25))
    reward = np.array([1.0, 2.0, 3.0, -4.0, 0.5, 0.0, -1.0, 7.0], np.float32)
    done = np.array([0.0, 1.0, 0.0, 1.0, 1.0, 0.0, 0.0, 1.0], np.float32)
    batch = make_batch(5)._replace(reward=reward, done=done)
    expected = reward + (1.0 - done) * 0.9 * 0.15
    y = per_sample_targets("td3", config, state, batch, jax.random.key(0))
    np.testing.assert_allclose(y, expected, atol=1e-5)

    # Swapping which head is lower must not change the result (it is the min, not head 0).
    state2 = probe_state("td3", actor_raw_bias=math.atanh(0.4), offsets=(-0.25, 0.5))
    y2 = per_sample_targets("td3", config, state2, batch, jax.random.key(0))
    np.testing.assert_allclose(y2, expected, atol=1e-5)

    # The critic loss is the sum over heads of the per-head MSE against that y.
    _, metrics = jitted_update("td3")(config, state, batch, jax.random.key(0))
    agent = build("td3", config)
    q = np.asarray(jax.jit(agent.critic_apply)(state.critic_params, batch.obs, batch.action))
    loss = np.mean((q[0] - expected) ** 2) + np.mean((q[1] - expected) ** 2)
    np.testing.assert_allclose(metrics["critic_loss"], loss, rtol=1e-5)
    np.testing.assert_allclose(metrics["q_mean"], q.mean(), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(metrics["target_mean"], expected.mean(), rtol=1e-5)


def test_done_one_target_is_reward_and_ignores_target_networks():
    config = make_config("td3")
    state = init_state("td3", 7)
    batch = make_batch(8)._replace(done=np.ones((BATCH,), np.float32))
    key = jax.random.key(9)
    y = per_sample_targets("td3", config, state, batch, key)
    np.testing.assert_allclose(y, batch.reward, rtol=0, atol=1e-6)
    # Wildly different target networks change nothing when every transition terminated.
    scrambled = state.replace(
        target_actor_params=jax.tree.map(
            lambda x: np.asarray(x) * 7 + 3, state.target_actor_params
        ),
        target_critic_params=jax.tree.map(
            lambda x: np.asarray(x) * -5 + 1, state.target_critic_params
        ),
    )
    update = jitted_update("td3")
    new_a, m_a = update(config, state, batch, key)
    new_b, m_b = update(config, scrambled, batch, key)
    assert_trees_close(new_a.critic_params, new_b.critic_params, atol=1e-7, rtol=0)
    np.testing.assert_allclose(m_a["target_mean"], np.mean(batch.reward), atol=1e-6)
    np.testing.assert_allclose(m_b["target_mean"], np.mean(batch.reward), atol=1e-6)


def test_done_zero_bootstraps():
    """With done=0 the target does use the target critic (the mask is not inverted)."""
    config = make_config("td3", policy_noise=0.0)
    state = probe_state("td3", actor_raw_bias=0.0, offsets=(2.0, 3.0))
    batch = make_batch(8)._replace(done=np.zeros((BATCH,), np.float32))
    y = per_sample_targets("td3", config, state, batch, jax.random.key(0))
    np.testing.assert_allclose(y, batch.reward + 0.99 * 2.0, atol=1e-5)


def test_tau_one_copies_online_params_on_actor_steps():
    config = make_config("td3", tau=1.0)
    update = jitted_update("td3")
    state0 = init_state("td3", 11)
    state1, m1 = update(config, state0, make_batch(1), jax.random.key(2))
    # First update: no actor step, targets untouched, critic moved.
    assert float(m1["actor_updated"]) == 0.0
    assert_trees_equal(state1.target_actor_params, state0.target_actor_params)
    assert_trees_equal(state1.target_critic_params, state0.target_critic_params)
    assert_trees_equal(state1.actor_params, state0.actor_params)
    assert trees_differ(state1.critic_params, state0.critic_params)
    state2, m2 = update(config, state1, make_batch(3), jax.random.key(4))
    assert float(m2["actor_updated"]) == 1.0
    assert trees_differ(state2.actor_params, state1.actor_params)
    assert_trees_close(state2.target_actor_params, state2.actor_params, atol=1e-7, rtol=0)
    assert_trees_close(state2.target_critic_params, state2.critic_params, atol=1e-7, rtol=0)


def test_polyak_uses_new_online_params():
    """On an actor step: target = tau * (updated online) + (1 - tau) * (old target)."""
    tau = 0.3
    config = make_config("td3", tau=tau, policy_freq=1)
    state = init_state("td3", 12)
    # Make the targets differ from the online params first.
    state = state.replace(
        target_actor_params=jax.tree.map(lambda x: np.asarray(x) + 0.1, state.target_actor_params),
        target_critic_params=jax.tree.map(
            lambda x: np.asarray(x) - 0.1, state.target_critic_params
        ),
    )
    new, _ = jitted_update("td3", 1)(config, state, make_batch(13), jax.random.key(14))
    assert_trees_close(
        new.target_actor_params,
        polyak(new.actor_params, state.target_actor_params, tau),
        atol=1e-6,
        rtol=1e-6,
    )
    assert_trees_close(
        new.target_critic_params,
        polyak(new.critic_params, state.target_critic_params, tau),
        atol=1e-6,
        rtol=1e-6,
    )


@pytest.mark.parametrize("policy_freq", [1, 2, 3])
def test_delayed_schedule(policy_freq):
    config = make_config("td3", policy_freq=policy_freq)
    update = jitted_update("td3", policy_freq)
    state = init_state("td3", 15)
    for i in range(1, 7):
        new, metrics = update(config, state, make_batch(i), jax.random.key(i))
        expect_actor = i % policy_freq == 0
        assert int(new.step) == i
        assert float(metrics["actor_updated"]) == float(expect_actor)
        assert trees_differ(new.critic_params, state.critic_params)
        for name in ("actor_params", "target_actor_params", "target_critic_params"):
            changed = trees_differ(getattr(new, name), getattr(state, name), atol=0.0)
            assert changed == expect_actor, (i, name)
        if not expect_actor:
            assert float(metrics["actor_loss"]) == 0.0
        state = new


N_KEYS = 256


def target_actions(config, state, offset):
    """Target action dim 0 for each of ``N_KEYS`` keys, read off the probe critic.

    Each update sees one transition with reward 0, done 0, so ``y = discount * (a' + offset)``.
    Returns the target actions and the smoothing-noise draws ``normal(key, (1, ACT))[0, 0]``
    that the agent should have made with the same keys.
    """
    batch = tj.Transition(
        obs=np.zeros((EACH, 1, OBS), np.float32), action=np.zeros((EACH, 1, ACT), np.float32),
        reward=np.zeros((EACH, 1), np.float32), next_obs=np.ones((EACH, 1, OBS), np.float32),
        done=np.zeros((EACH, 1), np.float32),
    )  # fmt: skip
    keys = jax.random.split(jax.random.key(123), N_KEYS)
    ys = [
        jitted_update_each("td3")(config, state, batch, keys[i : i + EACH])[1]["target_mean"]
        for i in range(0, N_KEYS, EACH)
    ]
    a = np.concatenate([np.asarray(y) for y in ys]) / config.discount - offset
    return a, np.asarray(_first_normal(keys))


@jax.jit
def _first_normal(keys):
    return jax.vmap(lambda k: jax.random.normal(k, (1, ACT))[0, 0])(keys)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_target_actions_within_bounds(sign):
    max_action = 2.0
    config = make_config(
        "td3", discount=1.0, policy_noise=1.0, noise_clip=0.5, max_action=max_action
    )
    state = probe_state("td3", actor_raw_bias=sign * 5.0, offsets=(0.0, 0.0))
    a, eps = target_actions(config, state, 0.0)
    assert np.all(np.abs(a) <= max_action + 1e-5)
    # The smoothing noise pushes the (almost saturated) target action past the bound often.
    assert np.sum(np.isclose(a, sign * max_action, atol=1e-6)) > 50
    # Exact reproduction with the same key: clip(pi'(s') + clip(noise), -max, max).
    pi = max_action * np.tanh(sign * 5.0)
    expected = np.clip(pi + np.clip(1.0 * eps, -0.5, 0.5), -max_action, max_action)
    np.testing.assert_allclose(a, expected, atol=1e-5)


def test_noise_clipping_bounds():
    config = make_config("td3", discount=0.5, policy_noise=100.0, noise_clip=0.3)
    offset = 0.7
    state = probe_state("td3", actor_raw_bias=0.0, offsets=(offset, offset + 1.0))
    a, eps = target_actions(config, state, offset)
    assert np.all(np.abs(a) <= 0.3 + 1e-5)
    # With a huge std nearly every draw is clipped, to both sides.
    assert np.sum(np.isclose(a, 0.3, atol=1e-5)) > 80
    assert np.sum(np.isclose(a, -0.3, atol=1e-5)) > 80
    np.testing.assert_allclose(a, np.clip(100.0 * eps, -0.3, 0.3), atol=1e-5)


def test_td3_target_depends_on_key_ddpg_does_not():
    batch = make_batch(20)
    k1, k2 = jax.random.key(1), jax.random.key(2)
    update, config, state = jitted_update("td3"), make_config("td3"), init_state("td3", 0)
    (a, ma), (b, mb) = update(config, state, batch, k1), update(config, state, batch, k2)
    assert trees_differ(a.critic_params, b.critic_params)
    assert float(ma["target_mean"]) != float(mb["target_mean"])

    update, config, state = jitted_update("ddpg"), make_config("ddpg"), init_state("ddpg", 0)
    (a, ma), (b, mb) = update(config, state, batch, k1), update(config, state, batch, k2)
    assert_trees_equal(a, b)
    assert float(ma["target_mean"]) == float(mb["target_mean"])


def test_ddpg_single_head_and_every_step_updates():
    config = make_config("ddpg")
    agent = build("ddpg", config)
    state = init_state("ddpg", 0)
    q = jax.jit(agent.critic_apply)(state.critic_params, np.zeros((5, OBS)), np.zeros((5, ACT)))
    assert q.shape == (1, 5)
    update = jitted_update("ddpg", 1)
    for i in range(3):
        new, metrics = update(config, state, make_batch(i), jax.random.key(i))
        assert float(metrics["actor_updated"]) == 1.0
        assert int(new.step) == i + 1
        for name in (
            "actor_params",
            "critic_params",
            "target_actor_params",
            "target_critic_params",
        ):
            assert trees_differ(getattr(new, name), getattr(state, name), atol=0.0), name
        state = new


def test_ddpg_target_bootstrap_by_hand():
    config = make_config("ddpg", discount=0.5)
    state = init_state("ddpg", 0)
    state = state.replace(
        target_actor_params=constant_actor_params(state.target_actor_params, math.atanh(-0.6)),
        target_critic_params=probe_critic_params(state.target_critic_params, (0.1,)),
    )
    reward = np.arange(1.0, 9.0, dtype=np.float32)
    done = np.array([0, 0, 1, 0, 1, 1, 0, 0], np.float32)
    batch = make_batch(3)._replace(reward=reward, done=done)
    y = per_sample_targets("ddpg", config, state, batch, jax.random.key(0))
    # a' = tanh(atanh(-0.6)) = -0.6 (no smoothing), Q' = a' + 0.1 = -0.5.
    np.testing.assert_allclose(y, reward + 0.5 * (1.0 - done) * -0.5, atol=1e-5)


# --------------------------------------------------------------------------------------------
# compilation, vmap, scan
# --------------------------------------------------------------------------------------------


def test_update_compiles_once():
    """The usual path: an agent built from Python floats, its ``update`` under ``jax.jit``.

    It traces once for all calls (critic-only and actor steps alike), and computes the same as
    the traced-config program the other tests use.
    """
    config = make_config("td3", **TD3_CASES["pf2"])
    agent = build("td3", config)
    traces = 0

    def counted(state, batch, key):
        nonlocal traces
        traces += 1
        return agent.update(state, batch, key)

    update = jax.jit(counted)
    state = traced_state = init_state("td3", 0)
    for i in range(5):
        batch, key = make_batch(i), jax.random.key(10 + i)
        state, metrics = update(state, batch, key)
        traced_state, traced_metrics = jitted_update("td3")(config, traced_state, batch, key)
        assert_trees_close(state, traced_state, atol=1e-6, rtol=1e-6)
        assert_trees_close(metrics, traced_metrics, atol=1e-6, rtol=1e-6)
    # A freshly initialised state (not produced by update) hits the same cache entry.
    update(init_state("td3", 99), make_batch(5), jax.random.key(5))
    assert traces == 1
    assert int(state.step) == 5


def test_vmap_over_states_matches_unbatched():
    config = make_config("td3", tau=0.2)
    n = 3
    keys = jax.random.split(jax.random.key(0), n)
    states = stack([jitted_init("td3")(keys[j]) for j in range(n)])
    assert trees_differ(index(states, 0).actor_params, index(states, 1).actor_params)
    singles = [index(states, j) for j in range(n)]
    vupdate = jax.jit(jax.vmap(build("td3", config).update))
    update = jitted_update("td3")
    for i in range(3):  # steps 1 and 3 critic-only, step 2 with the actor (cond under vmap)
        batches = stack([make_batch(100 * i + j) for j in range(n)])
        keys = jax.random.split(jax.random.key(500 + i), n)
        states, vmetrics = vupdate(states, batches, keys)
        for j in range(n):
            singles[j], metrics = update(config, singles[j], index(batches, j), keys[j])
            assert_trees_close(index(states, j), singles[j], what=f"member {j} step {i}")
            assert_trees_close(index(vmetrics, j), metrics)
    np.testing.assert_array_equal(states.step, [3, 3, 3])


def test_vmap_with_axis_name_keeps_the_actor_branch_and_each_schedule():
    """With ``axis_name``, the delayed actor update stays a ``cond`` under vmap (no select that
    computes it every step), and members on different schedules still update on their own."""
    config = make_config("td3", tau=0.2)
    n = 3
    keys = jax.random.split(jax.random.key(1), n)
    singles = [jitted_init("td3")(keys[j]) for j in range(n)]
    singles[1] = singles[1].replace(step=jnp.ones((), jnp.int32))  # member 1 is one step ahead
    states = stack(singles)
    agent = tj.td3(config, OBS, ACT, axis_name="m")
    vupdate = jax.vmap(agent.update, axis_name="m")
    batches = stack([make_batch(j) for j in range(n)])
    vkeys = jax.random.split(jax.random.key(7), n)
    assert "cond[" in str(jax.make_jaxpr(vupdate)(states, batches, vkeys))
    plain = str(jax.make_jaxpr(jax.vmap(build("td3", config).update))(states, batches, vkeys))
    assert "cond[" not in plain  # what axis_name avoids: both branches computed and selected
    update = jitted_update("td3")
    vupdate = jax.jit(vupdate)
    for i in range(3):
        batches = stack([make_batch(100 * i + j) for j in range(n)])
        vkeys = jax.random.split(jax.random.key(600 + i), n)
        states, vmetrics = vupdate(states, batches, vkeys)
        for j in range(n):
            singles[j], metrics = update(config, singles[j], index(batches, j), vkeys[j])
            assert_trees_close(index(states, j), singles[j], what=f"member {j} step {i}")
            assert_trees_close(index(vmetrics, j), metrics)
    np.testing.assert_array_equal(states.step, [3, 4, 3])


def test_vmap_over_hyperparameters():
    """Float config fields may be traced: a vmap over tau equals separately built agents."""
    taus = [0.1, 0.6]
    state = init_state("td3", 0)
    batch = make_batch(1)
    key = jax.random.key(2)
    configs = stack([make_config("td3", tau=t, policy_freq=1) for t in taus])
    swept, _ = jax.jit(jax.vmap(jitted_update("td3", 1), in_axes=(0, None, None, None)))(
        configs, state, batch, key
    )
    for j, tau in enumerate(taus):
        single, _ = jitted_update("td3", 1)(
            make_config("td3", tau=tau, policy_freq=1), state, batch, key
        )
        assert_trees_close(index(swept, j), single, atol=1e-6, rtol=1e-5)
    assert trees_differ(index(swept, 0).target_actor_params, index(swept, 1).target_actor_params)


@pytest.mark.parametrize("algo", ["td3", "ddpg"])
def test_scan_equals_python_loop(algo):
    policy_freq = 3 if algo == "td3" else 1
    config = make_config(algo, policy_freq=3, tau=0.1) if algo == "td3" else make_config(algo)
    agent = build(algo, config)
    n = 7
    batches = stack([make_batch(i) for i in range(n)])
    keys = jax.random.split(jax.random.key(42), n)
    state0 = init_state(algo, 3)

    @jax.jit
    def scanned(state, batches, keys):
        return jax.lax.scan(lambda s, xs: agent.update(s, *xs), state, (batches, keys))

    scan_state, scan_metrics = scanned(state0, batches, keys)
    update = jitted_update(algo, policy_freq)
    state = state0
    for i in range(n):
        state, metrics = update(config, state, index(batches, i), keys[i])
        assert_trees_close(index(scan_metrics, i), metrics)
    assert_trees_close(scan_state, state)
    assert int(scan_state.step) == n
    if algo == "td3":
        np.testing.assert_array_equal(scan_metrics["actor_updated"], [0, 0, 1, 0, 0, 1, 0])


# --------------------------------------------------------------------------------------------
# configuration
# --------------------------------------------------------------------------------------------


def test_td3_config_defaults():
    c = tj.TD3Config()
    assert c.discount == 0.99
    assert c.tau == 0.005
    assert c.policy_noise == 0.2
    assert c.noise_clip == 0.5
    assert c.policy_freq == 2
    assert c.actor_lr == 1e-3 and c.critic_lr == 1e-3
    assert c.max_action == 1.0


def test_ddpg_config_defaults():
    c = tj.DDPGConfig()
    assert tuple(c.hidden_sizes) == (256, 256)
    assert c.actor_lr == 1e-4
    assert c.critic_lr == 1e-3
    assert c.tau == 1e-2
    assert c.discount == 0.99


def test_default_ddpg_network_widths():
    agent = tj.ddpg(tj.DDPGConfig(), OBS, ACT)
    state = jax.eval_shape(agent.init, jax.random.key(0))
    shapes = [leaf.shape for leaf in jax.tree.leaves(state.actor_params)]
    assert sorted(shapes) == sorted([(OBS, 256), (256,), (256, 256), (256,), (256, ACT), (ACT,)])
    critic_shapes = [leaf.shape for leaf in jax.tree.leaves(state.critic_params)]
    assert (1, OBS + ACT, 256) in critic_shapes and (1, 256, 256) in critic_shapes


@pytest.mark.parametrize(
    "build_bad",
    [
        lambda: tj.td3(tj.TD3Config(policy_freq=0, hidden_sizes=HIDDEN), OBS, ACT),
        lambda: tj.td3(tj.TD3Config(policy_freq=-1, hidden_sizes=HIDDEN), OBS, ACT),
        lambda: tj.td3(tj.TD3Config(hidden_sizes=(16, 0)), OBS, ACT),
        lambda: tj.td3(tj.TD3Config(hidden_sizes=()), OBS, ACT),
        lambda: tj.td3(tj.TD3Config(hidden_sizes=HIDDEN), 0, ACT),
        lambda: tj.td3(tj.TD3Config(hidden_sizes=HIDDEN), OBS, 0),
        lambda: tj.ddpg(tj.DDPGConfig(hidden_sizes=(0,)), OBS, ACT),
        lambda: tj.ddpg(tj.DDPGConfig(hidden_sizes=HIDDEN), 0, ACT),
        lambda: tj.ddpg(tj.DDPGConfig(hidden_sizes=HIDDEN), OBS, -2),
    ],
)
def test_bad_config_raises(build_bad):
    with pytest.raises(ValueError):
        build_bad()


def test_actor_output_range_and_act_alias():
    agent = build("td3", make_config("td3", max_action=2.5))
    state = init_state("td3", 0)
    # Blow the actor's weights up so tanh saturates: outputs stay within +-max_action.
    big = jax.tree.map(lambda x: 100 * np.asarray(x), state.actor_params)
    obs = np.random.default_rng(1).normal(size=(64, OBS)).astype(np.float32) * 10
    a = np.asarray(jax.jit(agent.act)(big, obs))
    assert a.shape == (64, ACT)
    assert np.all(np.abs(a) <= 2.5 + 1e-6) and np.max(np.abs(a)) > 2.4
    np.testing.assert_array_equal(a, jax.jit(agent.actor_apply)(big, obs))


# --------------------------------------------------------------------------------------------
# sanity learning
# --------------------------------------------------------------------------------------------


def test_bandit_actor_learns_optimal_action():
    """One-step bandit, reward -(a - 0.5)^2, done = 1: the actor's action goes to 0.5."""
    config = tj.TD3Config(hidden_sizes=(32, 32), actor_lr=5e-3, critic_lr=1e-2)
    agent = tj.td3(config, 1, 1)

    @jax.jit
    def train(state, key):
        def body(state, key):
            k_act, k_upd = jax.random.split(key)
            action = jax.random.uniform(k_act, (64, 1), minval=-1.0, maxval=1.0)
            obs = jnp.ones((64, 1))
            batch = tj.Transition(
                obs=obs,
                action=action,
                reward=-((action[:, 0] - 0.5) ** 2),
                next_obs=obs,
                done=jnp.ones((64,)),
            )
            state, metrics = agent.update(state, batch, k_upd)
            return state, metrics["critic_loss"]

        return jax.lax.scan(body, state, jax.random.split(key, 500))

    act = jax.jit(agent.act)
    state = jax.jit(agent.init)(jax.random.key(0))
    start = float(act(state.actor_params, np.ones((1, 1), np.float32))[0, 0])
    state, losses = train(state, jax.random.key(1))
    action = float(act(state.actor_params, np.ones((1, 1), np.float32))[0, 0])
    assert abs(start - 0.5) > 0.2, start  # it really had to move
    assert abs(action - 0.5) < 0.1, action
    assert float(losses[-20:].mean()) < float(losses[:20].mean())


@pytest.mark.parametrize(
    "build_bad, message",
    [
        (lambda: tj.td3(tj.TD3Config(hidden_sizes=HIDDEN), 3.5, ACT), "observation_size"),
        (lambda: tj.td3(tj.TD3Config(hidden_sizes=HIDDEN), OBS, True), "action_size"),
        (lambda: tj.td3(tj.TD3Config(tau=2.0, hidden_sizes=HIDDEN), OBS, ACT), "tau"),
        (lambda: tj.td3(tj.TD3Config(tau=0.0, hidden_sizes=HIDDEN), OBS, ACT), "tau"),
        (lambda: tj.ddpg(tj.DDPGConfig(discount=1.5, hidden_sizes=HIDDEN), OBS, ACT), "discount"),
        (lambda: tj.td3(tj.TD3Config(actor_lr=float("nan"), hidden_sizes=HIDDEN), OBS, ACT),
         "actor_lr"),
    ],
)  # fmt: skip
def test_impossible_sizes_and_hyperparameters_are_refused(build_bad, message):
    """``td3(cfg, 3.5, ...)`` and ``tau=2`` are refused."""
    with pytest.raises(ValueError, match=message):
        build_bad()


def test_update_with_a_wrongly_shaped_batch_names_the_field():
    agent = build("td3", make_config("td3"))
    state = init_state("td3", 0)
    batch = make_batch(0)
    expected = r"Transition\.obs has shape \[8, 5\]; expected \[batch, 3\]"
    with pytest.raises(ValueError, match=expected):
        agent.update(state, batch._replace(obs=np.zeros((BATCH, 5), np.float32)), jax.random.key(0))
    with pytest.raises(ValueError, match=r"Transition\.reward has shape \[8, 1\]"):
        agent.update(state, batch._replace(reward=batch.reward[:, None]), jax.random.key(0))
    # a batch size that differs: the field that differs is named, not obs
    for name in ("reward", "done", "next_obs", "obs"):
        short = batch._replace(**{name: getattr(batch, name)[:7]})
        expected = rf"^Transition\.{name} has a batch of 7 rows \(shape \[7[],]"
        with pytest.raises(ValueError, match=expected) as err:
            agent.update(state, short, jax.random.key(0))
        assert "have 8; every field needs the same batch size" in str(err.value)


def test_act_on_observations_of_another_width_says_both_sizes():
    agent = build("td3", make_config("td3"))
    state = init_state("td3", 0)
    expected = (
        r"^act got observations of size 5 \(shape \[4, 5\]\); this agent's actor "
        r"takes observation_size 3 "
    )
    with pytest.raises(ValueError, match=expected):
        agent.act(state.actor_params, np.zeros((4, 5), np.float32))
    with pytest.raises(ValueError, match=expected):  # also where it is traced
        jax.jit(agent.act)(state.actor_params, np.zeros((4, 5), np.float32))
    with pytest.raises(ValueError, match="observations that are a scalar"):
        agent.act(state.actor_params, np.float32(0))
    assert agent.act(state.actor_params, np.zeros((OBS,), np.float32)).shape == (ACT,)


def test_critic_apply_on_inputs_of_another_width_names_the_argument():
    """A wrong width is one ValueError naming ``obs`` or ``action`` and both sizes the critics
    take (flax raised its ScopeParamShapeError); right widths give each head's Q-value."""
    agent = build("td3", make_config("td3"))
    state = init_state("td3", 0)
    obs, action = np.zeros((4, OBS), np.float32), np.zeros((4, ACT), np.float32)
    sizes = rf"this agent's critics take observations of size {OBS} and actions of size {ACT}"
    wide, narrow = np.zeros((4, 5), np.float32), np.zeros((4, 1), np.float32)
    cases = [
        ((wide, action), r"^critic_apply got obs of size 5 \(shape \[4, 5\]\)"),
        ((obs, narrow), r"^critic_apply got action of size 1 \(shape \[4, 1\]\)"),
        ((np.float32(0), action), r"^critic_apply got obs that is a scalar \(shape"),
    ]
    for args, expected in cases:
        with pytest.raises(ValueError, match=expected) as err:
            agent.critic_apply(state.critic_params, *args)
        assert sizes in str(err.value)
        with pytest.raises(ValueError, match=expected):  # also where it is traced
            jax.jit(agent.critic_apply)(state.critic_params, *args)
    with pytest.raises(ValueError, match=r"obs of shape \[4, 3\] and action of shape \[2, 2\]; "
                       "their leading axes must be the same"):  # fmt: skip
        agent.critic_apply(state.critic_params, obs, action[:2])
    # Right widths: one Q-value per head and row, each head's own network on [obs, action].
    rng = np.random.default_rng(1)
    obs, action = rng.normal(size=obs.shape).astype(np.float32), rng.normal(size=action.shape)
    q = agent.critic_apply(state.critic_params, obs, action.astype(np.float32))
    assert q.shape == (2, 4)
    assert not np.allclose(q[0], q[1])  # two independently initialised heads


def test_a_key_that_is_no_prng_key_is_one_type_error_naming_the_function():
    """``update(state, batch, 0)`` and ``init(0)`` once raised JAX's invalid-PRNG-key error
    from deep inside; a batch of keys where one is meant is refused too. A raw key and the
    typed key of the same seed are the same bits, so they give the same update."""
    agent = build("td3", make_config("td3"))
    state, batch = init_state("td3", 0), make_batch(0)
    advice = re.escape("must be one PRNG key, jax.random.key(seed) or jax.random.PRNGKey(seed)")
    bad = [(0, "int 0"), (np.zeros(3, np.uint32), "an array of shape [3] and dtype uint32"),
           (np.zeros(2, np.int32), "an array of shape [2] and dtype int32"),
           (jax.random.split(jax.random.key(0), 3), "an array of [3] keys")]  # fmt: skip
    for key, said in bad:
        with pytest.raises(TypeError, match=f"^update's key {advice}") as err:
            agent.update(state, batch, key)
        assert str(err.value).endswith(f", got {said}")
        with pytest.raises(TypeError, match=f"^init's key {advice}"):
            agent.init(key)
    update = jax.jit(agent.update)  # (compiled: op by op, an update takes seconds on a CPU)
    raw, typed = (update(state, batch, k) for k in (jax.random.PRNGKey(1), jax.random.key(1)))
    for a, b in zip(jax.tree.leaves(raw), jax.tree.leaves(typed), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
