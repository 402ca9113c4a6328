"""``factorq gym``: its command (``command.py``) and what only it needs."""
