"""New SQLite stores copied from the empty-store template (experiments/runtime/schema_template.py) are what MLflow
itself would create: same schema and version, the default experiment with the new store's own artifact
location; a damaged template is rebuilt, and without a usable cache MLflow creates the store as before."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest
from mlflow.tracking import MlflowClient

from experiments.runtime import schema_template
from experiments.runtime.tracking import Client


def _schema(db: Path) -> tuple[set, str]:
    """Each table's and index's definition as a set of lines: MLflow's own migrations emit a table's
    constraints in varying order (two stores MLflow made differ so)."""
    con = sqlite3.connect(db)
    try:
        rows = con.execute("SELECT type, name, sql FROM sqlite_master WHERE name NOT LIKE 'sqlite_%'")
        sql = {(kind, name, frozenset(line.strip().rstrip(",") for line in (text or "").splitlines()))
               for kind, name, text in rows}
        return sql, con.execute("SELECT version_num FROM alembic_version").fetchone()[0]
    finally:
        con.close()


def _experiments(uri: str) -> list[tuple[str, str, str]]:
    return [(e.experiment_id, e.name, e.artifact_location) for e in MlflowClient(uri).search_experiments()]


@pytest.mark.slow
def test_a_copied_store_is_what_mlflow_creates(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    by_mlflow, copied = tmp_path / "a" / "mlflow.db", tmp_path / "b" / "mlflow.db"
    by_mlflow.parent.mkdir()
    copied.parent.mkdir()
    MlflowClient(f"sqlite:///{by_mlflow}").search_experiments()
    client = Client(f"sqlite:///{copied}")
    assert schema_template.template_path().exists()  # built on the way, under tmp_path/cache
    assert _schema(copied) == _schema(by_mlflow)
    assert _experiments(f"sqlite:///{copied}") == [("0", "Default", str(Path.cwd() / "mlruns" / "0"))]
    assert _experiments(f"sqlite:///{by_mlflow}")[0][:2] == ("0", "Default")
    exp = client.create_experiment("ablation")  # and it takes runs as any store
    run = client.create_run(exp)
    client.log_metric(run.info.run_id, "loss", 0.5, step=3)
    assert [(m.step, m.value) for m in client.get_metric_history(run.info.run_id, "loss")] == [(3, 0.5)]
    assert exp == "1"  # ids continue as in a store MLflow made


def test_a_damaged_template_is_rebuilt(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    template = schema_template.template_path()
    template.parent.mkdir(parents=True)
    template.write_bytes(b"not a database")
    assert schema_template.create_from_template(tmp_path / "mlflow.db")
    assert _schema(tmp_path / "mlflow.db") == _schema(template)
    assert _experiments(f"sqlite:///{tmp_path / 'mlflow.db'}")[0][:2] == ("0", "Default")


def test_without_a_usable_cache_mlflow_creates_the_store(tmp_path, monkeypatch):
    blocker = tmp_path / "cache"
    blocker.write_text("a file where the cache folder would be")
    monkeypatch.setenv("XDG_CACHE_HOME", str(blocker))
    db = tmp_path / "store" / "mlflow.db"
    db.parent.mkdir()
    assert not schema_template.create_from_template(db) and not db.exists()
    Client(f"sqlite:///{db}")  # MLflow's own migrations
    assert _experiments(f"sqlite:///{db}")[0][:2] == ("0", "Default")
    assert sorted(p.name for p in db.parent.iterdir()) == ["mlflow.db", "mlflow.db.lock"]
