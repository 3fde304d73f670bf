"""Brax PPO, Brax SAC and td3-jax on one environment, each in a process of its own, each to its
own run length or the same wall-clock budget. The suite (:mod:`benchmarks.suite`) runs its
baselines through it.

Usage (from the project root):

  python -m benchmarks.compare --env ant --out DIR [--budget-s 120] \\
      [--algos ppo sac td3] [--td3-preset ant] [--td3-flag KEY=VALUE ...] \\
      [--ppo-flag KEY=VALUE ...] [--sac-flag KEY=VALUE ...] [--sac-recipe playground-dmc] \\
      [--num-evals 40] [--seed N] [--impl warp] [--smoke]

Environments: ``ant``, ``halfcheetah``, ``humanoid`` (Brax, MJX backend), any MuJoCo Playground
DM Control Suite task such as ``CheetahRun`` and Playground's locomotion tasks such as
``T1JoystickFlatTerrain`` (PPO only: Playground's own recipe for the task). ``--impl`` is the
physics of a Playground task: MuJoCo Warp (``warp``, Playground's default since 0.2, where the
robots' PPO runs by default) or MJX's JAX physics (``jax``, DM Control's default here).

Each algorithm runs in its own fresh Python process (spawned one after the other), so none
inherits another's compiled code or GPU memory. Its clock starts when that process starts
working (before it imports JAX or starts the GPU): imports, the accelerator's start-up,
environment creation, tracing, compilation and the evaluations are all inside the measured
wall-clock. An algorithm stops when its own run length ends, or at its first evaluation past
``--budget-s`` where one is given:

* Brax PPO / SAC (``brax.training.agents.{ppo,sac}.train.train``): ``progress_fn`` records
  ``(wall_s, num_steps, metrics["eval/episode_reward"])`` at every evaluation and raises a private
  exception once past the budget. Brax evaluates ``num_eval_envs`` (128) episodes, stochastic
  policy (Brax's default), between training epochs; ``--num-evals`` sets how many evaluations a
  full run makes (Brax's published recipes use 10 or 20, too few points inside a short budget).
* td3-jax: ``td3_jax.runner.run.train(cfg, DIR/td3_<env>, progress=False, time_budget_s=budget)``
with
  ``cfg`` = the preset (``--td3-preset``, default: the env's, cheetah-run's for Playground) with
  ``env``, ``checkpoint_every=10**9`` and ``--td3-flag`` settings. An evaluation (deterministic
  policy, ``eval_envs`` episodes) follows every chunk of ``eval_every`` steps. td3's own
  ``wall_time_s`` starts only after its environment is made, so each evaluation is stamped on
  the worker's clock instead, and the run is stopped on that clock the same way (a private
  exception raised from its metrics logger).

SAC settings: Brax publishes SAC settings only for hopper and walker2d, so for ant, halfcheetah
and humanoid ``--sac-recipe`` picks MuJoCo Playground's tuned Brax SAC config (default) or the Brax
colab's hopper entry; see ``SAC_RECIPES``.

Writes ``DIR/compare_<env>.csv`` (algorithm, env, wall_s, env_steps, eval_return,
eval_return_std), ``DIR/compare_<env>.png`` (eval return against wall-clock, one line per
algorithm), ``DIR/compare_<env>.json`` (date, device, versions, the exact settings of each
algorithm and their sources, status) and prints a table: per algorithm, the return of the last
evaluation at or before 1/4, 1/2, 3/4 and all of the budget, and the best return within it.

``--smoke`` shrinks every algorithm to a few environments and a few hundred steps, only to check
on a CPU that the code paths run; its numbers mean nothing.
"""

from __future__ import annotations

import argparse
import ast
import csv
import dataclasses
import datetime as dt
import json
import multiprocessing
import os
import platform
import sys
import time
import traceback
from importlib import metadata
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent

ALGOS = ("ppo", "sac", "td3")
BRAX_ENVS = ("ant", "halfcheetah", "humanoid")

