"""Environments of your own (#28): objects of the four kinds, ``--env module.path:function``,
the check that reports a wrong part in one line, seeds, several devices and the example."""

from __future__ import annotations

import dataclasses
import inspect
import json
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support import assert_one_line_error, main, optimised_env, read_records

from td3_jax import envs
from td3_jax.common import errors
from td3_jax.config.build import make_spec, make_train
from td3_jax.config.schema import TrainConfig
from td3_jax.core.training import key_for_seed
from td3_jax.envs import FunctionalEnv
from td3_jax.runner.run import train

REPO = Path(__file__).parents[2]
TINY = dict(num_envs=4, total_steps=64, eval_every=32, warmup_steps=16, batch_size=16,
            updates_per_iter=1, hidden_sizes=(16, 16), eval_envs=2, buffer_size=64)  # fmt: skip
TINY_FLAGS = ["--num-envs", "4", "--total-steps", "256", "--eval-every", "128",
              "--warmup-steps", "32", "--batch-size", "32", "--hidden-sizes", "16", "16",
              "--eval-envs", "2", "--quiet"]  # fmt: skip


def drift(limit: int = 1000) -> FunctionalEnv:
    """A toy environment: ``x [2]`` moved by the action, reward ``-|x|^2``, never terminates."""

    def reset(key):
        x = jax.random.uniform(key, (2,), minval=-1.0, maxval=1.0)
        return x, x

    def step(x, action):
        x = x + 0.1 * action
        return x, x, -jnp.sum(x**2), jnp.zeros((), bool)

    return FunctionalEnv(reset, step, observation_size=2, action_size=2, episode_length=limit,
                         name="drift")  # fmt: skip


def counter(low=-1.0, high=1.0) -> FunctionalEnv:
    """State ``(count, last action)``; observation ``[count]``; terminates at count 3."""

    def reset(key):
        del key
        return (jnp.zeros((), jnp.int32), jnp.zeros(3)), jnp.zeros(1)

    def step(state, action):
        count = state[0] + 1
        return (count, action), count[None].astype(jnp.float32), 1.0 * count, count == 3

    return FunctionalEnv(reset, step, observation_size=1, action_size=3, action_low=low,
                         action_high=high, episode_length=100, name="counter")  # fmt: skip


# ---------------------------------------------------------------------------------------------
# what td3-jax does with a FunctionalEnv
# ---------------------------------------------------------------------------------------------


def test_a_functional_env_gets_actions_rescaled_to_its_bounds():
    """The agent's -1, 0 and 1 reach the environment as low, the middle and high."""
    env = envs.make(counter(low=[-2.0, 0.0, 10.0], high=[2.0, 1.0, 20.0]))
    state = envs.reset(env, jax.random.PRNGKey(0), 1)
    state, _ = envs.step(env, state, jnp.array([[-1.0, 0.0, 1.0]]))
    np.testing.assert_allclose(state.inner[1][0], [-2.0, 0.5, 20.0])
    assert env.name == "object/counter" and env.row_size == 1


def test_termination_truncation_and_the_true_last_observation():
    """Terminated at count 3 (episode_length 5) or truncated at 2 (episode_length 2): the
    step's observation is the last one, the state's the next episode's first."""
    for limit, end, terminated in ((5, 3, True), (2, 2, False)):
        env = envs.make(counter(), episode_length=limit)
        state = envs.reset(env, jax.random.PRNGKey(0), 1)
        for _ in range(end):
            state, result = envs.step(env, state, jnp.zeros((1, 3)))
        assert bool(result.terminated[0]) is terminated
        assert bool(result.truncated[0]) is not terminated
        assert float(result.next_obs[0, 0]) == end and float(state.obs[0, 0]) == 0.0
        assert float(result.finished_return[0]) == sum(range(1, end + 1))


# ---------------------------------------------------------------------------------------------
# the check: one line for each wrong part
# ---------------------------------------------------------------------------------------------


def _branching_step(x, a):
    if x[0] > 0:  # a Python branch on a traced value
        return x, x, 0.0, False
    return x, x, 1.0, False


BAD = {
    "three outputs": (dict(step=lambda x, a: (x, x, 0.0)), "must return (state, observation"),
    "observation size": (dict(observation_size=3), "reset(key) gives an observation of float32[2]"),
    "step's observation": (dict(step=lambda x, a: (x, jnp.zeros(5), 0.0, False)), "float32[5]"),
    "reward shape": (dict(step=lambda x, a: (x, x, jnp.zeros(2), False)), "reward of float32[2]"),
    "state dtype": (dict(step=lambda x, a: (x.astype(jnp.int32), x, 0.0, False)),
                    "turns state from float32[2] into int32[2]"),
    "not jittable": (dict(step=_branching_step), "is not jittable"),
    "numpy on values": (dict(reset=lambda k: (np.asarray(k), np.zeros(2))), "is not jittable"),
    "infinite bound": (dict(action_high=float("inf")), "action_high must be 2 finite numbers"),
    "inverted bounds": (dict(action_low=1.0, action_high=0.0), "must be below action_high"),
    "bounds' shape": (dict(action_low=[0.0, 0.0, 0.0]), "action_low has shape (3,)"),
    "no bound": (dict(action_low=None), "action_low is None; give one number or action_size"),
    "a bound as text": (dict(action_high="1"), "action_high is '1'; give one number"),
    "missing attribute": (dict(step=lambda x, a: (x, x.obs, 0.0, False)), "AttributeError"),
    "action size": (dict(action_size=3), "step(state, action) with an action of float32[3] "
                    "(action_size) failed when traced: TypeError: add got incompatible shapes"),
}  # fmt: skip


