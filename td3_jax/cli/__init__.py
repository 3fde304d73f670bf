"""The ``td3-jax`` command line: parsing, subcommands, messages and exit codes."""

from td3_jax.cli.app import main

__all__ = ["main"]
