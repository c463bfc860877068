"""reports.bulk_metrics writes what MLflow's own log_batch writes: the same points through both into two runs of
one store must read back the same (histories, latest values, the raw rows), edge cases included."""

from __future__ import annotations

import math
import sqlite3

import pytest
from mlflow.entities import Metric

from experiments.tracking import Client
from reports import bulk_metrics

# (key, value, timestamp, step): duplicates, a step logged twice at one time with two values, steps out of order,
# an older timestamp at a later step, NaN (twice at one point), both infinities, and a 0 and a NaN at one point (the
# same rank: MLflow stores NaN as 0, and the first logged stays latest)
POINTS = [
    ("loss", 3.0, 1000, 0), ("loss", 2.0, 1010, 5), ("loss", 2.0, 1010, 5), ("loss", 2.5, 1010, 5),
    ("loss", 1.5, 1005, 10), ("loss", 9.0, 1020, 2), ("loss", math.nan, 1030, 3), ("loss", math.nan, 1030, 3),
    ("val", math.inf, 1000, 0), ("val", -math.inf, 1000, 1), ("val", 0.5, 999, 1),
    ("final", math.nan, 2000, 0), ("tie", 1.0, 5, 1), ("tie", 1.0, 5, 1), ("tie", -1.0, 5, 1),
    ("zero", 0.0, 7, 2), ("zero", math.nan, 7, 2),
]


def _raw(db, run_id: str) -> tuple[list, list]:
    with sqlite3.connect(db) as con:
        metrics = con.execute("SELECT key, value, timestamp, step, is_nan FROM metrics WHERE run_uuid = ? "
                              "ORDER BY key, step, timestamp, value, is_nan", (run_id,)).fetchall()
        latest = con.execute("SELECT key, value, timestamp, step, is_nan FROM latest_metrics WHERE run_uuid = ? "
                             "ORDER BY key", (run_id,)).fetchall()
    return metrics, latest


def _history(client: Client, run_id: str, key: str) -> list:
    return sorted((m.step, m.timestamp, repr(m.value)) for m in client.get_metric_history(run_id, key))


def test_bulk_insert_equals_mlflows_log_batch(tmp_path):
    db = tmp_path / "mlflow.db"
    client = Client(f"sqlite:///{db}")
    exp = client.create_experiment("bulk")
    ours, theirs = (client.create_run(exp).info.run_id for _ in range(2))
    assert bulk_metrics.supported(db)
    bulk_metrics.insert_new_run_metrics(db, ours, POINTS)
    client.log_batch(theirs, metrics=[Metric(k, v, ts, step) for k, v, ts, step in POINTS])

    assert _raw(db, ours) == _raw(db, theirs)
    metrics, latest = _raw(db, ours)
    assert len(metrics) == len(POINTS) - 3  # the exact duplicates and the second NaN dropped
    assert dict((k, (v, ts, step, nan)) for k, v, ts, step, nan in latest)["loss"] == (1.5, 1005, 10, 0)
    for key in ("loss", "val", "final", "tie", "zero"):
        assert _history(client, ours, key) == _history(client, theirs, key)
    a, b = client.get_run(ours).data.metrics, client.get_run(theirs).data.metrics
    assert a.keys() == b.keys() == {"loss", "val", "final", "tie", "zero"}
    assert all(repr(a[k]) == repr(b[k]) for k in a)


def test_a_store_with_other_metric_columns_is_not_written(tmp_path):
    db = tmp_path / "other.db"
    with sqlite3.connect(db) as con:
        con.execute("CREATE TABLE metrics (key TEXT, value REAL, run_uuid TEXT)")
        con.execute("CREATE TABLE latest_metrics (key TEXT, value REAL, run_uuid TEXT)")
    assert not bulk_metrics.supported(db)
    assert not bulk_metrics.supported(tmp_path / "missing-dir" / "none.db")


def test_a_run_that_already_has_metrics_is_refused_whole(tmp_path):
    db = tmp_path / "mlflow.db"
    client = Client(f"sqlite:///{db}")
    run = client.create_run(client.create_experiment("bulk")).info.run_id
    bulk_metrics.insert_new_run_metrics(db, run, POINTS[:2])
    with pytest.raises(sqlite3.IntegrityError):
        bulk_metrics.insert_new_run_metrics(db, run, POINTS[:4])
    assert len(_raw(db, run)[0]) == 2  # the failed call wrote nothing