@pytest.mark.parametrize("case", sorted(BAD))
def test_a_wrong_part_is_one_line_naming_it(case):
    change, needle = BAD[case]
    with pytest.raises(errors.CustomEnvironmentError) as caught:
        envs.make(dataclasses.replace(drift(), **change))
    message = str(caught.value)
    assert needle in message and message.startswith("object/drift: ")
    assert "\n" not in message and caught.value.exit_code == 2


def test_an_object_of_an_unknown_kind_says_what_is_taken():
    with pytest.raises(errors.CustomEnvironmentError, match=r"a builtins\.dict is not an env"):
        envs.make({"reset": None})


# ---------------------------------------------------------------------------------------------
# the sources' own objects
# ---------------------------------------------------------------------------------------------


def test_gymnax_objects_are_the_named_environment():
    """``(env, params)`` and a bare gymnax env match ``gymnax/Pendulum-v1``: sizes, bounds,
    time limit and the first observation of a key."""
    import gymnax

    named = envs.make("gymnax/Pendulum-v1")
    env, params = gymnax.make("Pendulum-v1")
    key = jax.random.PRNGKey(3)
    for made in (envs.make((env, params)), envs.make(env)):
        assert made.name == "object/Pendulum-v1"
        assert (made.observation_size, made.action_size, made.episode_length) == (3, 1, 200)
        np.testing.assert_array_equal(made.action_high, named.action_high)
        np.testing.assert_array_equal(made.reset_fn(key)[1], named.reset_fn(key)[1])


def test_a_brax_env_is_taken_and_its_wrapped_form_refused():
    from brax import envs as brax_envs

    made = envs.make(brax_envs.get_environment("inverted_pendulum", backend="positional"))
    assert (made.observation_size, made.action_size, made.episode_length) == (4, 1, 1000)
    assert made.mj_model is not None and made.qpos_fn is not None  # renderable
    wrapped = brax_envs.create("inverted_pendulum", backend="positional")
    with pytest.raises(errors.CustomEnvironmentError, match=r"brax\.envs\.get_environment"):
        envs.make(wrapped)


def playground_point_mass():
    """The example's point mass as a Playground ``MjxEnv`` with a dict observation: the
    actor's ``state`` (positions) is the start of the critics' ``privileged_state``."""
    import mujoco
    from ml_collections import config_dict
    from mujoco import mjx
    from mujoco_playground import MjxEnv, State

    from examples.point_mass import XML

    class PointMass(MjxEnv):
        def __init__(self):
            super().__init__(config_dict.create(ctrl_dt=0.02, sim_dt=0.02, episode_length=50))
            self._mj_model = mujoco.MjModel.from_xml_string(XML)
            self._mjx_model = mjx.put_model(self._mj_model)

        def _obs(self, data):
            return {"state": data.qpos, "velocity": data.qvel,
                    "privileged_state": jnp.concatenate([data.qpos, data.qvel])}  # fmt: skip

        def reset(self, rng):
            data = mjx.make_data(self._mjx_model).replace(qpos=jax.random.uniform(rng, (2,)))
            return State(data, self._obs(data), jnp.zeros(()), jnp.zeros(()), {}, {})

        def step(self, state, action):
            data = mjx.step(self._mjx_model, state.data.replace(ctrl=action))
            return state.replace(data=data, obs=self._obs(data), reward=-data.qpos[0])

        xml_path = property(lambda self: "")
        action_size = property(lambda self: 2)
        mj_model = property(lambda self: self._mj_model)
        mjx_model = property(lambda self: self._mjx_model)

    return PointMass()


def test_a_playground_env_with_dict_observations_gets_an_asymmetric_critic(monkeypatch):
    """Actor 2 (positions), critics 4 (positions and velocities): one row of 4 where the
    actor's is the critics' prefix, of 4 side by side for another key; a missing key is one
    line; the agent's critics take the critics' observation."""
    monkeypatch.syspath_prepend(str(REPO))
    env = playground_point_mass()
    made = envs.make(env)
    assert (made.name, made.episode_length) == ("object/PointMass", 50)
    assert (made.observation_size, made.critic_observation_size, made.critic_offset) == (2, 4, 0)
    assert made.row_size == 4
    side_by_side = envs.make(env, options=envs.EnvOptions(critic_obs_key="velocity"))
    assert (side_by_side.critic_observation_size, side_by_side.critic_offset) == (2, 2)
    with pytest.raises(errors.EnvironmentOptionError, match="'speed' is not one of"):
        envs.make(env, options=envs.EnvOptions(critic_obs_key="speed"))
    spec = make_spec(TrainConfig(**TINY), env=env)
    assert spec.agent.critic_observation_size == 4 and spec.env.observation_size == 2


