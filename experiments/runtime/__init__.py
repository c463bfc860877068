"""What lets studies run side by side and survive faults: the MLflow client with retries and the
store's shared names (tracking), a new store from a template (schema_template), stores checked
before anything is written (store_check), a claim per cell (claims), the shared cell queue
(cell_queue) and the Optuna storage it and the sweeps use (optuna_storage), worker processes
(processes), idle workers' capacity lent to an evaluating cell's physics (spread), which job runs next
(schedule), the one rule for study names (study_names), faults of the store that stop a study at once
(store_faults), and the one place that leans on MLflow's and Optuna's internal storage (backend_internals).
"""
