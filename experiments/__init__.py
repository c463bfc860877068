"""Experiment management, `python -m experiments {ablation,sweep,smoothing,idm,milestones,ui}` (cli).

Top level, a study from its config to its tracked results: validated study configs and profiles (study_config,
eval_sweep_config, config_errors), the ablation runner (ablation, cells), one cell's run and a cell group's packed run
(cell_run, pack; weights_resume: a cell resumed from its kept weights), evaluation and the logged model (evaluation,
model_logging), success statistics shared with the reports (stats), each episode of a task with modes rolled out
several times (mode_repeats), the milestones and post-processing studies (milestones, control_studies), training
throughput against worker processes (scaling) and the MLflow UI launcher (ui).
Subpackages: runtime (tracking, claims, the cell queue, processes, stores), sweeps (Optuna sweeps).
"""
