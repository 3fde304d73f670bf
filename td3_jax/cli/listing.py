"""The subcommands that list what this installation offers: ``envs`` (each environment and
what it still needs to run here) and ``presets`` (each preset and the flags it sets)."""

from __future__ import annotations

from td3_jax.cli.commands import EnvsCommand, PresetsCommand
from td3_jax.cli.parsing import parse
from td3_jax.config.presets import NAMES, PRESETS, preset
from td3_jax.config.schema import ConfigError, as_flag

__all__ = ["envs_main", "envs_table", "presets_main"]


def envs_main(args: list[str]) -> None:
    """One line per environment: its name, the td3-jax extra it needs, whether it runs here
    (else what it still needs); then which physics Playground's tasks get here, and how to
    train an environment of your own."""
    from td3_jax import envs  # lazy: imports JAX
    from td3_jax.envs import physics  # lazy: imports JAX
    from td3_jax.envs.custom import KINDS  # lazy: imports JAX

    command = parse(EnvsCommand, args, "td3-jax envs")
    if command.menagerie is not None and not command.menagerie.expanduser().is_dir():
        raise ConfigError(f"--menagerie {command.menagerie} is not a directory")
    for line in envs_table(envs.catalog(command.menagerie)):
        print(line)
    missing = physics.warp_missing()
    engine = f"MJX's JAX implementation; {missing}" if missing else "MuJoCo Warp"
    print(f"\nPlayground physics here by default: {engine}. --impl jax|warp chooses.")
    print(f"Your own environment: --env module.path:function, a function returning "
          f"{KINDS} (docs/guides/own-environment.md).")  # fmt: skip


def envs_table(rows: list[tuple[str, str, str]]) -> list[str]:
    """The lines of ``td3-jax envs``' table of ``(name, extra, what it still needs)`` rows:
    a header, then each environment, its extra (``-``: none) and ``yes`` where it runs here,
    else ``no:`` and what it needs."""
    cells = [("environment", "extra", "runs here")]
    cells += [(name, extra or "-", f"no: {need}" if need else "yes") for name, extra, need in rows]
    name_width = max(len(c[0]) for c in cells)
    extra_width = max(len(c[1]) for c in cells)
    return [f"{n:<{name_width}}  {e:<{extra_width}}  {h}" for n, e, h in cells]


def presets_main(args: list[str]) -> None:
    """One line per preset (the named ones, else all): its name and the flags it sets; an
    unknown name is :func:`~td3_jax.config.presets.preset`'s ConfigError (the closest names)."""
    names = parse(PresetsCommand, args, "td3-jax presets").names or NAMES  # (no old names)
    for name in names:
        preset(name)  # (refuses an unknown name before anything is printed)
    for name in names:
        settings = " ".join(as_flag(k, v) for k, v in PRESETS[name].items())
        print(f"{name}: {settings}")