# ---------------------------------------------------------------------------------------------
# module.path:function
# ---------------------------------------------------------------------------------------------


FACTORIES = """
from td3_jax.envs import FunctionalEnv
import test_custom_envs

def make():
    return test_custom_envs.drift()

def broken():
    raise RuntimeError("no robot here")

def not_an_env():
    return 42

def make_env():
    return make()

def the_class():
    return FunctionalEnv

NOT_CALLABLE = 3
"""


@pytest.mark.parametrize(
    ("spec", "needle"),
    [
        ("my_factories:make", "object/drift"),  # (made: no error)
        ("my_factories:", "neither a factory, written module.path:function"),
        ("my-factories:make", "neither a factory"),
        ("no_such_package.envs:make", "no module 'no_such_package' in"),
        ("my_factories.py:make", "give the module's name, not its file: --env my_factories:make"),
        ("my_factories:mak", "my_factories has no 'mak'; did you mean 'make'?"),
        ("my_factories:NOT_CALLABLE", "is not callable (int)"),
        ("my_factories_broken:make", "importing my_factories_broken raised ModuleNotFoundError"),
        ("my_factories:broken", "calling it raised RuntimeError: no robot here"),
        ("my_factories:not_an_env", "a builtins.int is not an environment"),
        ("my_factories:the_class", "FunctionalEnv is a class: return an instance of it"),
    ],
)
def test_a_factory_is_found_from_the_current_directory_or_said_in_one_line(
    spec, needle, tmp_path, monkeypatch
):
    (tmp_path / "my_factories.py").write_text(FACTORIES)
    (tmp_path / "my_factories_broken.py").write_text("import a_package_it_needs\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in ("", os.getcwd())])
    for name in ("my_factories", "my_factories_broken"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    if spec == "my_factories:make":
        made = envs.make(spec)
        assert made.name == spec and made.observation_size == 2 and str(tmp_path) in sys.path
        return
    with pytest.raises(errors.CustomEnvironmentError) as caught:
        envs.make(spec)
    assert needle in str(caught.value) and "\n" not in str(caught.value)


def test_a_factory_importing_mjx_in_its_body_does_not_print_its_warp_notes(
    tmp_path, monkeypatch, capsys
):
    """MJX's "Failed to import warp" lines, printed when a factory's body imports Brax where
    Warp is not installed, are dropped as they are for td3-jax's own imports; the factory's
    other output stays."""
    (tmp_path / "noisy_factories.py").write_text(textwrap.dedent("""
        import jax.numpy as jnp
        from td3_jax.envs import FunctionalEnv

        def make():
            print("Failed to import warp: No module named 'warp'")
            print("building a still world")
            print("Failed to import mujoco_warp: No module named 'warp'")
            still = lambda x, a: (x, x, -jnp.sum(x**2), jnp.zeros((), bool))
            return FunctionalEnv(lambda key: (jnp.zeros(2), jnp.zeros(2)), still,
                                 observation_size=2, action_size=2)
        """))  # fmt: skip
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "noisy_factories", raising=False)
    made = envs.make("noisy_factories:make")
    assert made.observation_size == 2
    assert capsys.readouterr().out == "building a still world\n"


def test_the_warp_notes_filter_passes_each_other_line_as_it_ends(monkeypatch):
    """A line reaches standard output as soon as its newline is written (a slow factory's
    progress shows), a note is dropped even when written in pieces, and a last line without
    its newline is kept; without a standard output nothing is filtered or raised."""
    import io

    from td3_jax.envs.physics import without_warp_import_notes

    out = io.StringIO()
    monkeypatch.setattr(sys, "stdout", out)
    with without_warp_import_notes():
        print("step 1 of 2")
        assert out.getvalue() == "step 1 of 2\n"
        sys.stdout.write("Failed to import ")
        sys.stdout.write("warp: No module named 'warp'\nstep 2")
        assert out.getvalue() == "step 1 of 2\n"
        sys.stdout.write(" of 2\ndone")
        print("\r50%", end="", flush=True)  # (a flushed progress bar passes at once)
        assert out.getvalue() == "step 1 of 2\nstep 2 of 2\ndone\r50%"
        print("Failed to", end="", flush=True)  # (what may begin a note waits for its line)
        assert out.getvalue().endswith("\r50%")
        print(" import warp: No module named 'warp'")
    assert out.getvalue() == "step 1 of 2\nstep 2 of 2\ndone\r50%"
    monkeypatch.setattr(sys, "stdout", None)
    with without_warp_import_notes():
        pass


TYPO_FACTORIES = """
import json

def make_arm():
    return None

def make_leg():
    return None

class Arms:
    @staticmethod
    def make():
        return None

LINK_COUNT = 3
"""


@pytest.fixture
def typo_modules(tmp_path, monkeypatch):
    """``typo_factories`` and ``typo_pkg.envs`` (each of them the module above) on the Python
    path, not in the current directory; forgotten again afterwards."""
    (tmp_path / "typo_factories.py").write_text(TYPO_FACTORIES)
    (tmp_path / "typo_pkg").mkdir()
    (tmp_path / "typo_pkg" / "__init__.py").write_text("")
    (tmp_path / "typo_pkg" / "envs.py").write_text(TYPO_FACTORIES)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.chdir(tmp_path.parent)
    yield
    for name in [n for n in sys.modules if n.partition(".")[0] in ("typo_factories", "typo_pkg")]:
        del sys.modules[name]


@pytest.mark.parametrize(
    ("spec", "said"),
    [
        ("typo_factories:make_ar", "typo_factories has no 'make_ar'; did you mean 'make_arm'?"),
        ("typo_factories:MAKE_LEG", "typo_factories has no 'MAKE_LEG'; did you mean 'make_leg'?"),
        ("typo_pkg.envs:mak_arm", "typo_pkg.envs has no 'mak_arm'; did you mean 'make_arm'?"),
        ("typo_factories:Arms.mak", "typo_factories:Arms has no 'mak'; did you mean 'make'?"),
        # a module or a number is no factory: never suggested; the callables are listed
        ("typo_factories:jsn", "typo_factories has no 'jsn'; its public callables: Arms, "
                               "make_arm, make_leg"),
        ("typo_factories:LINK_CONT", "typo_factories has no 'LINK_CONT'; its public callables: "
                                   "Arms, make_arm, make_leg"),
    ],
)  # fmt: skip
def test_a_mistyped_factory_gets_the_closest_callable(typo_modules, spec, said):
    with pytest.raises(errors.CustomEnvironmentError) as caught:
        envs.make(spec)
    assert str(caught.value) == f"{spec}: {said}"


_LAZY_FACTORIES = """
import warnings
__all__ = ["make_arm", "old_make", "broken_make"]


def make_arm():
    pass


def __getattr__(name):  # PEP 562: names looked up lazily
    if name == "old_make":
        warnings.warn("old_make is deprecated", DeprecationWarning)
        return make_arm
    if name == "broken_make":
        raise ImportError("its optional dependency is missing")
    raise AttributeError(name)
"""


def test_a_module_whose_lookups_warn_or_fail_still_gets_one_line(tmp_path, monkeypatch, recwarn):
    """A module's ``__getattr__`` that warns or raises (not AttributeError) while its names are
    looked at for a suggestion: still the one line, nothing warned; the deprecated name is
    suggested (it is a callable), the broken one never."""
    (tmp_path / "lazy_factories.py").write_text(_LAZY_FACTORIES)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "lazy_factories", raising=False)
    cases = [
        ("lazy_factories:old_mak", "did you mean 'old_make'?"),
        ("lazy_factories:zzz", "its public callables: make_arm, old_make"),
    ]
    for spec, said in cases:
        with pytest.raises(errors.CustomEnvironmentError) as caught:
            envs.make(spec)
        assert str(caught.value).endswith(said) and "\n" not in str(caught.value)
    assert not [w for w in recwarn if "deprecated" in str(w.message)]
    sys.modules.pop("lazy_factories", None)


