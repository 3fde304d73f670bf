"""Where a train command's settings come from before its flags apply: the run's own
config.json (``--resume``), ``--preset``, the preset made for ``--env``, else the device's
defaults; then what the device and the installation decide (an accelerator's sizes, the
physics of a Playground task)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from td3_jax.cli.argv import flag_value, given_fields
from td3_jax.cli.run_folder import RESUME_NEEDS_OUT
from td3_jax.config.presets import device_defaults, env_preset, preset
from td3_jax.config.schema import ConfigError, TrainConfig

__all__ = ["base_config", "choose_physics", "resumed_settings", "scale_to_device"]


def base_config(args: list[str]) -> tuple[TrainConfig, str | None, str]:
    """``(defaults, preset, source)`` for the train flags ``args``, ``source`` saying where
    they come from: ``resume`` (the run's saved config.json), ``preset`` (--preset), ``env``
    (the preset made for --env) or ``device`` (an environment without a preset:
    :func:`device_defaults`, the CPU ones here; :func:`scale_to_device` swaps in the
    accelerator's once JAX is up)."""
    from td3_jax.runner.rundir import CONFIG_FILE, load_config  # lazy: imports JAX

    out = flag_value(args, "--out")
    name = flag_value(args, "--preset")
    if "--resume" in args:
        if not out:  # (the command names it: run_folder.with_run_directory; --help shows
            if {"-h", "--help"} & set(args):  # the flags over the defaults)
                return TrainConfig(), None, "resume"
            raise ConfigError(RESUME_NEEDS_OUT)
        if name:
            _check_resumed_preset(name, Path(out))
        if (Path(out) / CONFIG_FILE).exists():
            return load_config(Path(out)), None, "resume"
        return TrainConfig(), None, "resume"  # (train() says there is nothing to resume)
    if name:
        return preset(name), name, "preset"  # ConfigError naming the closest for an unknown one
    env = flag_value(args, "--env") or TrainConfig.env
    name = env_preset(env)
    if name:
        return dataclasses.replace(preset(name), env=env), name, "env"
    return device_defaults(env, accelerator=False), None, "device"


def _check_resumed_preset(name: str, out: Path) -> None:
    """A resume keeps its run's config: ``--preset`` may only name the preset the run was
    started from (so the command that started it, plus ``--resume``, resumes it)."""
    from td3_jax.runner.rundir import load_run_info  # lazy: imports JAX

    try:
        started = load_run_info(out).get("preset")
    except Exception:  # (no or an unreadable config.json: train() says what is wrong)
        return
    if started != name:
        was = f"--preset {started}" if started else "no preset"
        raise ConfigError(f"--preset {name} given but the run was started with {was}; a resume "
                          "keeps its run's config (leave --preset out)")  # fmt: skip


def resumed_settings(cfg: TrainConfig, out: Path) -> TrainConfig:
    """``cfg`` for a --resume of ``out``: an --eval-every given as the run was started (3000,
    which the fresh run took as the whole iterations of 3008) is the saved one; and, where the
    run is not in use and has a checkpoint, a flag that the resume may not change is refused
    before the settings' own checks, whose advice (``try --batch-size 256``) would name a
    change that the resume then refuses (:func:`td3_jax.runner.rundir.config_changes`)."""
    from td3_jax.runner import rundir  # lazy: imports JAX

    if not (out / rundir.CONFIG_FILE).exists():
        return cfg  # (the run says there is nothing to resume)
    saved = rundir.load_config(out)
    cfg = rundir.eval_every_as_saved(cfg, saved)
    import jax  # lazy: JAX, only for a run

    if jax.process_index() == 0:  # (as the resume itself checks first, in its writer only)
        rundir.check_not_in_use(out)
    if rundir.checkpoint_steps(out):
        rundir.config_changes(saved, cfg, rundir.load_members(out, cfg))
    return cfg


def scale_to_device(cfg: TrainConfig, args: list[str]) -> TrainConfig:
    """An environment without a preset on an accelerator: its defaults, then the given flags
    ``args`` (``cfg`` unchanged on a CPU)."""
    import jax  # lazy: JAX, only for a run

    if jax.default_backend() == "cpu":
        return cfg
    base = device_defaults(cfg.env, accelerator=True)
    return dataclasses.replace(base, **{n: getattr(cfg, n) for n in given_fields(args)})


def choose_physics(cfg: TrainConfig, devices: int | None) -> tuple[TrainConfig, int | None]:
    """A Playground task's physics (``--impl``; default: MuJoCo Warp where it can run) and the
    device count, said in one line; ``--impl warp`` where Warp cannot run is a ConfigError
    naming what is missing. On Warp a run of one process takes one GPU unless ``--devices``
    asks for more (a run of several processes takes every device, as on JAX physics)."""
    if not cfg.env.startswith("playground/"):
        return cfg, devices
    import jax  # lazy: JAX, only for a run

    from td3_jax.envs import physics  # lazy: imports JAX

    asked = cfg.impl or ("warp" if cfg.env_backend == "warp" else None)
    try:
        impl = physics.resolve(asked)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    note = ""
    one_host = jax.process_count() == 1  # (several processes: the mesh spans them all)
    if impl == "warp" and devices is None and one_host and jax.device_count() > 1:
        n = jax.device_count()
        devices, note = 1, f" on one GPU (--local-processes {n} --replay-shards {n} runs it on " \
                           f"all {n}, a process each)"  # fmt: skip
    elif impl == "jax" and asked is None:
        note = f": {physics.warp_missing()}"  # (why not Warp, the default where it runs)
    if jax.process_index() == 0:
        name = "MuJoCo Warp" if impl == "warp" else "MJX's JAX implementation"
        print(f"physics: {name} (--impl {impl}){note}", flush=True)
    return dataclasses.replace(cfg, impl=impl), devices
