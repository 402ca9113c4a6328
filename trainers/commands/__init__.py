"""The commands of ``factorq``, a folder each (``<name>/command.py`` with what only it needs
beside it: ``config.py``, ``methods.py``, ``report.py``); ``runner.registry`` finds them."""