def test_pythonpath_folders_under_pythons_prefix_are_searched_for_a_close_module(
    tmp_path, monkeypatch
):
    """A container's ``PYTHONPATH=/usr/src/app`` under a system Python (prefix ``/usr``): its
    modules are the user's own, so a mistyped one is told the closest there."""
    app = tmp_path / "usr" / "src" / "app"
    app.mkdir(parents=True)
    (app / "my_robot_envs.py").write_text("def make():\n    pass\n")
    monkeypatch.setattr(sys, "prefix", str(tmp_path / "usr"))
    monkeypatch.setattr(sys, "base_prefix", str(tmp_path / "usr"))
    monkeypatch.setenv("PYTHONPATH", str(app))
    monkeypatch.syspath_prepend(str(app))
    monkeypatch.chdir(tmp_path)
    with pytest.raises(errors.CustomEnvironmentError) as caught:
        envs.make("my_robot_env:make")
    assert str(caught.value).endswith("; did you mean 'my_robot_envs'?")


@pytest.mark.parametrize(
    ("spec", "missing", "close"),
    [
        ("typo_factorie:make_arm", "typo_factorie", "typo_factories"),
        ("typo_pk.envs:make_arm", "typo_pk", "typo_pkg"),
        ("typo_pkg.env:make_arm", "typo_pkg.env", "typo_pkg.envs"),
    ],
)
def test_a_mistyped_module_gets_the_closest_module(typo_modules, spec, missing, close):
    """On the Python path, though not in the current directory; in a package, its modules."""
    with pytest.raises(errors.CustomEnvironmentError) as caught:
        envs.make(spec)
    said = str(caught.value)
    assert said.startswith(f"{spec}: no module {missing!r} in ") and "\n" not in said
    assert said.endswith(f"; did you mean {close!r}?")


