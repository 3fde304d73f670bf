"""Where environment creation spends its time: ``python -m benchmarks.profile_make_env brax/ant``.

Starts the backend first (so its start-up is not counted), then profiles ``td3_jax.envs.make``
and prints the 25 functions with the largest cumulative time.
"""

from __future__ import annotations

import cProfile
import pstats
import sys
import time


def main(argv: list[str] | None = None) -> None:
    import jax

    from td3_jax import envs

    argv = sys.argv[1:] if argv is None else argv
    jax.devices()
    name = argv[0] if argv else "brax/ant"
    start = time.perf_counter()
    profile = cProfile.Profile()
    profile.enable()
    envs.make(name)
    profile.disable()
    print(f"make {name}: {time.perf_counter() - start:.2f} s")
    pstats.Stats(profile).sort_stats("cumulative").print_stats(25)


if __name__ == "__main__":
    main()
