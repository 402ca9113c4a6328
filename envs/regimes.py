"""The obstacle regimes of the paper's grid (SPEC section 1) by name and obstacle period: static
obstacles, obstacles that scatter every 10 steps, and every step. Torch-free (the reports and the
results schema read them without importing torch).

In code they are *regimes* (``REGIMES``, ``REGIME_PERIODS``): a *world* is a
``factorq_envs.protocol.World``. Their names stay what results files, options (``--worlds``) and
the paper call them.

>>> REGIMES
('static', 'semi-dynamic', 'dynamic')
>>> REGIME_PERIODS["semi-dynamic"]
10
"""

#: Obstacle period per regime: steps between two scatters (0: never moves).
REGIME_PERIODS = {"static": 0, "semi-dynamic": 10, "dynamic": 1}
#: The regimes, in the paper's order.
REGIMES = tuple(REGIME_PERIODS)