def test_a_mistyped_module_with_nothing_close_gets_no_guess(typo_modules):
    with pytest.raises(errors.CustomEnvironmentError) as caught:
        envs.make("quite_unlike_anything:make_arm")
    assert "did you mean" not in str(caught.value)
    assert str(caught.value).endswith("--resume, eval, render and export)")


def test_the_cli_says_a_mistyped_factory_in_one_line(typo_modules, tmp_path, capsys):
    code, _, err = main(["train", "--env", "typo_factories:make_ar", *TINY_FLAGS, "--out",
                         str(tmp_path / "run")], capsys)  # fmt: skip
    assert_one_line_error(code, err, "has no 'make_ar'; did you mean 'make_arm'?")


@pytest.mark.mjx
def test_the_cli_sweeps_a_factory_over_seeds_and_finds_it_again(tmp_path, monkeypatch, capsys):
    """``sweep --env examples.point_mass:make`` over 2 learning rates x 2 seeds: config.json
    records the factory, each member is evaluated, ``eval`` makes the environment again from
    it; from a directory where the module is not found, ``eval`` says so in one line."""
    monkeypatch.chdir(REPO)
    out = tmp_path / "run"
    code, _, err = main(["sweep", "--env", "examples.point_mass:make", "--seeds", "2",
                         "--sweep-actor-lr", "1e-3", "3e-4", *TINY_FLAGS, "--out", str(out)],
                        capsys)  # fmt: skip
    assert code == 0, err
    assert json.loads((out / "config.json").read_text())["env"] == "examples.point_mass:make"
    last = read_records(out)[-1]
    assert last["env"] == "examples.point_mass:make" and len(last["per_member"]) == 4
    returns = [m["eval_return_mean"] for m in last["per_member"]]
    assert all(-2 * 100 < r < 0 for r in returns)  # -distance each step, distance < 2
    code, stdout, err = main(["eval", "--run", str(out), "--episodes", "2"], capsys)
    assert code == 0 and "actor_lr=0.0003 seed=1" in stdout, err
    monkeypatch.chdir(tmp_path)  # where examples/ is not, nor on the path, nor imported
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in ("", str(REPO))])
    for name in ("examples", "examples.point_mass"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    code, _, err = main(["eval", "--run", str(out)], capsys)
    assert_one_line_error(code, err, "no module 'examples'", "--resume, eval, render and export")


CHANGING_FACTORY = """
import test_custom_envs

def make():
    return test_custom_envs.counter(low=LOW, high=3.0)
"""


@pytest.mark.runs
def test_a_changed_factory_is_noticed_by_resume_eval_and_export(tmp_path, monkeypatch, capsys):
    """config.json records the factory's sizes, bounds and time limit; after the factory's
    lower bound changes from -3 to -1, eval, export and --resume each stop with one line naming
    the difference (export would otherwise write a policy with the new bounds)."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.delitem(sys.modules, "changing", raising=False)
    (tmp_path / "changing.py").write_text(CHANGING_FACTORY.replace("LOW", "-3.0"))
    out = tmp_path / "run"
    args = ["train", "--env", "changing:make", *TINY_FLAGS, "--out", str(out)]
    code, _, err = main(args, capsys)
    assert code == 0, err
    recorded = json.loads((out / "config.json").read_text())["environment"]
    assert recorded == {"observation_size": 1, "critic_observation_size": None,
                        "action_size": 3, "action_low": [-3.0] * 3, "action_high": [3.0] * 3,
                        "episode_length": 100}  # fmt: skip
    code, _, err = main(["eval", "--run", str(out), "--episodes", "2"], capsys)
    assert code == 0, err  # unchanged: fine
    (tmp_path / "changing.py").write_text(CHANGING_FACTORY.replace("LOW", "-1.0"))
    monkeypatch.delitem(sys.modules, "changing", raising=False)
    difference = "action_low [-3.0, -3.0, -3.0] then, [-1.0, -1.0, -1.0] now"
    for command in (["eval", "--run", str(out)],
                    ["export", "--run", str(out), "--format", "npz"],
                    [*args, "--resume", "--total-steps", "384"]):  # fmt: skip
        code, _, err = main(command, capsys)
        assert_one_line_error(code, err, "changing:make makes another environment", difference)
        monkeypatch.delitem(sys.modules, "changing", raising=False)
    assert not (out / "policy.npz").exists()


def test_td3_jax_envs_says_extras_whether_each_runs_here_and_how_to_add_your_own(capsys):
    code, stdout, _ = main(["envs"], capsys)
    rows = {line.split()[0]: line.split(maxsplit=2)[1:] for line in stdout.splitlines()
            if line.strip() and " " in line.strip()}  # fmt: skip
    assert code == 0 and rows["environment"] == ["extra", "runs here"]
    assert rows["gymnax/Pendulum-v1"] == ["-", "yes"] and rows["brax/ant"] == ["-", "yes"]
    assert rows["playground/CheetahRun"][0] == "playground"
    assert rows["playground/T1JoystickFlatTerrain"][0] == "locomotion"
    assert re.search(r"^Your own environment: --env module\.path:function", stdout, re.M)


# ---------------------------------------------------------------------------------------------
# objects in the library: make_train, run.train, resume
# ---------------------------------------------------------------------------------------------


def test_make_train_takes_an_object_and_vmaps_over_seeds():
    """Two seeds of a FunctionalEnv in one program: each seed's evaluations are its own."""
    cfg = TrainConfig(**TINY)
    run = jax.jit(jax.vmap(make_train(cfg, env=drift(limit=8))))
    _, metrics = run(jnp.stack([key_for_seed(0), key_for_seed(1)]))
    returns = np.asarray(metrics["eval_returns"])
    assert returns.shape == (2, cfg.num_chunks, cfg.eval_envs)
    assert np.all(returns < 0) and np.all(returns > -8 * 4.5)  # 8 steps of -|x|^2, |x| < 1.5
    assert not np.allclose(returns[0], returns[1])


def _turning_nan(what: str) -> FunctionalEnv:
    """An environment whose rewards (``what="reward"``) or observations (``"obs"``) turn NaN
    after each environment's 10th step (4 environments: 40 env steps)."""

    def reset_counted(key):
        x = jax.random.uniform(key, (2,), minval=-1.0, maxval=1.0)
        return (x, jnp.zeros((), jnp.int32)), x

    def step_counted(state, action):
        x, count = state[0] + 0.1 * action, state[1] + 1
        reward, seen = -jnp.sum(x**2), x
        if what == "reward":
            reward = jnp.where(count > 10, jnp.nan, reward)
        else:
            seen = jnp.where(count > 10, jnp.nan, seen)
        return (x, count), seen, reward, jnp.zeros((), bool)

    return FunctionalEnv(reset_counted, step_counted, observation_size=2, action_size=2,
                         episode_length=1000, name=f"nan-{what}-later")  # fmt: skip


def _stopped_by_nan(what: str, run_dir: Path) -> str:
    """The error that stops a run of :func:`_turning_nan` ``(what)`` (warm-up of 64 steps)."""
    cfg = TrainConfig(**{**TINY, "eval_every": 32, "total_steps": 96, "warmup_steps": 64})
    with pytest.raises(errors.NonFiniteError) as info:
        train(cfg, run_dir, env=_turning_nan(what), progress=False)
    said = str(info.value)
    assert "in the chunk ending at env step 64" in said
    return said


@pytest.mark.runs
def test_nan_rewards_from_an_environment_are_named_as_its_own(tmp_path):
    """A step whose reward turns NaN after 40 env steps stops the run naming the environment's
    rewards first (the losses and values it poisons follow), not the learner alone; the
    chunk before it is recorded with its finite mean reward."""
    said = _stopped_by_nan("reward", tmp_path / "run")
    assert said.startswith("non-finite rewards from the environment (its step returned NaN or "
                           "inf)"), said  # fmt: skip
    (record,) = read_records(tmp_path / "run")
    assert record["env_steps"] == 32 and np.isfinite(record["reward_mean"])


@pytest.mark.runs
def test_nan_observations_from_an_environment_are_named_as_its_own(tmp_path):
    """Observations that turn NaN after 40 env steps (the rewards stay finite) stop the run
    naming the environment's observations first, not the learner alone."""
    said = _stopped_by_nan("obs", tmp_path / "run")
    assert said.startswith("non-finite observations from the environment (its reset or step "
                           "returned NaN or inf), critic_loss"), said  # fmt: skip


def test_a_run_of_an_object_records_it_and_resumes_only_with_it(tmp_path, capsys):
    """config.json records ``object/drift``; resuming without the object (CLI or eval) is one
    line saying what to do; with it the run goes on; no traced programs are stored."""
    out, programs = tmp_path / "run", tmp_path / "programs"
    cfg = TrainConfig(**{**TINY, "total_steps": 32})
    train(cfg, out, env=drift(limit=8), progress=False, program_dir=programs)
    assert json.loads((out / "config.json").read_text())["env"] == "object/drift"
    assert not programs.exists() or not any(programs.iterdir())
    for args in (["train", "--out", str(out), "--resume", "--total-steps", "64"],
                 ["eval", "--run", str(out)]):  # fmt: skip
        code, _, err = main(args, capsys)
        assert_one_line_error(code, err, "object/drift was handed to td3-jax as a Python object")
    with pytest.raises(
        errors.CustomEnvironmentError,
        match=r"^object/drift was handed to "
        r"td3-jax as a Python object.*: pass the object again \(env=obj",
    ):
        train(dataclasses.replace(cfg, total_steps=64), out, resume=True, progress=False)
    records = train(dataclasses.replace(cfg, total_steps=64), out, env=drift(limit=8),
                    resume=True, progress=False)  # fmt: skip
    assert [r["env_steps"] for r in records] == [64] and records[0]["env"] == "object/drift"

    # from Python, eval and export take the object too; another object is refused by name or
    # by what the policy depends on (here its action bounds), a run made by name refuses one
    from td3_jax.common.errors import ConfigError, CustomEnvironmentError
    from td3_jax.runner import finished
    from td3_jax.tools import export

    _, _, meta, returns = finished.evaluate_run(out, episodes=3, seed=0, env=drift(limit=8))
    assert returns.shape == (1, 3) and np.all(returns < 0) and meta["env_steps"] == 64
    path, policy = export.export_run(out, "npz", tmp_path / "p.npz", env=drift(limit=8))
    assert path.stat().st_size > 0 and policy.env_steps == 64
    wider = dataclasses.replace(drift(limit=8), action_high=2.0)
    with pytest.raises(
        CustomEnvironmentError, match=re.escape("action_high [1.0, 1.0] then, [2.0, 2.0] now")
    ):
        finished.evaluate_run(out, episodes=3, seed=0, env=wider)
    with pytest.raises(CustomEnvironmentError, match="another environment than the one"):
        train(dataclasses.replace(cfg, total_steps=96), out, env=wider, resume=True,
              progress=False)  # fmt: skip
    renamed = dataclasses.replace(drift(limit=8), name="other")
    with pytest.raises(ConfigError, match="trained on object/drift; the environment handed"):
        finished.evaluate_run(out, episodes=3, seed=0, env=renamed)


# ---------------------------------------------------------------------------------------------
# several devices, and the example learning
# ---------------------------------------------------------------------------------------------


@pytest.mark.processes
def test_a_factory_env_on_two_devices_gives_the_one_device_numbers(tmp_path):
    """The point mass on 2 forced CPU devices (its MJX state split over them) and on 1."""
    code = f"""
        import json, sys
        sys.path.insert(0, {str(REPO)!r})
        from td3_jax.config.schema import TrainConfig
        from td3_jax.runner.run import train
        cfg = TrainConfig(env="examples.point_mass:make", **{TINY!r})
        runs = [train(cfg, {str(tmp_path)!r} + f"/d{{d}}", devices=d, progress=False)
                for d in (1, 2)]
        print(json.dumps([[r[k] for r in run] for run in runs
                          for k in ("devices", "critic_loss", "eval_return_mean")]))
    """
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=2",
           "JAX_PLATFORMS": "cpu"}  # fmt: skip
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], env=env, cwd=tmp_path,
                          capture_output=True, text=True, timeout=600)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    one_devices, one_loss, one_return, two_devices, two_loss, two_return = json.loads(
        proc.stdout.strip().splitlines()[-1])  # fmt: skip
    assert set(one_devices) == {1} and set(two_devices) == {2}
    np.testing.assert_allclose(two_loss, one_loss, rtol=1e-3)
    np.testing.assert_allclose(two_return, one_return, rtol=1e-3)


