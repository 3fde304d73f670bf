"""Everything that runs inside ``jit``: the TD3/DDPG agent, networks, losses, the distributional
critic, exploration noise, the replay ring with n-step returns, running statistics, the training
chunk, populations of seeds and sweeps, evaluation worlds. Pure functions over pytrees: no files,
no prints, no command-line flag names."""

__all__: list[str] = []
