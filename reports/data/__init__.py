"""The studies as data: loaded from an MLflow store into pandas (store), exported into the
repository (export, with its models on request: export_models), read back from those exports as a store
(export_store) or into an MLflow store (studyimport), and aggregated over seeds (seed_aggregates).
"""