def random_point_mass_return(episodes: int = 64, seed: int = 7) -> float:
    """The point mass's mean return under uniformly random actions, stepped here from its
    own reset and step (not through td3-jax), each episode to its termination or time limit."""
    if str(REPO) not in sys.path:  # (pytest runs from the repository's root: usually there)
        sys.path.append(str(REPO))
    from examples import point_mass

    fenv = point_mass.make()
    reset, step = jax.jit(jax.vmap(fenv.reset)), jax.jit(jax.vmap(fenv.step))
    state, _ = reset(jax.random.split(jax.random.PRNGKey(seed), episodes))
    rng = np.random.default_rng(seed)
    total, alive = np.zeros(episodes), np.ones(episodes, bool)
    for _ in range(point_mass.EPISODE_LENGTH):
        action = rng.uniform(fenv.action_low, fenv.action_high, (episodes, 2)).astype(np.float32)
        state, _, reward, terminated = step(state, jnp.asarray(action))
        total += np.where(alive, np.asarray(reward), 0.0)
        alive &= ~np.asarray(terminated)
    return float(total.mean())


@pytest.mark.slow
def test_the_example_learns_to_reach_the_target():
    """``python examples/point_mass.py`` (about a minute on 2 cores) ends with a return above
    a third of a random policy's (measured here: about -60; a policy that goes straight to
    the target gets about -8), and says it learned."""
    random_return = random_point_mass_return()
    assert -80 < random_return < -40
    proc = subprocess.run([sys.executable, str(REPO / "examples" / "point_mass.py")],
                          capture_output=True, text=True, timeout=600,
                          env=optimised_env())  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
    evaluations = re.search(r"steps: (.*) \(\d+ s\)", proc.stdout).group(1)
    returns = [float(r) for r in evaluations.split(", ")]
    assert returns[-1] > random_return / 3 and returns[-1] > returns[0]
    assert "learned" in proc.stdout


