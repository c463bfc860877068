"""Faults of the store in the middle of a study: a store file that became read-only, a full disk, a store file that
disappeared (deleted or moved). No retry fixes them, so the command stops at once: one `error:` line, a summary of
what finished, exit code 3. Nothing more is written to the store: the runs it could not finish stay as they were
(RUNNING, with their last checkpoint artifact), and re-running the same command once the store is usable again
resumes them, as after a kill (docs/scale-out.md, "Faults on one machine").

`fault_reason` recognises such a fault in an exception (or the exceptions it wraps: MLflow wraps SQLAlchemy's,
which wrap sqlite3's); `StoreWatch` notices a store file that was deleted or replaced while the study ran (an open
SQLite connection would go on writing into the deleted file, and a new one would create an empty store);
`write_details` keeps the traceback out of the terminal, in a file the error line names.
"""

from __future__ import annotations

import errno
import os
import tempfile
import traceback
from pathlib import Path

DISK_IO = "a disk I/O error"
# what SQLite says (through sqlite3, SQLAlchemy and MLflow) -> what it means for the user
_SQLITE = (("attempt to write a readonly database", "the store file is read-only"),
           ("readonly database", "the store file is read-only"),
           ("database or disk is full", "the disk is full"),
           ("disk i/o error", DISK_IO),  # (retried first: tracking.with_retries)
           ("unable to open database file", "the store file cannot be opened (deleted, moved or unreadable)"),
           ("no such table", "the store file lost its tables (deleted or replaced while the study ran)"),
           ("database disk image is malformed", "the store file is damaged"))
_ERRNOS = {errno.ENOSPC: "the disk is full", errno.EDQUOT: "the disk quota is exceeded",
           errno.EROFS: "the file system is read-only"}
ADVICE = ("nothing more was written to it; the unfinished runs keep their last checkpoint: free space, make the store "
          "writable or put it back, then re-run the same command to resume them")


class StoreFault(RuntimeError):
    """The store failed mid-study in a way no retry fixes; str() is the one-line reason. `outcome`: what the study
    finished before (experiments.ablation.StudyOutcome, or None), `unfinished`: the keys of the cells it left."""

    def __init__(self, reason: str, outcome=None, unfinished: list[str] | None = None):
        super().__init__(reason)
        self.outcome, self.unfinished = outcome, list(unfinished or [])


def _chain(exc: BaseException):
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        yield exc
        exc = exc.__cause__ or exc.__context__


def is_lasting(exc: BaseException) -> bool:
    """A store fault no retry fixes (a read-only or full store, one that disappeared); a disk I/O error may pass."""
    reason = fault_reason(exc)
    return reason is not None and reason != DISK_IO


def fault_reason(exc: BaseException) -> str | None:
    """One line naming the store fault that `exc` is or wraps, else None (any other error)."""
    for e in _chain(exc):
        if isinstance(e, StoreFault):
            return str(e)
        if isinstance(e, OSError) and e.errno in _ERRNOS:
            where = f" ({e.filename})" if e.filename else ""
            return f"{_ERRNOS[e.errno]}{where}"
        text = str(e).lower()
        for needle, meaning in _SQLITE:
            if needle in text:
                return meaning
    return None


class StoreWatch:
    """The identity (device, inode) of a local SQLite store file when the study started; `check` raises StoreFault
    once the file at that path is gone or another one."""

    def __init__(self, db: Path | None):
        self.db = db
        self.identity = self._identity()

    def _identity(self) -> tuple[int, int] | None:
        if self.db is None:
            return None
        try:
            st = os.stat(self.db)
        except FileNotFoundError:
            return None
        return st.st_dev, st.st_ino

    def check(self) -> None:
        if self.db is None or self.identity is None:
            return
        now = self._identity()
        if now != self.identity:
            what = "was deleted or moved" if now is None else "was replaced by another file"
            raise StoreFault(f"the store file {self.db} {what} while the study ran")


def write_details(exc: BaseException) -> Path | None:
    """The traceback of `exc` in a file of the temporary folder (its path), or None when even that cannot be
    written (a full disk)."""
    try:
        fd, name = tempfile.mkstemp(prefix="acrmdn-store-fault-", suffix=".log")
        with os.fdopen(fd, "w") as f:
            f.write("".join(traceback.format_exception(exc)))
        return Path(name)
    except OSError:
        return None
