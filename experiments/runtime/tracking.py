"""MLflow tracking: the one home of what experiments/ and reports/ share about the store (its
URI, tags, experiment names, statuses), a client that retries on SQLite lock contention,
experiments and parent runs, batched metrics, flattened params.

The store defaults to `sqlite:///mlflow.db`, relative to the working directory (worker
processes start in the same one, and no generated file names a path of this machine), with
artifacts in `mlartifacts/` beside the db file; MLFLOW_TRACKING_URI overrides both. Creating
a fresh SQLite schema is serialised by a lock file beside the db (two studies started at the
same moment in a fresh folder would otherwise race on MLflow's migrations).
"""

from __future__ import annotations

import functools
import logging
import os
import re
import subprocess
import time
from collections.abc import Callable, Iterable, Mapping
from importlib import metadata
from pathlib import Path
from typing import Any

import tenacity
from mlflow.entities import Metric, Param, RunTag
from mlflow.tracking import MlflowClient

from experiments.runtime.backend_internals import is_param_conflict, is_transient_store_error
from experiments.runtime.schema_template import create_from_template
from experiments.runtime.store_faults import StoreFault, StoreWatch, is_lasting
from stm.training.interrupts import whole_step

log = logging.getLogger(__name__)

DEFAULT_DB = "mlflow.db"
DEFAULT_TRACKING_URI = f"sqlite:///{DEFAULT_DB}"
PARENT_TAG = "mlflow.parentRunId"
NOTE_TAG = "mlflow.note.content"  # a run's description in the MLflow UI (Markdown)
KIND_TAG = "mlflow.experimentKind"
# without this kind MLflow 3 opens an experiment in its GenAI layout (traces, prompts) instead of its runs
EXPERIMENT_KIND = "custom_model_development"
FAILED_STATUSES = ("FAILED", "KILLED")  # a cell or trial run that did not finish: a gap in a report
ABLATION, SWEEP, SMOOTHING, IDM, MILESTONES = "ablation", "sweep", "smoothing", "idm", "milestones"
STUDY_KINDS = (ABLATION, SWEEP, SMOOTHING, IDM, MILESTONES)  # one MLflow experiment per study kind
MILESTONE_ITERATION = "milestone.iteration"  # param of a milestones study's run: its checkpoint's iteration
PACKAGES = ("torch", "numpy", "pybullet", "pytorch-kinematics", "mlflow", "optuna", "scipy", "acrmdn")


def tracking_uri() -> str:
    """MLFLOW_TRACKING_URI if set, else `sqlite:///mlflow.db` (relative to the working directory)."""
    return os.environ.get("MLFLOW_TRACKING_URI", "").strip() or DEFAULT_TRACKING_URI


def sqlite_path(uri: str) -> Path | None:
    """The db file of a local SQLite store (relative if the URI is), else None."""
    return Path(uri.removeprefix("sqlite:///")) if uri.startswith("sqlite:///") else None


def store_dir(uri: str) -> Path:
    """The folder that holds a local store (its db file), else the working directory."""
    db = sqlite_path(uri)
    if db is not None:
        return db.parent
    if uri.startswith("file:"):
        return Path(uri.removeprefix("file://"))
    return Path(".")


def schema_lock(db: Path):
    """An inter-process lock beside a SQLite db file, held while a process may create its schema."""
    from filelock import FileLock

    return FileLock(f"{db}.lock", timeout=120)


def with_retries(fn: Callable, attempts: int = 8, base_delay: float = 0.05) -> Callable:
    """Retry a store call on SQLite lock contention (exponential backoff with full jitter); not a store that is
    read-only, full or gone (experiments/runtime/store_faults.py): waiting does not fix those."""

    def transient(exc: BaseException) -> bool:
        return is_transient_store_error(exc) and not is_lasting(exc)

    return tenacity.retry(retry=tenacity.retry_if_exception(transient), reraise=True,
                          stop=tenacity.stop_after_attempt(attempts),
                          wait=tenacity.wait_random_exponential(multiplier=base_delay, max=10),
                          before_sleep=tenacity.before_sleep_log(log, logging.DEBUG))(fn)


class Client:
    """MlflowClient whose every method retries on transient SQLite errors. `create=False` (the processes that join a
    study the main process started): a local store that does not exist is a StoreFault (it disappeared), not a new
    empty store. `check_store()` raises StoreFault once the store file is not the one this client opened."""

    def __init__(self, uri: str | None = None, create: bool = True):
        self.uri = uri or tracking_uri()
        db = sqlite_path(self.uri)
        self._watch = StoreWatch(None)
        if db is None:
            self._client = MlflowClient(tracking_uri=self.uri)
            return
        if not create and not db.exists():
            raise StoreFault(f"the store file {db} was deleted or moved while the study ran")
        with schema_lock(db):  # opening a fresh store creates (migrates) its schema: one process at a time
            if not db.exists():
                create_from_template(db)  # a copy of an empty store: seconds faster than MLflow's migrations
            self._client = with_retries(MlflowClient)(tracking_uri=self.uri)
            with_retries(self._client.search_experiments)(max_results=1)
        self._watch = StoreWatch(db)

    def check_store(self) -> None:
        self._watch.check()

    def __getattr__(self, name: str) -> Any:
        attr = getattr(self._client, name)
        return with_retries(_whole_call(attr)) if callable(attr) else attr


