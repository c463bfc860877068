"""A study export (reports.data.export) back into an MLflow store, through MLflow's client API.

    python -m reports import reports/studies/<slug> [...] [--tracking-uri URI]

The export is validated whole first (its runs.json, its records against their digest, and every artifact against its
sha256): a corrupt, partial or edited export is one line naming what is wrong, and nothing is written. An export of
the format before the digest (acrmdn-study-export/1, reports.data.export.FORMAT_UNVERIFIED) is read as it is: its
records are unverified, which the import says. Then the runs are created in the experiment of
the study's kind (created if missing): the original start times, run names, params, tags, metric histories (steps
and timestamps), artifacts, status and end time; each child's
parent link points to the new parent run, and every run keeps its original id in tag `export.run_id` (reports
show that id). A run that fails midway deletes the runs it created.

A cell's claim (experiments/runtime/claims.py: its `claim.<n>` params and beat tag) is left behind: it names a
process of the exporting store, and a snapshot's unfinished cells (reports.data.export) are to be resumed here.

An export that carries models (`reports export --with-models`) brings each as the run's artifact
weights_at/<iteration>/weights.pt, with its config/config.json: `python -m experiments milestones --study NAME` then
evaluates them in this store as it evaluates kept checkpoints in the original one.

Importing twice does not duplicate: a study whose parent carries the same export digest (the sha256 of runs.json)
is skipped; a different study of the same study_name already in the store is an error (exit 2): import it into
another store.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from experiments.runtime.claims import BEAT_TAG, CLAIM
from experiments.runtime.study_names import RULE, is_study_name, shown
from experiments.runtime.tracking import PARENT_TAG, Client, get_or_create_experiment, sqlite_path
from reports.data.export import FORMAT, FORMATS, RECORDS_KEY, RUN_NAME_TAG, RUNS_FILE, ExportError, records_digest
from reports.data.store import SOURCE_RUN_TAG, Store

DIGEST_TAG = "export.digest"  # on the imported parent: the sha256 of the runs.json it came from
RUN_KEYS = {"run_id": str, "run_name": (str, type(None)), "status": str, "start_time": int,
            "end_time": (int, type(None)), "parent_run_id": (str, type(None)), "params": dict, "tags": dict,
            "metrics": dict, "histories": dict, "artifacts": dict}
BATCH = 500  # MLflow takes at most 1000 metrics or 100 params per log_batch


def _fail(folder: Path, what: str) -> ExportError:
    return ExportError(f"{folder}: not a valid study export: {what}")


def read_export(folder: Path) -> tuple[dict, str]:
    """The export's runs.json, checked (fields, one parent, parent links, artifacts present with their sha256),
    and its digest."""
    try:
        raw = (folder / RUNS_FILE).read_bytes()
        doc = json.loads(raw)
    except OSError as exc:
        raise _fail(folder, f"cannot read {RUNS_FILE} ({exc.strerror or exc})") from None
    except ValueError as exc:
        raise _fail(folder, f"{RUNS_FILE} is not JSON ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") not in FORMATS:
        raise _fail(folder, f"{RUNS_FILE} is not of format {' or '.join(FORMATS)}")
    for key in ("study_name", "experiment"):
        if not isinstance(doc.get(key), str) or not doc[key]:
            raise _fail(folder, f"no {key}")
    if not is_study_name(doc["study_name"]):
        raise _fail(folder, f"study_name {shown(doc['study_name'])}: {RULE}")
    if doc["format"] == FORMAT and doc.get(RECORDS_KEY) != records_digest(doc):
        raise _fail(folder, f"its records do not match their digest ({RECORDS_KEY}): {RUNS_FILE} was edited after "
                    "the export")
    runs = doc.get("runs")
    if not isinstance(runs, list) or not runs:
        raise _fail(folder, "no runs")
    for i, run in enumerate(runs):
        bad = [k for k, t in RUN_KEYS.items() if not isinstance(run, dict) or not isinstance(run.get(k), t)]
        if bad:
            raise _fail(folder, f"run {i} lacks or mistypes {', '.join(bad)}")
        for key, hist in run["histories"].items():
            pts = hist.get("points") if isinstance(hist, dict) else None
            if not isinstance(pts, list) or not all(isinstance(p, list) and len(p) == 3 and
                                                    all(isinstance(x, int | float) for x in p) for p in pts):
                raise _fail(folder, f"run {run['run_id']}: bad history of {key}")
        if not all(isinstance(v, int | float) for v in run["metrics"].values()) or \
                not all(isinstance(v, str) for v in (*run["params"].values(), *run["tags"].values())):
            raise _fail(folder, f"run {run['run_id']}: a metric that is not a number, or a param or tag not text")
    ids = [r["run_id"] for r in runs]
    if len(set(ids)) != len(ids):
        raise _fail(folder, "a run id appears twice")
    parent = runs[0]
    if parent["parent_run_id"] is not None or parent["tags"].get("study_name") != doc["study_name"]:
        raise _fail(folder, "the first run is not the study's parent run")
    for run in runs[1:]:
        if run["parent_run_id"] not in ids[:ids.index(run["run_id"])]:
            raise _fail(folder, f"run {run['run_id']} has no parent before it in the export")
    for run in runs:
        for path, digest in run["artifacts"].items():
            local = _artifact(folder, run, path)
            if not local.is_file():
                raise _fail(folder, f"missing artifact {local.relative_to(folder)}")
            if hashlib.sha256(local.read_bytes()).hexdigest() != digest:
                raise _fail(folder, f"artifact {local.relative_to(folder)} does not match its sha256")
    return doc, hashlib.sha256(raw).hexdigest()


def _artifact(folder: Path, run: dict, path: str) -> Path:
    local = (folder / "artifacts" / run["run_id"] / path)
    if ".." in Path(path).parts or Path(path).is_absolute():
        raise _fail(folder, f"artifact path {path!r} leaves the export")
    return local


def _existing(uri: str, experiment: str, study_name: str) -> dict[str, Any] | None:
    """The parent run of `study_name` in the store (a row of Store.parents), or None."""
    db = sqlite_path(uri)
    if db is not None and not db.exists():
        return None  # a new store
    parents = Store(uri).parents()
    if parents.empty or "tags.study_name" not in parents:
        return None
    hit = parents[(parents["tags.study_name"] == study_name) & (parents["experiment"] == experiment)]
    return hit.iloc[0].to_dict() if len(hit) else None


def _points(run: dict) -> list[tuple[str, float, int, int]]:
    """The run's metric points (key, value, timestamp, step): its histories, and a latest value without one."""
    out = []
    for key, hist in sorted(run["histories"].items()):
        out += [(key, float(v), int(ts), int(step)) for step, ts, v in hist["points"]]
    for key, value in sorted(run["metrics"].items()):  # a latest value without history (not written by MLflow)
        if key not in run["histories"]:
            out.append((key, float(value), int(run["end_time"] or run["start_time"]), 0))
    return out


