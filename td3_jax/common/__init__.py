"""The ground floor: errors, the one module that names other libraries' private parts
(``upstream``), the member axis, and the host process's threads, signals and caches
(``runtime``). Imports nothing else of td3_jax."""

__all__: list[str] = []
