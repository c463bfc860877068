"""Everything that leans on how MLflow and Optuna store things, beyond their public API: their SQL
tables, private attributes and modules, and the text of the errors their storages raise. An upgrade
of either (pyproject bounds both to the major version tested) is checked here first; the rest of
the project uses their public API.

What is leaned on, and why:

- MLflow's SQLite schema (tables `alembic_version`, `experiments`, `experiment_tags`, `runs`).
  A new store is a copy of an empty one (experiments/runtime/schema_template.py), because MLflow
  builds a store by running its ~70 migrations one by one (~6.5 s a store). The copy must not
  carry the default experiment (id 0) with the template's artifact location, and no public call
  removes it (delete_experiment only marks it deleted): `drop_default_experiment` deletes its rows.
  The template is trusted only while it has MLflow's version table and no experiment
  (`is_empty_store`). Reports open a SQLite file read-only first (`table_names`), because MLflow
  opening a file that is not its store would create or migrate tables in it.
- The error texts through which a storage's conflicts reach us: MLflow wraps the driver's
  exceptions, so SQLite's lock contention is known by its text (`is_transient_store_error`, retried
  by experiments/runtime/tracking.py) and so is a param another process inserted between our read
  and our write (`is_param_conflict`: PostgreSQL's and SQLite's unique-key errors, MLflow's own check).
- MLflow's unique key on a run's params: a cell's claim (experiments/runtime/claims.py) is the param
  `claim.<n>`, and of two processes logging it at once exactly one succeeds; `lost_param_race`
  tells that loss (MLflow's INVALID_PARAMETER_VALUE) from any other failure.
- The fluent API's pinned tracking URI, a private attribute (`pinned_tracking_uri`): logging a model
  goes through the fluent API, and no public call tells a pinned URI from a resolved one, so
  experiments/model_logging.py could not otherwise put back exactly what was there.
- MLflow's artifact repository (`artifact_repository`, from its store modules): a report replaces
  its folder of the parent run's artifacts as a whole (reports/study_report/build.py), and
  MlflowClient has no call that deletes artifacts.
- Optuna's RDB storage creating its schema through SQLAlchemy when it opens: processes opening a
  fresh server database at once race on it, the loser seeing a unique-key or "already exists"
  error (`is_schema_race`); the schema then exists, so a retry just opens it.
- Optuna's refusal to record a trial that another worker had already failed as stale (a late
  heartbeat) and re-queued: raised as ValueError("Cannot tell a FAIL trial."), masked by an
  AssertionError from its own clean-up (`told_after_failed_as_stale`).

Not here, because they use only the public API: the cell queue (Optuna trials as work items,
popped by `study.ask`: experiments/runtime/cell_queue.py) and the claims' tags and params.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path
from typing import Any

# a param another process inserted between our read and our write (PostgreSQL, SQLite, MLflow's own check)
_PARAM_CONFLICTS = ("duplicate key", "UNIQUE constraint failed", "Changing param values is not allowed")
_RETRY_MARKERS = ("database is locked", "database table is locked", "sqlite3.OperationalError", "disk I/O error")


def drop_default_experiment(db: Path) -> None:
    """Delete the default experiment (id 0) and its tags from a fresh SQLite MLflow store."""
    con = sqlite3.connect(db)
    try:
        with con:
            con.execute("DELETE FROM experiment_tags WHERE experiment_id = 0")
            con.execute("DELETE FROM experiments WHERE experiment_id = 0")
    finally:
        con.close()


def is_empty_store(path: Path) -> bool:
    """An SQLite file with MLflow's schema version table and no experiment (what drop_default_experiment leaves)."""
    try:
        con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
        try:
            version = con.execute("SELECT version_num FROM alembic_version").fetchone()
            empty = con.execute("SELECT COUNT(*) FROM experiments").fetchone()[0] == 0
        finally:
            con.close()
    except sqlite3.DatabaseError:
        return False
    return version is not None and empty


MLFLOW_TABLES = frozenset({"experiments", "runs"})  # tables every MLflow store has


def table_names(path: Path) -> set[str]:
    """The tables of an existing SQLite file, read-only (sqlite3.Error when it is not a database)."""
    con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        return {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")}
    finally:
        con.close()


def is_transient_store_error(exc: BaseException) -> bool:
    """SQLite lock contention (or a passing I/O error) as it reaches us through MLflow: worth a retry."""
    text = f"{type(exc).__name__}: {exc}"
    return any(m in text for m in _RETRY_MARKERS)


def is_param_conflict(exc: BaseException) -> bool:
    """A param logged by another process between our read and our write."""
    return any(m in str(exc) for m in _PARAM_CONFLICTS)


def lost_param_race(exc: Any) -> bool:
    """An MlflowException from log_param for a key the run already has (another process logged it first)."""
    return getattr(exc, "error_code", None) == "INVALID_PARAMETER_VALUE"


def pinned_tracking_uri() -> str | None:
    """The tracking URI pinned by mlflow.set_tracking_uri, None when unset (then the environment
    variable or the default applies)."""
    from mlflow.tracking._tracking_service import utils

    return utils._tracking_uri


def artifact_repository(artifact_uri: str):
    """MLflow's artifact repository of a run's artifact URI (it can delete, which MlflowClient cannot)."""
    from mlflow.store.artifact.artifact_repository_registry import get_artifact_repository

    return get_artifact_repository(artifact_uri)


def is_schema_race(exc: BaseException) -> bool:
    """The loser's error when processes create an Optuna RDB schema at once."""
    from sqlalchemy.exc import IntegrityError, ProgrammingError

    return isinstance(exc, IntegrityError | ProgrammingError)


def told_after_failed_as_stale(exc: BaseException | None) -> bool:
    """Optuna's refusal to record a trial that another worker had already failed as stale (its heartbeat
    came late, e.g. on a starved machine) and re-queued: the work it did stands. The chain of exceptions
    is searched, since Optuna's clean-up masks it."""
    while exc is not None:
        if isinstance(exc, ValueError) and str(exc).startswith("Cannot tell a FAIL trial"):
            return True
        exc = exc.__context__
    return False