def _whole_call(fn: Callable) -> Callable:
    """A store call that a Ctrl-C does not cut short: the interrupt comes as the call returns. Cut inside
    SQLAlchemy, a call could leave the process's connection holding SQLite's write lock, and the Ctrl-C's own
    writes (the runs marked KILLED) then waited for it and gave up."""

    @functools.wraps(fn)
    def call(*args: Any, **kwargs: Any) -> Any:
        with whole_step():
            return fn(*args, **kwargs)

    return call


def get_or_create_experiment(client: Client, name: str) -> str:
    """The experiment of a study kind, tagged as model development (the UI then opens on its runs)."""
    exp = client.get_experiment_by_name(name)
    if exp is None:
        location = None
        db = sqlite_path(client.uri)
        if db is not None:  # keep artifacts beside the db file, not in whatever cwd a later run uses
            location = (db.resolve().parent / "mlartifacts" / name).as_uri()
        try:
            exp = client.get_experiment(client.create_experiment(name, artifact_location=location,
                                                                 tags={KIND_TAG: EXPERIMENT_KIND}))
        except Exception:
            exp = client.get_experiment_by_name(name)  # created concurrently
            if exp is None:
                raise
    if exp.lifecycle_stage == "deleted":
        client.restore_experiment(exp.experiment_id)
    if exp.tags.get(KIND_TAG) != EXPERIMENT_KIND:  # an experiment created before the kind was set
        try:
            client.set_experiment_tag(exp.experiment_id, KIND_TAG, EXPERIMENT_KIND)
        except Exception:  # another process set it at the same moment (a unique-key violation)
            if client.get_experiment(exp.experiment_id).tags.get(KIND_TAG) != EXPERIMENT_KIND:
                raise
    return exp.experiment_id


def find_parent_run(client: Client, experiment_id: str, study_name: str):
    """The study's parent run: the earliest, the one concurrent commands settle on (get_or_create_parent_run)."""
    runs = client.search_runs(
        [experiment_id],
        filter_string=f"tags.study_name = '{study_name}' and tags.role = 'parent'",
        order_by=["attributes.start_time ASC", "attributes.run_id ASC"],
        max_results=1,
    )
    return runs[0] if runs else None


