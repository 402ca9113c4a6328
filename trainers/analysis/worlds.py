"""The obstacle regimes' names and periods for code that must not import torch (the reports,
the results schema): ``factorq_envs.world.WORLD_PERIODS`` imports torch with the world's
functions. ``tests/test_runner.py`` checks that the two stay equal; the envs helper's later
renames can make ``factorq_envs`` hold them in a torch-free module and this one
import them."""

#: Obstacle period per regime (0: never moves), as ``factorq_envs.world.WORLD_PERIODS``.
WORLD_PERIODS = {"static": 0, "semi-dynamic": 10, "dynamic": 1}
WORLDS = tuple(WORLD_PERIODS)