# Brax PPO, published settings: google/brax, notebooks/training.ipynb (the Brax training colab),
# cell "Training some pre-included Brax environments", dict `train_fn` ("We determined some
# reasonable hyperparameters offline and share them here"), entries for ant, humanoid and
# halfcheetah; ppo.train's defaults for everything not listed (network sizes, clipping 0.3,
# GAE 0.95, 128 eval envs, stochastic eval).
BRAX_PPO: dict[str, dict[str, Any]] = {
    "ant": dict(
        num_timesteps=50_000_000,
        num_evals=10,
        reward_scaling=10,
        episode_length=1000,
        normalize_observations=True,
        action_repeat=1,
        unroll_length=5,
        num_minibatches=32,
        num_updates_per_batch=4,
        discounting=0.97,
        learning_rate=3e-4,
        entropy_cost=1e-2,
        num_envs=4096,
        batch_size=2048,
        seed=1,
    ),
    "humanoid": dict(
        num_timesteps=50_000_000,
        num_evals=10,
        reward_scaling=0.1,
        episode_length=1000,
        normalize_observations=True,
        action_repeat=1,
        unroll_length=10,
        num_minibatches=32,
        num_updates_per_batch=8,
        discounting=0.97,
        learning_rate=3e-4,
        entropy_cost=1e-3,
        num_envs=2048,
        batch_size=1024,
        seed=1,
    ),
    "halfcheetah": dict(
        num_timesteps=50_000_000,
        num_evals=20,
        reward_scaling=1,
        episode_length=1000,
        normalize_observations=True,
        action_repeat=1,
        unroll_length=20,
        num_minibatches=32,
        num_updates_per_batch=8,
        discounting=0.95,
        learning_rate=3e-4,
        entropy_cost=0.001,
        num_envs=2048,
        batch_size=512,
        seed=3,
    ),
}
BRAX_PPO_SOURCE = (
    "google/brax notebooks/training.ipynb (Brax training colab), train_fn dict, entry for the env"
)

# Brax SAC. The Brax colab publishes SAC settings only for hopper and walker2d (ant, humanoid and
# halfcheetah get PPO there), so there is no Brax-published SAC recipe for these environments.
# Two published recipes for brax.training's SAC on MJX, selectable with --sac-recipe:
#   playground-dmc (default): MuJoCo Playground's tuned Brax SAC config for DM Control Suite,
#     mujoco_playground/config/dm_control_suite_params.py brax_sac_config() (playground 0.2.0),
#     with the environment's episode length 1000; the Playground tasks read it from that module.
#   brax-hopper: the Brax colab's SAC entry for hopper (same notebook as BRAX_PPO).
SAC_RECIPES: dict[str, dict[str, Any]] = {
    "playground-dmc": dict(
        num_timesteps=5_000_000,
        num_evals=10,
        reward_scaling=1.0,
        episode_length=1000,
        normalize_observations=True,
        action_repeat=1,
        discounting=0.99,
        learning_rate=1e-3,
        num_envs=128,
        batch_size=512,
        grad_updates_per_step=8,
        max_replay_size=1048576 * 4,
        min_replay_size=8192,
        network_factory=dict(q_network_layer_norm=True),
    ),
    "brax-hopper": dict(
        num_timesteps=6_553_600,
        num_evals=20,
        reward_scaling=30,
        episode_length=1000,
        normalize_observations=True,
        action_repeat=1,
        discounting=0.997,
        learning_rate=6e-4,
        num_envs=128,
        batch_size=512,
        grad_updates_per_step=64,
        max_devices_per_host=1,
        max_replay_size=1048576,
        min_replay_size=8192,
        seed=1,
    ),
}
SAC_SOURCES = {
    "playground-dmc": "mujoco_playground/config/dm_control_suite_params.py brax_sac_config() "
    "(Playground's tuned Brax SAC for DM Control; no Brax-published SAC recipe for this env)",
    "brax-hopper": "google/brax notebooks/training.ipynb (Brax training colab), train_fn['hopper']",
}
# Playground's DM Control PPO config, copied from brax_ppo_config() of the same module; used only
# if the installed Playground lacks mujoco_playground.config.dm_control_suite_params.
PLAYGROUND_PPO_FALLBACK = dict(
    num_timesteps=60_000_000,
    num_evals=10,
    reward_scaling=10.0,
    episode_length=1000,
    normalize_observations=True,
    action_repeat=1,
    unroll_length=30,
    num_minibatches=32,
    num_updates_per_batch=16,
    discounting=0.995,
    learning_rate=1e-3,
    entropy_cost=1e-2,
    num_envs=2048,
    batch_size=1024,
    num_resets_per_eval=10,
)

# --smoke: a few environments and a few hundred steps, only to run every code path on a CPU.
SMOKE = {
    "ppo": dict(
        num_timesteps=1_600,
        num_evals=3,
        num_envs=8,
        batch_size=8,
        num_minibatches=2,
        unroll_length=5,
        num_updates_per_batch=2,
        episode_length=50,
        num_eval_envs=8,
    ),
    "sac": dict(
        num_timesteps=1_000,
        num_evals=3,
        num_envs=8,
        batch_size=32,
        grad_updates_per_step=1,
        min_replay_size=128,
        max_replay_size=4_096,
        episode_length=50,
        num_eval_envs=8,
    ),
    "td3": dict(
        num_envs=8,
        total_steps=800,
        eval_every=400,
        warmup_steps=100,
        batch_size=32,
        buffer_size=4_096,
        updates_per_iter=1,
        eval_envs=8,
        episode_length=50,
    ),
}

# td3-jax preset per environment (--td3-preset overrides); Playground tasks borrow halfcheetah's.
TD3_PRESET = {"ant": "ant", "halfcheetah": "halfcheetah", "humanoid": "humanoid"}
TD3_PRESET_DEFAULT = "cheetah-run"


