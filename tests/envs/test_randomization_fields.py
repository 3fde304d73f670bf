"""Domain randomisation on MuJoCo Warp is refused, not silently skipped, when a task's
randomiser draws a model field that Warp simulates as one value for every world; and the
canary for MJX's Warp table of per-world fields that the check reads."""

from __future__ import annotations

import jax
import pytest

from td3_jax.common import upstream
from td3_jax.envs import locomotion
from td3_jax.envs.base import EnvironmentOptionError, EnvOptions, refuse_locomotion_options

mjx = pytest.importorskip("mujoco.mjx")
mujoco = pytest.importorskip("mujoco")

_XML = '<mujoco><worldbody><body><joint/><geom size="1"/></body></worldbody></mujoco>'


def _randomization(*fields: str) -> locomotion.Randomization:
    """A Randomization of a one-body MJX model drawing ``fields`` (paths as keystr spells them
    without the leading dot), found by name among the model's leaves."""
    model = mjx.put_model(mujoco.MjModel.from_xml_string(_XML))
    paths = [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_flatten_with_path(model)[0]]
    leaves = tuple(paths.index("." + name) for name in fields)
    return locomotion.Randomization(randomizer=None, model=model, leaves=leaves)


def test_the_names_of_the_drawn_fields_are_the_models_field_paths():
    rand = _randomization("body_mass", "opt.gravity", "geom_friction")
    assert locomotion.randomized_field_names(rand) == ("body_mass", "opt.gravity", "geom_friction")


def test_a_field_warp_shares_between_worlds_is_refused_by_name():
    rand = _randomization("body_mass", "opt.gravity")
    with pytest.raises(EnvironmentOptionError) as err:
        locomotion.check_warp_randomization("T", rand, frozenset({"body_mass"}))
    message = str(err.value)
    assert "opt.gravity" in message and "body_mass" not in message
    assert "--impl jax" in message and "playground/T" in message


def test_fields_warp_keeps_per_world_pass():
    rand = _randomization("body_mass", "geom_friction")
    locomotion.check_warp_randomization("T", rand, frozenset({"body_mass", "geom_friction"}))


def test_mjx_warp_lists_the_fields_playground_randomisers_draw_as_per_world():
    """Canary for ``mujoco.mjx.warp.types._BATCH_DIM``: the fields the T1, G1 and Go1
    randomisers of Playground 0.2.0 draw are per-world there, the model's index tables are not."""
    pytest.importorskip("mujoco.mjx.warp.types")
    per_world = upstream.warp_per_world_model_fields()
    drawn = {"body_mass", "body_ipos", "geom_friction", "pair_friction", "qpos0", "dof_armature",
             "dof_damping", "dof_frictionloss", "actuator_gainprm", "actuator_biasprm"}  # fmt: skip
    assert drawn <= per_world, f"no longer per world: {sorted(drawn - per_world)}"
    assert not {"actuator_trntype", "dof_jntid", "body_parentid"} & per_world


@pytest.mark.parametrize(
    ("options", "said"),
    [
        (dict(domain_randomization=True), "--domain-randomization applies to"),
        (dict(pushes=False), "--no-pushes applies to"),
        (dict(domain_randomization=True, pushes=True), "--domain-randomization, --pushes apply to"),
    ],
)
def test_locomotion_options_refused_elsewhere_are_named_in_one_sentence(options, said):
    with pytest.raises(EnvironmentOptionError) as err:
        refuse_locomotion_options("brax/ant", EnvOptions(**options))
    assert str(err.value) == f"{said} Playground's locomotion tasks, not brax/ant"
    refuse_locomotion_options("brax/ant", EnvOptions())  # (nothing set: nothing refused)
