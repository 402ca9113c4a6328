"""The base layer: random streams, argument checks and configs.

Everything above imports from here (the worlds in ``envs``, the agent in ``factorq_torch``, the
compiled path and the trainers); nothing here imports anything of the project outside this package.
"""