def default_td3_preset(env: str) -> str:
    """The td3-jax preset an environment is compared with: its own (ant, t1, ...), a robot's
    family preset for other locomotion tasks, else cheetah-run's (DM Control Suite)."""
    from td3_jax.config import presets

    name = env_id(env)
    return (
        TD3_PRESET.get(env)
        or presets.env_preset(name)
        or presets.robot_preset(name)
        or (TD3_PRESET_DEFAULT)
    )


TIME_ZERO = (
    "just before the environment is created and the train function is called, in a fresh "
    "process: environment creation, tracing, compilation and evaluations are all included"
)


class _BudgetReached(Exception):
    """Raised from a Brax progress_fn to stop training once the wall-clock budget has passed."""


# --------------------------------------------------------------------------------------------
# Settings
# --------------------------------------------------------------------------------------------


def parse_flags(items: list[str] | None, what: str) -> dict[str, str]:
    """``["KEY=VALUE", ...]`` as a dict of strings (values are converted later)."""
    flags = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise SystemExit(f"{what}: expected KEY=VALUE, got {item!r}")
        flags[key.strip().replace("-", "_")] = value.strip()
    return flags


def literal(value: str) -> Any:
    """A Python literal (``50_000_000``, ``3e-4``, ``True``, ``(256, 256)``), else the string."""
    try:
        return ast.literal_eval(value)
    except (ValueError, SyntaxError):
        return value


def td3_overrides(flags: dict[str, str]) -> dict[str, Any]:
    """--td3-flag values converted to the types of td3_jax.config.schema.TrainConfig's fields."""
    from td3_jax.config.schema import TrainConfig

    fields = {f.name: str(f.type) for f in dataclasses.fields(TrainConfig)}
    out: dict[str, Any] = {}
    for key, raw in flags.items():
        if key not in fields:
            raise SystemExit(f"--td3-flag: unknown setting {key!r}; known: {', '.join(fields)}")
        kind = fields[key]
        if raw.lower() == "none" and "None" in kind:
            out[key] = None
        elif kind.startswith("Literal"):  # a choice of strings (e.g. precision=bfloat16)
            out[key] = raw
        elif "tuple" in kind:
            out[key] = tuple(int(v) for v in raw.replace(",", " ").split())
        elif kind.startswith("bool"):
            if raw.lower() not in ("true", "false", "1", "0"):
                raise SystemExit(f"--td3-flag {key}: expected true or false, got {raw!r}")
            out[key] = raw.lower() in ("true", "1")
        elif "float" in kind:
            out[key] = float(raw)
        elif "int" in kind:
            number = float(raw.replace("_", ""))
            if number != int(number):
                raise SystemExit(f"--td3-flag {key}: expected an integer, got {raw!r}")
            out[key] = int(number)
        else:
            out[key] = raw
    return out


def is_brax_env(env: str) -> bool:
    return env in BRAX_ENVS


def is_locomotion_env(env: str) -> bool:
    """A MuJoCo Playground locomotion task (a robot from MuJoCo Menagerie)."""
    from td3_jax.envs import locomotion

    return env in locomotion.names()


def env_id(env: str) -> str:
    """td3-jax's name of the environment."""
    return f"brax/{env}" if is_brax_env(env) else f"playground/{env}"


# --------------------------------------------------------------------------------------------
# Workers (each runs in a fresh spawned process)
# --------------------------------------------------------------------------------------------


def _device() -> dict[str, Any]:
    import jax

    device = jax.devices()[0]
    return {
        "platform": device.platform,
        "device_kind": device.device_kind,
        "device_count": jax.device_count(),
    }


def _announce(algo: str, source: str, settings: dict[str, Any]) -> None:
    listing = " ".join(f"{k}={v}" for k, v in settings.items())
    print(f"[{algo}] settings from {source}: {listing}", flush=True)


def _brax_settings(job: dict[str, Any]) -> tuple[dict[str, Any], str]:
    """The keyword arguments of ppo.train / sac.train for this job, and where they come from."""
    algo, env = job["algo"], job["env"]
    if is_brax_env(env):
        if algo == "ppo":
            settings, source = dict(BRAX_PPO[env]), BRAX_PPO_SOURCE
        else:
            settings = dict(SAC_RECIPES[job["sac_recipe"]])
            source = SAC_SOURCES[job["sac_recipe"]]
    elif is_locomotion_env(env):
        if algo != "ppo":
            raise SystemExit(f"{algo} has no Playground locomotion settings; use ppo or td3")
        from mujoco_playground.config import locomotion_params

        settings = locomotion_params.brax_ppo_config(env).to_dict()
        source = (
            f"mujoco_playground.config.locomotion_params.brax_ppo_config({env!r}) "
            f"(playground {_version('playground')})"
        )
    else:
        try:
            from mujoco_playground.config import dm_control_suite_params as params

            config = (params.brax_ppo_config if algo == "ppo" else params.brax_sac_config)(env)
            settings = config.to_dict()
            source = (
                f"mujoco_playground.config.dm_control_suite_params.brax_{algo}_config({env!r}) "
                f"(playground {_version('playground')})"
            )
        except ImportError:
            settings = dict(
                PLAYGROUND_PPO_FALLBACK if algo == "ppo" else SAC_RECIPES["playground-dmc"]
            )
            source = "copy of Playground's DM Control config (module not installed)"
    published = dict(settings)
    if job["num_evals"] is not None:
        settings["num_evals"] = job["num_evals"]
    if job["smoke"]:
        settings.update(SMOKE[algo])
    if job["seed"] is not None:
        settings["seed"] = job["seed"]
    settings.update({k: literal(v) for k, v in job["flags"].items()})
    return {"published": published, "used": settings}, source


