"""One module per ``factorq`` command (its experiment only), and the pieces experiments share
(``experiment``: keys, env, tables, recorder; ``dqn``: the DQN baseline). A module that assigns
``NAME = "..."`` is a command (``factorq_trainers.runner.registry``)."""
