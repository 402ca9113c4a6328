"""Doors into factorq_torch for other libraries' agents, each behind its optional extra
(``sb3``: Stable-Baselines3). Nothing here is imported by ``factorq_torch`` itself."""