def _brax_train_kwargs(algo: str, used: dict[str, Any]) -> tuple[Any, dict[str, Any]]:
    """``(brax.training module of algo, its train() keyword arguments)`` from the settings
    (``network_factory`` turned into the factory function)."""
    import functools

    kwargs = dict(used)
    if algo == "ppo":
        from brax.training.agents.ppo import networks as nets
        from brax.training.agents.ppo import train as agent

        make_networks = nets.make_ppo_networks
    else:
        from brax.training.agents.sac import networks as nets
        from brax.training.agents.sac import train as agent

        make_networks = nets.make_sac_networks
        # Playground's SAC config has num_resets_per_eval, which sac.train does not take.
        kwargs.pop("num_resets_per_eval", None)
    factory = kwargs.pop("network_factory", None)
    if factory:
        kwargs["network_factory"] = functools.partial(make_networks, **dict(factory))
    return agent, kwargs


def _run_brax(job: dict[str, Any], result: dict[str, Any]) -> None:
    from benchmarks import brax_shim

    result["shimmed"] = brax_shim.install()
    import numpy as np

    algo, env_name, budget = job["algo"], job["env"], job["budget_s"]
    settings, source = _brax_settings(job)
    result["settings"], result["source"] = settings, source
    _announce(algo, source, settings["used"])
    agent, kwargs = _brax_train_kwargs(algo, settings["used"])
    rows = result["rows"]

    def progress(num_steps, metrics):
        wall = time.perf_counter() - start
        ret = float(np.asarray(metrics["eval/episode_reward"]))
        std = metrics.get("eval/episode_reward_std")
        rows.append(
            dict(
                wall_s=wall,
                env_steps=int(num_steps),
                eval_return=ret,
                eval_return_std=None if std is None else float(np.asarray(std)),
            )
        )
        print(f"[{algo}] {wall:7.1f} s  {int(num_steps):>12,} steps  return {ret:9.1f}", flush=True)
        if budget is not None and wall >= budget:
            raise _BudgetReached

    start = job["launch"]
    if is_brax_env(env_name):
        from brax import envs

        environment = envs.get_environment(env_name, backend="mjx")
    else:
        from mujoco_playground import wrapper

        environment = _playground_env(env_name, job["impl"], settings["used"], result)
        if not hasattr(wrapper, "wrap_for_brax_training"):
            raise RuntimeError("this Playground has no wrapper.wrap_for_brax_training")
        kwargs["wrap_env_fn"] = wrapper.wrap_for_brax_training
    try:
        agent.train(environment=environment, progress_fn=progress, **kwargs)
        result["stopped_by"] = "run length"
    except _BudgetReached:
        result["stopped_by"] = "budget"
    result["wall_s_total"] = time.perf_counter() - start


def _playground_env(env_name: str, impl: str, used: dict[str, Any],
                    result: dict[str, Any]) -> Any:  # fmt: skip
    """A Playground task for Brax PPO/SAC on the physics ``impl``: DM Control Suite as
    Playground loads it; a locomotion task built as td3-jax builds it (offline Menagerie
    assets, pushes off as in the td3-jax presets and FastTD3's published runs, no domain
    randomisation, the task's own Warp buffers for the recipe's ``num_envs``)."""
    if not is_locomotion_env(env_name):
        from mujoco_playground import dm_control_suite

        return dm_control_suite.load(env_name, config_overrides={"impl": impl})
    from td3_jax.envs import locomotion
    from td3_jax.envs.base import EnvOptions

    worlds = max(int(used.get("num_envs", 1)), int(used.get("num_eval_envs", 128)))
    options = EnvOptions(pushes=False, impl=impl, worlds=worlds)
    environment, _ = locomotion.load(env_name, impl=impl, options=options)
    result["env_config"] = {"impl": impl, "pushes": "off", "domain_randomization": False}
    return environment


