"""factorq_torch: the Factor-Q algorithm (and tabular Q-learning) for torchrl.

``functional`` holds one pure tensor function per equation of the paper; the other modules wrap
them as TensorDict modules, torchrl losses and an online collector.
"""

__version__ = "0.1.0"