def _create(client: Client, exp_id: str, run: dict, folder: Path, new_ids: dict[str, str], digest: str) -> str:
    from mlflow.entities import Metric, Param

    # a cell's claim names a process of the exporting store: here the run is free to be resumed (a snapshot)
    tags = {k: v for k, v in run["tags"].items() if k != BEAT_TAG} | {SOURCE_RUN_TAG: run["run_id"]}
    if run["parent_run_id"] is None:
        tags[DIGEST_TAG] = digest
    else:
        tags[PARENT_TAG] = new_ids[run["parent_run_id"]]
    tags.pop(RUN_NAME_TAG, None)
    rid = client.create_run(exp_id, start_time=run["start_time"], tags=tags, run_name=run["run_name"]).info.run_id
    new_ids[run["run_id"]] = rid
    params = [Param(k, str(v)) for k, v in sorted(run["params"].items()) if not k.startswith(CLAIM)]
    for i in range(0, len(params), 100):
        client.log_batch(rid, params=params[i:i + 100])
    metrics = [Metric(*point) for point in _points(run)]
    for i in range(0, len(metrics), BATCH):
        client.log_batch(rid, metrics=metrics[i:i + BATCH])
    for path in sorted(run["artifacts"]):
        parent = str(Path(path).parent)
        client.log_artifact(rid, str(_artifact(folder, run, path)), None if parent == "." else parent)
    if run["status"] not in ("RUNNING", "SCHEDULED"):
        client.set_terminated(rid, run["status"], run["end_time"])
    return rid


def plan(folder: Path, uri: str) -> tuple[dict, str, bool]:
    """The validated export, its digest, and whether the store still lacks it (False: imported before); a
    different study of the same name in the store is an ExportError."""
    doc, digest = read_export(folder)
    existing = _existing(uri, doc["experiment"], doc["study_name"])
    if existing is not None and existing.get(f"tags.{DIGEST_TAG}") != digest:
        raise ExportError(f"study {doc['study_name']!r} is already in {uri} (parent run {existing['run_id']}) with "
                          "other content; import into another store")
    return doc, digest, existing is None


def import_study(folder: Path, uri: str, doc: dict, digest: str) -> None:
    """Import one validated export (plan) into the store at `uri` (created if missing)."""
    client = Client(uri)
    exp_id = get_or_create_experiment(client, doc["experiment"])
    new_ids: dict[str, str] = {}
    try:
        for run in doc["runs"]:
            _create(client, exp_id, run, folder, new_ids, digest)
    except Exception as exc:
        for rid in new_ids.values():  # nothing half-imported: the runs created so far go
            client.delete_run(rid)
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ExportError(f"import of {folder} failed ({first}); the {len(new_ids)} run(s) it created were "
                          "deleted") from None


def export_folders(root: Path) -> list[Path]:
    """The export folders in `root` (or `root` itself when it is one), sorted."""
    if (root / RUNS_FILE).is_file():
        return [root]
    found = sorted(p.parent for p in root.glob(f"*/{RUNS_FILE}")) if root.is_dir() else []
    if not found:
        raise ExportError(f"no study exports (*/{RUNS_FILE}) in {root}")
    return found


def import_exports(paths: list[Path], uri: str) -> list[tuple[Path, dict, bool]]:
    """Every export in `paths` (export folders, or folders of them) into the store, all validated and checked
    against the store before the first is imported: (folder, runs.json, imported now)."""
    plans = [(f, *plan(f, uri)) for p in paths for f in export_folders(p)]
    names = [doc["study_name"] for _, doc, _, _ in plans]
    dup = next((n for n in names if names.count(n) > 1), None)
    if dup is not None:
        raise ExportError(f"two exports of study {dup!r} among {', '.join(map(str, paths))}")
    for folder, doc, digest, new in plans:
        if new:
            import_study(folder, uri, doc, digest)
    return [(folder, doc, new) for folder, doc, _, new in plans]