def td3_config(job: dict[str, Any]):
    """The td3-jax TrainConfig of a job (validated) and the settings changed from the preset."""
    from td3_jax.config import presets
    from td3_jax.config import schema as td3_config

    overrides: dict[str, Any] = {} if is_brax_env(job["env"]) else {"impl": job.get("impl")}
    if job["smoke"]:
        overrides.update(SMOKE["td3"])
    if job["seed"] is not None:
        overrides["seed"] = job["seed"]
    overrides.update(td3_overrides(job["flags"]))
    try:
        cfg = dataclasses.replace(
            presets.preset(job["td3_preset"]),
            env=env_id(job["env"]),
            checkpoint_every=10**9,
            **overrides,
        )
        return td3_config.validate(cfg), overrides
    except td3_config.ConfigError as err:
        raise SystemExit(f"td3-jax settings: {err}") from err


def _run_td3(job: dict[str, Any], result: dict[str, Any]) -> None:
    from td3_jax.runner import run as td3_run

    cfg, overrides = td3_config(job)
    result["settings"] = {"preset": job["td3_preset"], "used": dataclasses.asdict(cfg)}
    result["source"] = f"td3_jax.config.presets.PRESETS[{job['td3_preset']!r}] + flags"
    _announce("td3", result["source"], {"env": cfg.env, **overrides})
    run_dir = Path(job["out"]) / f"td3_{job['env']}"
    if run_dir.exists():
        run_dir = run_dir.with_name(f"{run_dir.name}_{time.strftime('%Y%m%d-%H%M%S')}")
    result["run_dir"] = str(run_dir)

    # td3's own wall_time_s starts only after its environment is made. Stamp every evaluation
    # with this process's clock instead, started at the worker's launch like the Brax runs, and
    # stop on that clock: raise from the logger once past the budget, as the Brax runs raise
    # from progress_fn.
    budget, rows = job["budget_s"], result["rows"]

    class StampedLogger(td3_run.MetricsLogger):
        def write(self, record):
            wall = time.perf_counter() - start
            record["compare_wall_s"] = wall
            out = super().write(record)
            steps, ret = int(record["env_steps"]), float(record["eval_return_mean"])
            rows.append(
                dict(
                    wall_s=wall,
                    env_steps=steps,
                    eval_return=ret,
                    eval_return_std=float(record["eval_return_std"]),
                    td3_wall_time_s=float(record["wall_time_s"]),
                )
            )
            print(f"[td3] {wall:7.1f} s  {steps:>12,} steps  return {ret:9.1f}", flush=True)
            if budget is not None and wall >= budget and not keep:
                raise _BudgetReached
            return out

    td3_run.MetricsLogger = StampedLogger
    start = job["launch"]
    # --td3-checkpoint: the run stops on its own clock (which starts after the environment is
    # made, so it ends up to one chunk plus environment creation past the budget) and saves a
    # checkpoint, for td3-jax render/export afterwards; evaluations past the budget are kept in
    # the CSV but not counted in the table.
    keep = job.get("td3_checkpoint", False)
    own_budget = budget - (time.perf_counter() - start) if keep and budget else budget
    try:
        td3_run.train(cfg, run_dir, progress=False, time_budget_s=own_budget)
        result["stopped_by"] = "budget, checkpointed" if keep else "run length"
    except _BudgetReached:
        result["stopped_by"] = "budget"
    result["wall_s_total"] = time.perf_counter() - start


def _worker(job: dict[str, Any]) -> None:
    """Runs one algorithm and writes its result JSON (also when it fails)."""
    job = {**job, "launch": time.perf_counter()}  # every clock starts at the worker's launch
    result: dict[str, Any] = {"algo": job["algo"], "rows": [], "status": "ok"}
    try:
        result["device"] = _device()
        (_run_td3 if job["algo"] == "td3" else _run_brax)(job, result)
    except BaseException as err:  # report every failure, then exit non-zero
        result["status"] = "failed"
        result["error"] = f"{type(err).__name__}: {err}"
        result["traceback"] = traceback.format_exc()
        print(f"[{job['algo']}] FAILED: {result['error']}", flush=True)
    Path(job["result_path"]).write_text(json.dumps(result, indent=2, default=str) + "\n")
    if result["status"] != "ok":
        sys.exit(1)


# --------------------------------------------------------------------------------------------
# Output
# --------------------------------------------------------------------------------------------


def _version(name: str) -> str | None:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def versions() -> dict[str, Any]:
    names = ["jax", "jaxlib", "brax", "mujoco", "mujoco-mjx", "playground", "flax", "optax"]
    found = {n: _version(n) for n in names}
    found["td3-jax"] = _version("td3-jax")
    found["python"] = platform.python_version()
    return found


def write_csv(path: Path, env: str, results: dict[str, dict]) -> None:
    with path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(
            ["algorithm", "env", "wall_s", "env_steps", "eval_return", "eval_return_std"]
        )
        for algo, result in results.items():
            for row in result["rows"]:
                std = row.get("eval_return_std")
                writer.writerow(
                    [
                        algo,
                        env,
                        f"{row['wall_s']:.3f}",
                        row["env_steps"],
                        f"{row['eval_return']:.4f}",
                        "" if std is None else f"{std:.4f}",
                    ]
                )


