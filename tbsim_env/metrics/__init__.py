"""Evaluation metrics of tbsim (WOSAC realism metrics in ``tbsim_env.metrics.wosac``)."""
