"""Check, before a study writes anything, that its stores answer: the MLflow tracking store
(a local SQLite file that may be locked by another writer, or a tracking server that may be
down) and an Optuna RDB storage / cell queue (PostgreSQL). A store that may come back (locked,
refused, timed out) is tried a bounded number of times with exponential backoff; one that
cannot (a missing folder, a folder we may not write to, a store file that is read-only or whose
disk is full, a file that is not a database) fails at once. Faults that come later, mid-study:
experiments/runtime/store_faults.py. Either way: one clear error, and nothing has been written.

ACRMDN_STORE_ATTEMPTS (default 6) and ACRMDN_STORE_DELAY (first wait in seconds, default 0.5,
doubling: 0.5 + 1 + 2 + 4 + 8 = 15.5 s in all by default) tune the retries.
"""

from __future__ import annotations

import logging
import os
import sqlite3
import tempfile
import urllib.request
from collections.abc import Callable
from pathlib import Path

import tenacity

log = logging.getLogger(__name__)


class StoreUnavailable(RuntimeError):
    """A store did not answer within the retries; str() is the one-line message."""


class StoreUnusable(StoreUnavailable):
    """A store that no retry can fix (missing folder, no write permission, not a database)."""


class _Permanent(Exception):
    """Raised by a probe for a fault that waiting cannot fix."""


def _probe_sqlite(path: Path) -> None:
    folder = path.absolute().parent
    if not folder.is_dir():
        raise _Permanent(f"folder {folder} does not exist; create it or set MLFLOW_TRACKING_URI")
    try:  # the db, its journal and the artifacts are created in this folder
        tempfile.TemporaryFile(dir=folder).close()
    except OSError as exc:
        raise _Permanent(f"folder {folder} is not writable ({exc.strerror}); run from a folder you can write "
                         "to or set MLFLOW_TRACKING_URI") from None
    if not path.exists():  # a new store: nothing can hold a lock on it yet
        return
    con = sqlite3.connect(path, timeout=0.2)
    try:
        con.execute("BEGIN IMMEDIATE")  # takes (and drops) the write lock a study would need
        # a file we may not write opens read-only, and BEGIN IMMEDIATE succeeds on it all the same: a write,
        # rolled back, is what fails on it (and on a disk with no room for the journal)
        con.execute("CREATE TABLE acrmdn_write_probe (x)")
        con.rollback()
    except sqlite3.DatabaseError as exc:  # OperationalError (locked, busy) is a subclass: transient
        if isinstance(exc, sqlite3.OperationalError) and "locked" in str(exc):
            raise
        if "readonly" in str(exc):
            raise _Permanent("the file is read-only; make it writable (chmod u+w) or set MLFLOW_TRACKING_URI") from None
        if "full" in str(exc):
            raise _Permanent("its disk is full; free space and re-run") from None
        raise _Permanent(f"{path} is not a usable SQLite database ({exc}); move it aside or set "
                         "MLFLOW_TRACKING_URI") from None
    finally:
        con.close()


def _probe_http(uri: str) -> None:
    with urllib.request.urlopen(f"{uri.rstrip('/')}/health", timeout=5) as resp:
        if resp.status != 200:
            raise OSError(f"HTTP {resp.status}")


def _probe_rdb(url: str) -> None:
    import sqlalchemy

    engine = sqlalchemy.create_engine(url, connect_args={"connect_timeout": 5} if url.startswith("postgresql")
                                      else {})
    try:
        with engine.connect() as con:
            con.execute(sqlalchemy.text("SELECT 1"))
    finally:
        engine.dispose()


def redact(url: str) -> str:
    """postgresql://user:secret@host/db -> postgresql://user:***@host/db (likewise http://user:pw@...)."""
    if "@" not in url:
        return url
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError

    try:
        return make_url(url).render_as_string(hide_password=True)
    except ArgumentError:
        return url


def _retry(what: str, probe: Callable[[], None], attempts: int, delay: float) -> None:
    def on_retry(state: tenacity.RetryCallState) -> None:
        log.warning("%s not ready (%s); retry %d/%d in %.1fs", what, _reason(state.outcome.exception()),
                    state.attempt_number, attempts - 1, state.next_action.sleep)

    try:
        tenacity.retry(retry=tenacity.retry_if_not_exception_type(_Permanent), reraise=True,
                       stop=tenacity.stop_after_attempt(attempts),
                       wait=tenacity.wait_exponential(multiplier=delay, min=delay, max=60),
                       before_sleep=on_retry)(probe)()
    except _Permanent as exc:
        raise StoreUnusable(f"{what}: {exc}; nothing was written") from None
    except Exception as exc:  # locked, refused, timed out, DNS: all transient at start-up
        raise StoreUnavailable(f"{what} did not answer after {attempts} tries ({_reason(exc)}); nothing was "
                               "written; start it (or wait for the other writer) and re-run") from None


def _reason(exc: BaseException | None) -> str:
    return f"{type(exc).__name__}: {exc}".splitlines()[0][:300]


def wait_for_stores(tracking: str, optuna_urls: tuple[str, ...] = (), attempts: int | None = None,
                    delay: float | None = None) -> None:
    """Raise StoreUnavailable unless the tracking store and every Optuna RDB URL answer
    (StoreUnusable, at once, for a fault no retry can fix)."""
    attempts = attempts or int(os.environ.get("ACRMDN_STORE_ATTEMPTS", "6"))
    delay = delay if delay is not None else float(os.environ.get("ACRMDN_STORE_DELAY", "0.5"))
    if tracking.startswith("sqlite:///"):
        path = Path(tracking.removeprefix("sqlite:///"))
        _retry(f"MLflow store {path}", lambda: _probe_sqlite(path), attempts, delay)
    elif tracking.startswith(("http://", "https://")):
        _retry(f"MLflow tracking server {redact(tracking)}", lambda: _probe_http(tracking), attempts, delay)
    for url in optuna_urls:
        if url.startswith("sqlite:///"):
            path = Path(url.removeprefix("sqlite:///"))
            _retry(f"Optuna storage {path}", lambda path=path: _probe_sqlite(path), attempts, delay)
        elif url.startswith("postgresql"):
            _retry(f"Optuna storage {redact(url)}", lambda url=url: _probe_rdb(url), attempts, delay)
