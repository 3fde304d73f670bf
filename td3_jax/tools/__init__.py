"""What is done with a finished run: export a policy (``export``), the NumPy-only policy file
reader (``policy_file``, importable without JAX), and videos (``render``)."""

__all__: list[str] = []
