"""Experiment management: validated study configs and profiles (config), the ablation runner
(ablation, cells, worker, evaluation), Optuna sweeps (sweep), MLflow tracking helpers
(tracking), Wilson intervals (stats), the MLflow UI launcher (ui) and the command line
`python -m experiments {ablation,sweep,ui}` (cli)."""