def file_safe(name: str) -> str:
    """`name` as part of a file name (a task's, or a study's in RESULTS.md's figure names); never a study's folder,
    which is the study name itself (experiments.runtime.study_names)."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name)


def report_index(study_name: str) -> str:
    """Where `python -m reports` writes a study's report page (in the working directory): reports/out/<name>/, the
    name being a folder name by the study name rule (experiments.runtime.study_names)."""
    return f"reports/out/{study_name}/index.html"


def settle_window(uri: str) -> float:
    """Seconds a command that created a run waits before it looks for an earlier one. MLflow
    sets a run's start_time on the client before the insert commits, so a run that started
    earlier may become visible later; one whose insert took longer than this is withdrawn by
    its creator (get_or_create_parent_run). A local SQLite store commits in milliseconds."""
    return 0.5 if sqlite_path(uri) is not None else 3.0


def wait_for_earlier_runs(start_ms: int, window: float) -> None:
    """Sleep until `window` seconds after `start_ms`: by then a run started before it is visible."""
    time.sleep(max(0.0, start_ms / 1000 + window - time.time()))


def get_or_create_parent_run(client: Client, experiment_id: str, study_name: str, tags: Mapping[str, str]) -> str:
    """The study's parent run, marked RUNNING (a re-run reuses it). Commands of one study started
    at once (workers on several hosts) may each create one: after the settle window all see the
    same earliest, settle on it, and each deletes only the duplicate it created itself."""
    from mlflow.exceptions import MlflowException

    all_tags = {"study_name": study_name, "role": "parent", **tags}
    window = settle_window(client.uri)
    for _ in range(5):
        own = None
        run = find_parent_run(client, experiment_id, study_name)
        if run is None:
            began = time.time()
            own = client.create_run(experiment_id, run_name=study_name, tags=all_tags)
            if time.time() - began > window and _withdraw_parent_run(client, experiment_id, own.info.run_id):
                continue  # so slow that others may have settled on a later run meanwhile: theirs it is
            run = own
        wait_for_earlier_runs(run.info.start_time, window)
        first = find_parent_run(client, experiment_id, study_name)
        if first is None:  # the one we saw was deleted by its creator
            continue
        if own is not None and first.info.run_id != own.info.run_id:
            _withdraw_parent_run(client, experiment_id, own.info.run_id)
        try:
            client.update_run(first.info.run_id, status="RUNNING")
            client.log_batch(first.info.run_id, tags=[RunTag(k, str(v)) for k, v in all_tags.items()])
        except MlflowException as exc:  # deleted by its creator just after we found it
            if "deleted" not in str(exc):
                raise
            continue
        return first.info.run_id
    raise RuntimeError(f"the parent run of study {study_name!r} kept being deleted by another command")


def _withdraw_parent_run(client: Client, experiment_id: str, parent_id: str) -> bool:
    """Delete a parent run this command created, unless a cell already hangs under it."""
    if client.search_runs([experiment_id], filter_string=f"tags.`{PARENT_TAG}` = '{parent_id}'", max_results=1):
        return False
    client.delete_run(parent_id)
    return True


def child_runs(client: Client, experiment_id: str, parent_id: str) -> list:
    return client.search_runs([experiment_id], filter_string=f"tags.`{PARENT_TAG}` = '{parent_id}'",
                              max_results=50_000)


def flatten(d: Mapping[str, Any], prefix: str = "") -> dict[str, str]:
    """{'a': {'b': 1}} -> {'a.b': '1'}; lists are joined with commas."""
    out: dict[str, str] = {}
    for key, value in d.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(flatten(value, f"{name}."))
        elif isinstance(value, (list, tuple)):
            out[name] = ",".join(str(v) for v in value)
        else:
            out[name] = str(value)
    return out


@functools.cache
def git_commit() -> str:
    here = Path(__file__).resolve().parent
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True,
                             timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here,
                               capture_output=True, text=True, timeout=10).stdout.strip()
        return f"{sha}-dirty" if dirty else sha
    except (OSError, subprocess.SubprocessError):
        return "unknown"


@functools.cache
def package_versions() -> dict[str, str]:
    out = {}
    for name in PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "absent"
    return out


def machine_params() -> dict[str, str]:
    """Where a run ran: host, CPU model, cores, Python (timings mean little without them)."""
    import platform

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), cpu)
    except OSError:
        pass
    return {"machine.host": platform.node(), "machine.cpu": cpu, "machine.cores": str(os.cpu_count()),
            "machine.python": platform.python_version()}


def provenance_params() -> dict[str, str]:
    return {"git_commit": git_commit(), **{f"version.{k}": v for k, v in package_versions().items()},
            **machine_params()}


def log_params(client: Client, run_id: str, params: Mapping[str, Any]) -> None:
    """Log params once. MLflow params are immutable, so on a resumed/reused run a value that
    changed since (e.g. the git commit) is recorded as a tag `changed.<key>` instead."""
    from mlflow.exceptions import MlflowException

    values = {k: str(v)[:6000] for k, v in params.items()}
    for attempt in range(3):
        existing = client.get_run(run_id).data.params
        new = [Param(k, v) for k, v in values.items() if k not in existing]
        try:
            if new:
                client.log_batch(run_id, params=new)
            break
        except MlflowException as exc:  # another command of the study logged them at the same moment: read again
            if attempt == 2 or not is_param_conflict(exc):
                raise
    changed = {f"changed.{k}": v for k, v in values.items() if k in existing and existing[k] != v}
    if changed:
        set_tags(client, run_id, changed)


def log_metrics(client: Client, run_id: str, metrics: Mapping[str, float], step: int = 0) -> None:
    now = int(time.time() * 1000)
    client.log_batch(run_id, metrics=[Metric(k, float(v), now, step) for k, v in metrics.items()])


def set_tags(client: Client, run_id: str, tags: Mapping[str, Any]) -> None:
    client.log_batch(run_id, tags=[RunTag(k, str(v)[:5000]) for k, v in tags.items()])


class MetricBuffer:
    """Collects (step, {name: value}) and writes them in one log_batch per flush: at least
    every `flush_seconds`, at every checkpoint and at the end. Steps <= `skip_through` are
    dropped: a resumed run recomputes them exactly and has logged them already."""

    def __init__(self, client: Client, run_id: str, max_pending: int = 2000, flush_seconds: float = 30.0,
                 skip_through: int = -1):
        self.client, self.run_id, self.max_pending = client, run_id, max_pending
        self.flush_seconds, self.skip_through = flush_seconds, skip_through
        self.pending: list[Metric] = []
        self._last_flush = time.monotonic()

    def add(self, step: int, values: Mapping[str, float]) -> None:
        if step <= self.skip_through:
            return
        now = int(time.time() * 1000)
        self.pending += [Metric(k, float(v), now, int(step)) for k, v in values.items()]
        if len(self.pending) >= self.max_pending or time.monotonic() - self._last_flush >= self.flush_seconds:
            self.flush()

    def extend(self, items: Iterable[tuple[int, Mapping[str, float]]]) -> None:
        for step, values in items:
            self.add(step, values)

    def flush(self) -> None:
        self._last_flush = time.monotonic()
        if self.pending:
            self.client.log_batch(self.run_id, metrics=self.pending)
            self.pending = []


def last_logged_step(client: Client, run_id: str, keys: Iterable[str]) -> int:
    """The highest step logged for any of `keys` (-1 if none)."""
    steps = [m.step for k in keys for m in client.get_metric_history(run_id, k)]
    return max(steps, default=-1)


def runs_page_url(experiment_id: str, host: str = "127.0.0.1", port: int = 5000) -> str:
    return f"http://{host}:{port}/#/experiments/{experiment_id}/runs"