PUBLISHED = HERE / "published" / "fasttd3_playground.csv"


def published_curves(env: str, path: Path = PUBLISHED) -> dict[str, list[tuple[float, float]]]:
    """``{algorithm: [(wall_s, eval_return), ...]}`` published for ``env`` (FastTD3's A100
    curves, see benchmarks/published/README.md); the (0, 0) placeholders are left out."""
    curves: dict[str, list[tuple[float, float]]] = {}
    if not path.exists():
        return curves
    with path.open() as f:
        for row in csv.DictReader(f):
            minutes, ret = float(row["wall_clock_min"]), float(row["eval_return_mean"])
            if row["task"] == env and (minutes, ret) != (0.0, 0.0):
                curves.setdefault(row["algorithm"], []).append((minutes * 60, ret))
    return curves


def published_at(curve: list[tuple[float, float]], t: float) -> float | None:
    """The published return linearly interpolated at ``t`` seconds (``None`` outside)."""
    import numpy as np

    times, returns = zip(*curve, strict=True)
    if not times[0] <= t <= times[-1]:
        return None
    return float(np.interp(t, times, returns))


def plot(path: Path, env: str, budget: float | None, span: float, results: dict[str, dict],
         device: str) -> None:  # fmt: skip
    """Return against wall-clock, one line per algorithm, FastTD3's published curves up to
    3.5 times ``span`` (the budget, else the longest run), the budget where one was given."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = {"ppo": "Brax PPO", "sac": "Brax SAC", "td3": "td3-jax TD3"}
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for algo, result in results.items():
        rows = result["rows"]
        if rows:
            ax.plot(
                [r["wall_s"] for r in rows],
                [r["eval_return"] for r in rows],
                marker="o",
                markersize=3,
                label=labels.get(algo, algo),
            )
    for algo, curve in published_curves(env).items():
        shown = [(t, r) for t, r in curve if t <= span * 3.5]
        if shown:
            ax.plot(*zip(*shown, strict=True), linestyle=":", marker="x", markersize=4,
                    label=f"{algo} (published, A100)")  # fmt: skip
    if budget:
        ax.axvline(budget, color="grey", linestyle="--", linewidth=1, label=f"budget {budget:g} s")
    ax.set_xlabel("wall-clock s (start-up and compile included)")
    ax.set_ylabel("eval episode return")
    ax.set_title(f"{env} on {device}")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def time_points(budget: float) -> list[float]:
    return [budget * f for f in (0.25, 0.5, 0.75, 1.0)]


def at_or_before(rows: list[dict], t: float) -> dict | None:
    before = [r for r in rows if r["wall_s"] <= t]
    return before[-1] if before else None


def steady_rate(rows: list[dict]) -> float | None:
    """Env steps/s between the second and the last evaluation (a program's start-up and first
    compiles excluded; ``None`` with fewer than three evaluations)."""
    rows = sorted(rows, key=lambda r: r["wall_s"])
    if len(rows) < 3 or rows[-1]["wall_s"] <= rows[1]["wall_s"]:
        return None
    return (rows[-1]["env_steps"] - rows[1]["env_steps"]) / (rows[-1]["wall_s"] - rows[1]["wall_s"])


def table_from_first(results: dict[str, dict], budget: float) -> str:
    """Each algorithm's return at the same times counted from its own first evaluation (its
    start-up set aside), and its steady env steps/s."""
    points = time_points(budget)
    head = ["algorithm", "first eval s", *(f"first +{p:g} s" for p in points), "steady env steps/s"]
    lines = ["| " + " | ".join(head) + " |", "| --- |" + " ---: |" * (len(head) - 1)]
    for algo, result in results.items():
        rows = sorted(result["rows"], key=lambda r: r["wall_s"])
        if not rows:
            continue
        first = rows[0]["wall_s"]
        shifted = [{**r, "wall_s": r["wall_s"] - first} for r in rows]
        cells = [algo, f"{first:.1f}"]
        for p in points:
            row = at_or_before(shifted, p)
            cells.append("-" if row is None else f"{row['eval_return']:.1f}")
        rate = steady_rate(rows)
        cells.append("-" if rate is None else f"{rate:,.0f}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def table(results: dict[str, dict], budget: float) -> str:
    points = time_points(budget)
    head = ["algorithm", "first eval s"] + [f"@{p:g} s" for p in points]
    head += ["best (s)", "steps @budget"]
    lines = ["| " + " | ".join(head) + " |", "| --- |" + " ---: |" * (len(head) - 1)]
    for algo, result in results.items():
        rows = sorted(result["rows"], key=lambda r: r["wall_s"])
        cells = [algo]
        if result["status"] != "ok" and not rows:
            cells += ["failed"] + [""] * (len(head) - 2)
            lines.append("| " + " | ".join(cells) + " |")
            continue
        cells.append(f"{rows[0]['wall_s']:.1f}" if rows else "-")
        for p in points:
            row = at_or_before(rows, p)
            cells.append("-" if row is None else f"{row['eval_return']:.1f}")
        within = [r for r in rows if r["wall_s"] <= budget]
        if within:
            best = max(within, key=lambda r: r["eval_return"])
            cells.append(f"{best['eval_return']:.1f} ({best['wall_s']:.0f})")
            cells.append(f"{within[-1]['env_steps']:,}")
        else:
            cells += ["-", "-"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Main
# --------------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    """The command line (see the module docstring)."""
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--env", required=True, help="ant, halfcheetah, humanoid or CheetahRun")
    parser.add_argument("--budget-s", type=float, default=None,
                        help="wall-clock per algorithm (default: each to its own run length)")
    parser.add_argument("--impl", choices=("warp", "jax"), default=None,
                        help="a Playground task's physics (default: warp for the locomotion "
                        "tasks, jax for DM Control)")  # fmt: skip
    parser.add_argument("--out", type=Path, required=True, help="output directory")
    parser.add_argument("--algos", nargs="+", choices=ALGOS, default=list(ALGOS))
    parser.add_argument("--td3-preset", default=None, help="td3-jax preset (default: per env)")
    parser.add_argument(
        "--td3-flag",
        action="extend",
        nargs="+",
        default=[],
        help="td3-jax TrainConfig KEY=VALUE ...",
    )
    parser.add_argument(
        "--ppo-flag", action="extend", nargs="+", default=[], help="brax ppo.train KEY=VALUE ..."
    )
    parser.add_argument(
        "--sac-flag", action="extend", nargs="+", default=[], help="brax sac.train KEY=VALUE ..."
    )
    parser.add_argument(
        "--sac-recipe",
        choices=sorted(SAC_RECIPES),
        default="playground-dmc",
        help="SAC settings for the Brax envs (Brax publishes none for them; see the source)",
    )
    parser.add_argument(
        "--num-evals",
        type=int,
        default=40,
        help="evaluations over a whole Brax PPO/SAC run (0: keep the published number)",
    )
    parser.add_argument("--seed", type=int, default=None, help="seed of every algorithm")
    parser.add_argument(
        "--td3-checkpoint",
        action="store_true",
        help="td3-jax stops on its own clock and keeps a checkpoint (for render/export)",
    )
    parser.add_argument("--smoke", action="store_true", help="tiny sizes: a CPU code-path check")
    parser.add_argument(
        "--merge",
        action="store_true",
        help="run nothing: write the CSV, plot, JSON and table from every algorithm's result in "
        "OUT (from earlier calls with --algos subsets, e.g. side by side on the GPUs of one host)",
    )
    return parser


def resolve_env(parser: argparse.ArgumentParser, name: str) -> str:
    """The environment's name as the workers take it (``ant``, ``CheetahRun``, ...), or a
    parser error naming the known ones."""
    env = name.removeprefix("brax/").removeprefix("playground/")
    if env.lower() in BRAX_ENVS:
        return env.lower()
    # importing Playground does not start a JAX backend (the workers own the GPU)
    from mujoco_playground import dm_control_suite

    if env not in dm_control_suite.ALL_ENVS and not is_locomotion_env(env):
        known = ", ".join([*BRAX_ENVS, *sorted(dm_control_suite.ALL_ENVS)])
        parser.error(f"unknown environment {name!r}; known: {known} and Playground's "
                     "locomotion tasks (td3-jax envs)")  # fmt: skip
    return env


def run_algo(job: dict[str, Any], context: Any) -> dict[str, Any]:
    """Runs one algorithm's job in a fresh spawned process; its result (a failure record when
    the process left none)."""
    result_path = Path(job["result_path"])
    result_path.unlink(missing_ok=True)
    limit = f"budget {job['budget_s']:g} s" if job["budget_s"] else "to its own run length"
    print(f"== {job['algo']} on {job['env']}, {limit}", flush=True)
    process = context.Process(target=_worker, args=(job,), name=f"compare-{job['algo']}")
    process.start()
    process.join()
    if result_path.exists():
        return json.loads(result_path.read_text())
    error = f"worker process ended with exit code {process.exitcode} and no result"
    print(f"[{job['algo']}] FAILED: {error}", flush=True)
    return {"algo": job["algo"], "rows": [], "status": "failed", "error": error}


def merged_results(parser: argparse.ArgumentParser, parts: Path) -> dict[str, dict]:
    """The results earlier calls left in ``parts`` (--merge)."""
    results = {algo: json.loads((parts / f"{algo}.json").read_text())
               for algo in ALGOS if (parts / f"{algo}.json").exists()}  # fmt: skip
    if not results:
        parser.error(f"--merge: no results in {parts}")
    return results


def summary_record(args: argparse.Namespace, env: str, results: dict[str, dict],
                   started: dt.datetime) -> dict[str, Any]:  # fmt: skip
    """The JSON summary: date, command, device, versions and each algorithm's settings."""
    devices = [r["device"] for r in results.values() if r.get("device")]
    budget = args.budget_s or float("inf")
    within = lambda rows: sum(r["wall_s"] <= budget for r in rows)
    return {
        "date": started.isoformat(timespec="seconds"),
        "command": [Path(sys.executable).name, *sys.argv],
        "env": env, "budget_s": args.budget_s, "smoke": args.smoke, "time_zero": TIME_ZERO,
        "device": devices[0] if devices else None,
        "host": {"machine": platform.machine(), "cpus": os.cpu_count()},
        "versions": versions(),
        "algorithms": {
            algo: {key: value for key, value in result.items() if key not in ("rows", "algo")}
            | {"evals": len(result["rows"]), "evals_within_budget": within(result["rows"]),
               "first_eval_s": min((r["wall_s"] for r in result["rows"]), default=None),
               "steady_env_steps_per_s": steady_rate(result["rows"])}
            for algo, result in results.items()
        },
    }  # fmt: skip