@pytest.mark.runs
def test_python_train_rounds_eval_every_as_the_cli_does_and_says_so(tmp_path, capsys):
    """4 environments: --eval-every 30 is not whole iterations; 32 (3 chunks, 96 steps) runs
    fewer steps past 90 than 28 (4 chunks, 112), and the run ends at 92, a whole iteration
    past 90 (its last chunk shortened). An eval_every past the run is lowered to it (64 steps:
    one evaluation at the end, not a chunk of 200)."""
    from td3_jax.runner import run

    cfg = TrainConfig(**{**TINY, "eval_every": 30, "total_steps": 90})
    records = train(cfg, tmp_path / "run", env=drift(limit=8), progress=True)
    assert [r["env_steps"] for r in records] == [32, 64, 92]
    out = capsys.readouterr().out
    assert "eval_every=30 runs as 32 (whole iterations of 4 env steps)" in out  # (Python's)
    longer = dataclasses.replace(cfg, eval_every=200, total_steps=64)
    assert run._eval_every_within_run(longer, tmp_path / "run", resume=True,
                                      say=True) == longer  # (kept: not the saved chunk's)
    lowered = run._eval_every_within_run(longer, tmp_path / "new", resume=False, say=True)
    assert lowered.eval_every == 64 and lowered.run_steps == 64
    assert "eval_every=200 is longer than total_steps=64" in capsys.readouterr().out


