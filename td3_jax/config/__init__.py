"""A training run's settings: the :class:`~td3_jax.config.schema.TrainConfig` schema and its one
validation (``schema``), presets as data (``presets``), and the adapter that turns a config into
the environment, agent and compiled-program inputs that the runner takes (``build``)."""

__all__: list[str] = []