def span_of(budget: float | None, results: dict[str, dict]) -> float:
    """The wall-clock the tables cover: the budget, else the longest run's last evaluation."""
    walls = [r["wall_s"] for result in results.values() for r in result["rows"]]
    return budget or max(walls, default=1.0)


def print_report(args: argparse.Namespace, env: str, results: dict[str, dict], device: str,
                 stem: Path) -> None:  # fmt: skip
    """The table, the published curves at the same times and what was written."""
    span = span_of(args.budget_s, results)
    limit = f"budget {args.budget_s:g} s" if args.budget_s else "each to its own run length"
    print()
    print(f"{env}, {limit}, {device}" + (" (SMOKE)" if args.smoke else ""))
    print("eval return of the last evaluation at or before each time (compile included):")
    print(table(results, span))
    print(
        "the same, counted from each algorithm's first evaluation (start-up set aside), and "
        "its steady rate (from its second evaluation on):"
    )
    print(table_from_first(results, span))
    points = time_points(span)
    for algo, curve in published_curves(env).items():
        values = [published_at(curve, t) for t in points]
        cells = ", ".join(f"@{t:g} s {'-' if v is None else f'{v:.1f}'}"
                          for t, v in zip(points, values, strict=True))  # fmt: skip
        print(f"published {algo} (A100, interpolated): {cells}")
    for name in (".csv", ".png", ".json"):
        print(f"wrote {stem.with_suffix(name)}")
    for algo, result in results.items():
        if result["status"] != "ok":
            print(f"{algo} failed: {result.get('error')}")


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    env = resolve_env(parser, args.env)
    if args.budget_s is not None and args.budget_s <= 0:
        parser.error("--budget-s must be positive")
    impl = args.impl or ("warp" if is_locomotion_env(env) else "jax")
    flags = {algo: parse_flags(getattr(args, f"{algo}_flag"), f"--{algo}-flag")
             for algo in ("ppo", "sac", "td3")}  # fmt: skip
    td3_preset = args.td3_preset or default_td3_preset(env)
    if "td3" in args.algos:  # bad td3 settings fail here, before any run starts
        td3_config(dict(env=env, smoke=args.smoke, seed=args.seed, flags=flags["td3"],
                        td3_preset=td3_preset, impl=impl))  # fmt: skip
    parts = args.out / f"compare_{env}_parts"
    parts.mkdir(parents=True, exist_ok=True)
    started = dt.datetime.now(dt.UTC)
    context = multiprocessing.get_context("spawn")
    results = merged_results(parser, parts) if args.merge else {}
    for algo in [] if args.merge else args.algos:
        job = dict(algo=algo, env=env, budget_s=args.budget_s, smoke=args.smoke, seed=args.seed,
                   flags=flags[algo], num_evals=args.num_evals or None,
                   sac_recipe=args.sac_recipe, td3_preset=td3_preset, impl=impl,
                   td3_checkpoint=args.td3_checkpoint, out=str(args.out),
                   result_path=str(parts / f"{algo}.json"))  # fmt: skip
        results[algo] = run_algo(job, context)
    summary = summary_record(args, env, results, started)
    device = summary["device"]["device_kind"] if summary["device"] else "unknown device"
    stem = args.out / f"compare_{env}"
    write_csv(stem.with_suffix(".csv"), env, results)
    plot(stem.with_suffix(".png"), env, args.budget_s, span_of(args.budget_s, results), results,
         device)
    stem.with_suffix(".json").write_text(json.dumps(summary, indent=2, default=str) + "\n")
    print_report(args, env, results, device, stem)
    return 1 if any(r["status"] != "ok" for r in results.values()) else 0


if __name__ == "__main__":
    sys.exit(main())
