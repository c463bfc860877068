"""A new SQLite MLflow store as a copy of an empty one: MLflow builds a fresh store by running its
schema migrations one by one (~70 of them, ~330 DDL statements, each its own transaction), which
takes ~6.5 s, ~5 s of it waiting on fsync, for every new store. Built once per MLflow version
and machine, the empty store is a file copy from then on.

The template is what MLflow itself created, minus the default experiment (id 0): MLflow adds
that one when it first opens a store that lacks it, with the new store's own artifact location,
so a copied store is what MLflow would have made (the SQL that removes it and checks a template:
experiments/runtime/backend_internals.py). Anything going wrong here (no writable cache,
a damaged template) only costs the time saved: the caller then lets MLflow create the store.

The template lies in $XDG_CACHE_HOME/acrmdn (default ~/.cache/acrmdn), named by MLflow's version.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from importlib import metadata
from pathlib import Path

from experiments.runtime.backend_internals import drop_default_experiment, is_empty_store

log = logging.getLogger(__name__)


def template_path() -> Path:
    cache = os.environ.get("XDG_CACHE_HOME", "").strip() or str(Path.home() / ".cache")
    return Path(cache) / "acrmdn" / f"mlflow-{metadata.version('mlflow')}-empty-store.db"


def _build(template: Path) -> None:
    """MLflow creates a store in a scratch folder beside the template; its default experiment is
    dropped, and the file moved into place in one step (readers never see a half-built one)."""
    from mlflow.tracking import MlflowClient

    with tempfile.TemporaryDirectory(dir=template.parent) as scratch:
        db = Path(scratch) / "mlflow.db"
        MlflowClient(tracking_uri=f"sqlite:///{db}").search_experiments(max_results=1)
        drop_default_experiment(db)
        os.replace(db, template)


def create_from_template(db: Path) -> bool:
    """Make the (absent) SQLite store `db` a copy of the empty template, building the template first
    if need be; the caller holds db's schema lock. False, with `db` left absent, when the template
    cannot be had: then MLflow creates the store itself."""
    from filelock import FileLock

    template = template_path()
    try:
        template.parent.mkdir(parents=True, exist_ok=True)
        with FileLock(f"{template}.lock", timeout=120):
            if not (template.exists() and is_empty_store(template)):
                _build(template)
    except Exception as exc:  # noqa: BLE001 - a faster path only; MLflow's own creation still works
        log.debug("no schema template for %s (%s: %s)", db, type(exc).__name__, exc)
        return False
    partial = db.with_name(f".{db.name}.{os.getpid()}.partial")
    try:
        shutil.copyfile(template, partial)
        os.replace(partial, db)  # the store appears whole
        return True
    except OSError as exc:
        partial.unlink(missing_ok=True)
        log.debug("new store %s not copied from the schema template (%s)", db, exc)
        return False
