"""Optional glue for RL libraries (the ``rl`` extra): RLlib and SuperSuit / Stable-Baselines3.

Nothing here is imported by ``tbsim_env`` itself; each module imports its library lazily.
"""
