"""Store faults injected into a study run in this process (`--workers 1`), from the moment its first checkpoint is
in the store: imported before experiments.cli.main by tests/test_store_faults.py.

ACRMDN_TEST_STORE_FAULT selects the fault:
- "disk-full": the disk has no room left. SQLite may not grow the store file by a page (its own max_page_count
  limit, frozen at the file's size on every connection: a genuine SQLITE_FULL, "database or disk is full", while
  writes that fit in the pages it has still succeed, as on a full disk), and every artifact the local artifact
  store (mlartifacts/) is given fails with ENOSPC.
- "read-only": the store file becomes read-only: SQLite's query_only on every connection (SQLITE_READONLY, "attempt
  to write a readonly database", what a file the process may not write gives; a test that runs as root cannot
  take the write permission from itself).
- "gone": the store file is moved away (to mlflow.db.moved beside it), as by a user or a clean-up job.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

from mlflow.store.artifact.local_artifact_repo import LocalArtifactRepository
from sqlalchemy import event
from sqlalchemy.engine import Engine

import experiments.cell_run as cell_run

FAULT = os.environ["ACRMDN_TEST_STORE_FAULT"]
DB = Path(os.environ["MLFLOW_TRACKING_URI"].removeprefix("sqlite:///"))
_on = False
_signal = cell_run.test_signal


def _after_checkpoint(marks) -> None:
    global _on
    if not _on:
        _on = True
        if FAULT == "gone":
            DB.rename(DB.with_name(DB.name + ".moved"))
    _signal(marks)


@event.listens_for(Engine, "checkout")
def _checkout(dbapi_connection, connection_record, connection_proxy) -> None:
    if not _on or FAULT == "gone":
        return
    cur = dbapi_connection.cursor()
    if FAULT == "read-only":
        cur.execute("PRAGMA query_only = 1")
    else:
        pages = cur.execute("PRAGMA page_count").fetchone()[0]
        cur.execute(f"PRAGMA max_page_count = {pages}")
    cur.close()


def _no_room(write):
    def full(self, local, *args, **kwargs):
        if _on and FAULT == "disk-full":
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), self.artifact_dir)
        return write(self, local, *args, **kwargs)
    return full


cell_run.test_signal = _after_checkpoint
LocalArtifactRepository.log_artifact = _no_room(LocalArtifactRepository.log_artifact)
LocalArtifactRepository.log_artifacts = _no_room(LocalArtifactRepository.log_artifacts)
