"""The host process around the compiled chunk: the training loop (evaluate, log, checkpoint),
the run directory, checkpoints, the compiled programs and their store, sharding over devices,
metrics, curves and experiment tracking."""

__all__: list[str] = []
