"""Check, before a study writes anything, that its stores answer: the MLflow tracking store
(a local SQLite file that may be locked by another writer, or a tracking server that may be
down) and an Optuna RDB storage / cell queue (PostgreSQL). Each is tried a bounded number of
times with exponential backoff; then one clear error, and nothing has been written.

ACRMDN_STORE_ATTEMPTS (default 6) and ACRMDN_STORE_DELAY (first wait in seconds, default 0.5,
doubling: 0.5 + 1 + 2 + 4 + 8 = 15.5 s in all by default) tune the retries.
"""

from __future__ import annotations

import logging
import os
import sqlite3
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path

log = logging.getLogger(__name__)


class StoreUnavailable(RuntimeError):
    """A store did not answer within the retries; str() is the one-line message."""


def _probe_sqlite(path: Path) -> None:
    if not path.exists():  # a new store: nothing can hold a lock on it yet
        if not path.parent.is_dir():
            raise OSError(f"folder {path.parent} does not exist")
        return
    con = sqlite3.connect(path, timeout=0.2)
    try:
        con.execute("BEGIN IMMEDIATE")  # takes (and drops) the write lock a study would need
        con.rollback()
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


def _redact(url: str) -> str:
    """postgresql://user:secret@host -> postgresql://user:***@host"""
    if "://" in url and "@" in url:
        scheme, rest = url.split("://", 1)
        cred, host = rest.rsplit("@", 1)
        if ":" in cred:
            cred = cred.split(":", 1)[0] + ":***"
        return f"{scheme}://{cred}@{host}"
    return url


def _retry(what: str, probe: Callable[[], None], attempts: int, delay: float) -> None:
    for attempt in range(1, attempts + 1):
        try:
            probe()
            return
        except Exception as exc:  # locked, refused, timed out, DNS: all transient at start-up
            reason = f"{type(exc).__name__}: {exc}".splitlines()[0][:300]
            if attempt == attempts:
                raise StoreUnavailable(f"{what} did not answer after {attempts} tries ({reason}); "
                                       "nothing was written; start it (or wait for the other writer) "
                                       "and re-run") from None
            log.warning("%s not ready (%s); retry %d/%d in %.1fs", what, reason, attempt, attempts - 1, delay)
            time.sleep(delay)
            delay *= 2


def wait_for_stores(tracking: str, optuna_urls: tuple[str, ...] = (), attempts: int | None = None,
                    delay: float | None = None) -> None:
    """Raise StoreUnavailable unless the tracking store and every Optuna RDB URL answer."""
    attempts = attempts or int(os.environ.get("ACRMDN_STORE_ATTEMPTS", "6"))
    delay = delay if delay is not None else float(os.environ.get("ACRMDN_STORE_DELAY", "0.5"))
    if tracking.startswith("sqlite:///"):
        path = Path(tracking.removeprefix("sqlite:///"))
        _retry(f"MLflow store {path}", lambda: _probe_sqlite(path), attempts, delay)
    elif tracking.startswith(("http://", "https://")):
        _retry(f"MLflow tracking server {_redact(tracking)}", lambda: _probe_http(tracking), attempts, delay)
    for url in optuna_urls:
        if url.startswith(("postgresql", "sqlite:///")):
            _retry(f"Optuna storage {_redact(url)}", lambda url=url: _probe_rdb(url), attempts, delay)
