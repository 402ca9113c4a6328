"""envs: the FactoredGrid world of the paper, for torchrl and gymnasium."""
