"""Optuna sweeps of the mixture count and the auto-conditioning schedule: the sweep itself and its
search space (runner), what one trial does (objective), its figures (figures) and
optuna-dashboard over the sweep storage (dashboard, `python -m experiments.sweeps.dashboard`).
"""
