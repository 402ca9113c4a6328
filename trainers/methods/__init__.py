"""What several commands' methods share: the grid experiment's configuration, env and tabular
agents (``experiment``) and the batched DQN (``dqn``)."""
