"""Runnable examples (a package, so ``--env examples.point_mass:make`` imports from the
repository's root)."""