def _line_of(function, text: str) -> int:
    """The file line of ``function``'s source holding ``text``."""
    lines, first = inspect.getsourcelines(function)
    return first + next(i for i, line in enumerate(lines) if text in line)


def _einsum_step(x, action):
    x = jnp.einsum("i,ij->j", x, jnp.ones((3, 2)))  # (3 rows for 2 entries: raised in opt_einsum)
    return x, x, 0.0, False


def _parsing_step(x, action):
    return _parsed(x), x, 0.0, False


def _parsed(x):
    return x + json.loads("{not json")  # (raised in Python's json: this line is the own one)


@pytest.mark.parametrize(
    ("change", "function", "text"),
    [
        (dict(action_size=3), drift, "x = x + 0.1 * action"),  # (a shape error in JAX)
        (dict(step=_branching_step), _branching_step, "if x[0] > 0"),  # (not jittable)
        (dict(step=_einsum_step), _einsum_step, "jnp.einsum"),  # (another library's frames)
        (dict(step=_parsing_step), _parsed, "json.loads"),  # (the deepest own frame)
    ],
)
def test_a_failure_in_the_environments_own_code_names_its_line(change, function, text):
    with pytest.raises(errors.CustomEnvironmentError) as caught:
        envs.make(dataclasses.replace(drift(), **change))
    assert f" (at {__file__}:{_line_of(function, text)})" in str(caught.value)


def test_a_factory_that_raises_names_the_line(tmp_path, monkeypatch):
    (tmp_path / "my_factories.py").write_text(FACTORIES)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "my_factories", raising=False)
    line = FACTORIES.splitlines().index('    raise RuntimeError("no robot here")') + 1
    with pytest.raises(errors.CustomEnvironmentError) as caught:
        envs.make("my_factories:broken")
    assert str(caught.value) == ("my_factories:broken: calling it raised RuntimeError: no robot "
                                 f"here (at {tmp_path / 'my_factories.py'}:{line})")  # fmt: skip


IMPORTING_FACTORIES = """
from json import dumps
from td3_jax import TrainConfig

def make_arm():
    return None
"""


def test_a_package_that_re_exports_its_factories_still_gets_the_closest(tmp_path, monkeypatch):
    (tmp_path / "armpkg").mkdir()
    (tmp_path / "armpkg" / "arms.py").write_text("def make_arm():\n    return None\n")
    (tmp_path / "armpkg" / "__init__.py").write_text(
        "from json import dumps\nfrom .arms import make_arm\n\ndef register():\n    pass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    for spec, said in (("armpkg:make_arn", "did you mean 'make_arm'?"),
                       ("armpkg:zzz", "its public callables: make_arm, register")):  # fmt: skip
        with pytest.raises(errors.CustomEnvironmentError) as caught:
            envs.make(spec)
        assert str(caught.value).endswith(said), caught.value
    for name in [n for n in sys.modules if n.partition(".")[0] == "armpkg"]:
        del sys.modules[name]


def test_a_mistyped_factory_lists_what_its_module_defines_not_what_it_imported(
    tmp_path, monkeypatch
):
    (tmp_path / "importing_factories.py").write_text(IMPORTING_FACTORIES)
    (tmp_path / "only_imports.py").write_text("from json import dumps, loads\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    for name in ("importing_factories", "only_imports"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    said = {}
    for spec in ("importing_factories:nope", "only_imports:nope"):
        with pytest.raises(errors.CustomEnvironmentError) as caught:
            envs.make(spec)
        said[spec] = str(caught.value)
    assert said["importing_factories:nope"].endswith("its public callables: make_arm")
    assert said["only_imports:nope"].endswith("its public callables: dumps, loads")
