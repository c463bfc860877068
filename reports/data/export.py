"""A compact export of one study, kept in the repository (reports/studies/<name>/) so that RESULTS.md regenerates
on a machine that does not have the study's MLflow store (reports.data.studyimport reads it back into a store).

    python -m reports export --study NAME_OR_RUN_ID [--tracking-uri URI] [--out reports/studies]
                             [--with-models [--models-at N ...]] [--with-checkpoints]

An export folder holds:
    runs.json   the study's parent run first, then every run below it (children, any depth) by start time; per
                run: run_id (the original id), run_name, status, start_time and end_time (epoch ms),
                parent_run_id (original id; null for the parent), params, tags, metrics (latest values),
                histories (every metric key: [[step, timestamp ms, value], ...] sorted, thinned as
                HISTORY_NOTE says) and artifacts (path -> sha256 of the exported file); plus format,
                study_name, experiment (the study kind), and models ({"at": [N, ...]}) where it carries models;
                records_sha256, the digest of all the above (records_digest), which the import checks: a record
                edited after the export is refused (format acrmdn-study-export/2; /1 exports have none).
    artifacts/<run_id>/rollouts/<task>.npz, rollouts/ik_timing.json and rollouts/modes/<task>.json (mode use per
                episode, experiments.mode_repeats): the artifacts the reports read; nothing else (no checkpoints
                or figures, and models only as below). Float arrays are stored as float32.

Models travel with an export on request (`--with-models`, reports.data.export_models): each finished cell's final
model and, with `--models-at N ...`, the checkpoints its cells kept at those iterations, as weights alone
(artifacts/<run_id>/weights_at/<N>/weights.pt, stm.training.weights: float32 state dict and configs, read with
torch.load(weights_only=True), a few MB each; the same weights give the same bytes) with the run's
config/config.json. The choice is remembered: a later plain export of the study carries the same models (and those
of new finished cells), and refuses to drop one the store no longer holds. Imported into a fresh store, the study's
models are evaluated anew by `python -m experiments milestones --study NAME [--iterations N ...] [--feedback MODE]`
exactly as they are from the original store.

A snapshot (`--with-checkpoints`) is an export that can also be trained on: each unfinished cell's resume
checkpoint (checkpoint/model.pt: weights, optimiser, RNG state, history) comes along byte for byte, and every
checkpoint a cell kept (checkpoint_at/<iteration>/) as its model alone (weights_at/<iteration>/weights.pt, as
`--with-models` writes them: a third of the bytes). Imported into a store elsewhere (reports.data.studyimport), the
same study command resumes every cell where it stopped and the milestones command evaluates the kept models.
Snapshots weigh megabytes per cell: they go to SNAPSHOTS (ignored by git), never to the committed exports.

The folder is ROOT/<study name> (the study name rule of experiments.runtime.study_names makes the name a folder name;
resolved, it must lie inside ROOT). An export replaces only an earlier export of the same study there (its runs.json
names the study) and deletes only the files that earlier runs.json listed; a folder holding anything else is an
error, and nothing is written.

The export is deterministic (sorted keys, fixed zip dates, canonical JSON): re-exporting an unchanged study gives
the same bytes, and a diff shows what changed. It names no path of this machine: tags that hold one
(mlflow.source.name, ...) and any param or tag whose value contains the store's folder, the working directory,
the home or the temporary directory are left out (listed in runs.json under `dropped`).
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import tempfile
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from envs.fileio import atomic_write_bytes
from experiments.cell_run import CHECKPOINT_DIR, CHECKPOINT_NAME
from experiments.mode_repeats import MODES_DIR
from experiments.runtime.study_names import inside, study_folder
from experiments.runtime.tracking import PARENT_TAG, store_dir
from reports.data.store import Store, Study

FORMAT = "acrmdn-study-export/2"  # /2: runs.json carries RECORDS_KEY, the digest of its records
# /1: exports written before the digest (the committed ones among them): read and imported as they are, their records
# unverified. A digest added to them now would certify nothing about edits made before it, so they get none: the
# format says which exports are verified
FORMAT_UNVERIFIED = "acrmdn-study-export/1"
FORMATS = (FORMAT, FORMAT_UNVERIFIED)
RECORDS_KEY = "records_sha256"
RUNS_FILE = "runs.json"
ARTIFACTS = "artifacts"
DEFAULT_EXPORTS = Path("reports/studies")
SNAPSHOTS = Path("snapshots")  # exports with checkpoints: out of git
MAX_HISTORY = 200  # points per metric history: the training curves need no more, and runs.json stays small
HISTORY_NOTE = (f"a metric history longer than {MAX_HISTORY} points keeps every k-th point in (step, timestamp) "
                f"order, k = ceil(n / {MAX_HISTORY}), and always its last one (MLflow's latest value); "
                "thinned_from gives n for those")
RUN_NAME_TAG = "mlflow.runName"
# tags that hold paths or the machine's state, never needed by a report
DROPPED_TAGS = ("mlflow.source.name", "mlflow.source.git.repoURL", "mlflow.log-model.history",
                "mlflow.databricks.notebookPath")
ROLLOUT_FILES = ("rollouts/ik_timing.json",)  # besides rollouts/*.npz


class ExportError(Exception):
    """A bad export or import (one line, exit code 2)."""


# ------------------------------------------------------------------------------------------------ writing
def dumps(obj: Any, indent: int = 0) -> str:
    """JSON with sorted keys, one line per key and per list of lists item (a history point), scalars and lists of
    scalars inline: compact, and line-based diffs stay readable."""
    pad = " " * (indent + 1)
    if isinstance(obj, dict) and obj:
        items = [f"{pad}{json.dumps(k)}: {dumps(v, indent + 1)}" for k, v in sorted(obj.items())]
        return "{\n" + ",\n".join(items) + "\n" + " " * indent + "}"
    if isinstance(obj, list) and any(isinstance(v, dict | list) for v in obj):
        return "[\n" + ",\n".join(pad + dumps(v, indent + 1) for v in obj) + "\n" + " " * indent + "]"
    return json.dumps(obj, separators=(", ", ": "))


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """np.savez_compressed's format with float arrays as float32 and fixed member dates (the same bytes for the
    same arrays; numpy stamps the current time)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for name in sorted(arrays):
            arr = arrays[name]
            if arr.dtype.kind == "f" and arr.dtype.itemsize > 4:
                arr = arr.astype(np.float32)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            with zf.open(info, "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.ascontiguousarray(arr), allow_pickle=False)
    return buf.getvalue()


def thin(points: list[list]) -> tuple[list[list], int | None]:
    """The history as exported (HISTORY_NOTE), and its original length when thinned."""
    n = len(points)
    if n <= MAX_HISTORY:
        return points, None
    k = math.ceil(n / MAX_HISTORY)
    keep = list(range(0, n, k))
    if keep[-1] != n - 1:
        keep.append(n - 1)
    return [points[i] for i in keep], n


def _sort_key(point: list) -> tuple:
    step, ts, value = point
    return step, ts, -math.inf if math.isnan(value) else value  # MLflow's order for the latest value


# ------------------------------------------------------------------------------------------------ reading
class _Exporter:
    def __init__(self, store: Store, study: Study, checkpoints: bool = False, models=None):
        self.store, self.study, self.client = store, study, store.client
        self.checkpoints = checkpoints
        self.models = models  # reports.data.export_models.ModelChoice, or None: no models
        self.roots = _machine_roots(store.uri)
        self.dropped: set[str] = set()
        self.snapshot_at: set[int] = set()  # the iterations of the checkpoints a snapshot's runs kept

    def runs(self) -> list:
        """The parent run, then every run below it (any depth), by start time and id."""
        parent = self.client.get_run(self.study.run_id)
        found, todo = [], [parent.info.run_id]
        while todo:
            rid = todo.pop()
            kids = self.store.search([parent.info.experiment_id], f"tags.`{PARENT_TAG}` = '{rid}'")
            found += kids
            todo += [k.info.run_id for k in kids]
        found.sort(key=lambda r: (r.info.start_time or 0, r.info.run_id))
        return [parent, *found]

    def portable(self, kind: str, values: dict[str, str]) -> dict[str, str]:
        out = {}
        for key, value in values.items():
            if key in (PARENT_TAG, RUN_NAME_TAG):  # kept as parent_run_id and run_name
                continue
            if (kind == "tag" and key in DROPPED_TAGS) or any(r in str(value) for r in self.roots):
                self.dropped.add(f"{kind} {key}")
                continue
            out[key] = value
        return out

    def histories(self, run_id: str, keys) -> dict[str, dict]:
        out = {}
        for key in sorted(keys):
            pts = sorted(([m.step, m.timestamp, m.value] for m in self.client.get_metric_history(run_id, key)),
                         key=_sort_key)
            pts, n = thin(pts)
            out[key] = {"points": pts, **({"thinned_from": n} if n else {})}
        return out

    def listed(self, run_id: str, folder: str) -> list[str]:
        """The files under an artifact folder of the run, any depth."""
        try:
            found, todo = [], [folder]
            while todo:
                for f in self.client.list_artifacts(run_id, todo.pop()):
                    (todo if f.is_dir else found).append(f.path)
            return sorted(found)
        except Exception as exc:  # noqa: BLE001 - an unreachable artifact store
            raise ExportError(f"cannot list the artifacts of run {run_id}: {str(exc).splitlines()[0]}") from None

    def resume_checkpoint(self, run, tmp: Path) -> dict[str, bytes]:
        """A snapshot's resume checkpoint of a run, byte for byte, unless the run FINISHED."""
        if run.info.status == "FINISHED":
            return {}
        paths = [p for p in self.listed(run.info.run_id, CHECKPOINT_DIR) if Path(p).name == CHECKPOINT_NAME]
        return {p: Path(self.client.download_artifacts(run.info.run_id, p, str(tmp))).read_bytes() for p in paths}

    def model_choice(self, run):
        """The models of a run: the export's choice and, in a snapshot, every checkpoint the run kept (and every
        model imported with it), as weights alone: a kept checkpoint is evaluated, never trained on, and its
        optimiser state would triple a snapshot."""
        from reports.data.export_models import ModelChoice, held_iterations

        if not self.checkpoints:
            return self.models
        kept = held_iterations(self, run.info.run_id)
        at = set(self.models.at if self.models else ()) | kept
        self.snapshot_at |= kept
        return ModelChoice(tuple(sorted(at))) if at or self.models else None

    def artifacts(self, run_id: str, tmp: Path) -> dict[str, bytes]:
        """rollouts/*.npz (float32), rollouts/ik_timing.json and rollouts/modes/*.json (canonical JSON) of a run, as
        exported bytes."""
        listed = self.listed(run_id, "rollouts")
        out = {}
        for path in sorted(p for p in listed if p.endswith(".npz") or p in ROLLOUT_FILES
                           or (p.startswith(f"{MODES_DIR}/") and p.endswith(".json"))):
            local = Path(self.client.download_artifacts(run_id, path, str(tmp)))
            try:
                if path.endswith(".npz"):
                    with np.load(local, allow_pickle=False) as z:
                        out[path] = npz_bytes({k: z[k] for k in z.files})
                else:
                    out[path] = (dumps(json.loads(local.read_text())) + "\n").encode()
            except (OSError, ValueError, zipfile.BadZipFile) as exc:
                raise ExportError(f"unreadable artifact {path} of run {run_id}: {exc}") from None
        return out

    def export(self) -> tuple[dict, dict[str, bytes]]:
        from reports.data.export_models import MODELS_KEY, run_models

        runs, files = [], {}
        with tempfile.TemporaryDirectory(prefix="export-") as tmp:
            for r in self.runs():
                rid = r.info.run_id
                arts = self.artifacts(rid, Path(tmp))
                if self.checkpoints:
                    arts.update(self.resume_checkpoint(r, Path(tmp)))
                models = self.model_choice(r)
                if models is not None:
                    arts.update(run_models(self, r, models, Path(tmp)))
                files.update({f"{ARTIFACTS}/{rid}/{p}": b for p, b in arts.items()})
                runs.append({
                    "run_id": rid, "run_name": r.info.run_name, "status": r.info.status,
                    "start_time": r.info.start_time, "end_time": r.info.end_time,
                    "parent_run_id": r.data.tags.get(PARENT_TAG) if rid != self.study.run_id else None,
                    "params": self.portable("param", r.data.params), "tags": self.portable("tag", r.data.tags),
                    "metrics": dict(r.data.metrics), "histories": self.histories(rid, r.data.metrics),
                    "artifacts": {p: hashlib.sha256(b).hexdigest() for p, b in arts.items()}})
        doc = {"format": FORMAT, "study_name": self.study.name, "experiment": self.study.experiment,
               "history_thinning": HISTORY_NOTE, "dropped": sorted(self.dropped), "runs": runs}
        if self.models is not None or self.snapshot_at:
            doc[MODELS_KEY] = {"at": sorted(set(self.models.at if self.models else ()) | self.snapshot_at)}
        return doc, files


def _machine_roots(uri: str) -> list[str]:
    """Folders of this machine whose paths must not reach an export (long enough not to match ordinary text)."""
    roots = {store_dir(uri).resolve(), Path.cwd().resolve(), Path.home(), Path(tempfile.gettempdir()).resolve()}
    return sorted(str(r) for r in roots if len(r.parts) > 1)


def export_study(store: Store, ident: str, out_root: Path | None = None, checkpoints: bool = False,
                 with_models: bool = False, models_at: list[int] | None = None) -> tuple[Path, dict, int]:
    """Write the export of study `ident` (study_name or parent run id) to out_root/<name>/ (default: DEFAULT_EXPORTS,
    or SNAPSHOTS with `checkpoints`), replacing an earlier export of the study there: the folder, its runs.json and
    its byte size. With `with_models`, or where the earlier export carried models, the models too (export_models)."""
    from reports.data.export_models import check_models, earlier_export, model_choice

    out_root = out_root or (SNAPSHOTS if checkpoints else DEFAULT_EXPORTS)
    if checkpoints and out_root.resolve() == DEFAULT_EXPORTS.resolve():
        raise ExportError(f"a snapshot holds checkpoints (megabytes per cell) and stays out of {DEFAULT_EXPORTS}, "
                          f"which git keeps; choose another --out (default {SNAPSHOTS})")
    study = store.studies(None, ident)[0]
    folder = study_folder(out_root, study.name)  # out_root/<name>, resolved inside out_root
    previous = previous_files(folder, study.name)  # never another study's export, nor a folder that is none
    earlier = earlier_export(folder)  # its models are remembered
    models = model_choice(with_models, models_at, earlier)
    doc, files = _Exporter(store, study, checkpoints, models).export()
    check_models(doc, models, earlier, folder)
    doc[RECORDS_KEY] = records_digest(doc)
    text = dumps(doc) + "\n"
    leaked = [r for r in _machine_roots(store.uri) if r in text]
    if leaked:  # a path in a metric key or a run name: refuse rather than commit it
        raise ExportError(f"the export of {study.name!r} would contain the path {leaked[0]}; rename what holds it")
    for rel, data in files.items():
        atomic_write_bytes(inside(folder, folder / rel), data)
    atomic_write_bytes(folder / RUNS_FILE, text.encode())  # last: it lists (and hashes) the files above
    _remove(folder, previous - {RUNS_FILE, *files})  # what the earlier export listed and this one does not
    return folder, doc, sum((folder / rel).stat().st_size for rel in (RUNS_FILE, *files))


def listed_files(doc: dict) -> set[str]:
    """The files of an export folder its runs.json lists: itself and every run's artifacts."""
    runs = doc.get("runs") if isinstance(doc.get("runs"), list) else []
    return {RUNS_FILE} | {f"{ARTIFACTS}/{r['run_id']}/{p}" for r in runs if isinstance(r, dict)
                          and isinstance(r.get("run_id"), str) and isinstance(r.get("artifacts"), dict)
                          for p in r["artifacts"]}


def previous_files(folder: Path, study_name: str) -> set[str]:
    """The files the export already in `folder` wrote (what a new export of the same study may replace or remove);
    an ExportError when the folder holds something else: another study's export, or anything without a readable
    runs.json (nothing there is ours to overwrite or delete)."""
    if not folder.exists() or (folder.is_dir() and not any(folder.iterdir())):
        return set()
    try:
        doc = json.loads((folder / RUNS_FILE).read_text())
    except (OSError, ValueError):
        raise ExportError(f"{folder} exists and is not a study export (no readable {RUNS_FILE}); move it aside or "
                          "choose another --out") from None
    owner = doc.get("study_name") if isinstance(doc, dict) else None
    if owner != study_name:
        raise ExportError(f"{folder} holds the export of study {owner!r}, not {study_name!r}; move it aside or choose "
                          "another --out")
    return listed_files(doc)


def _remove(folder: Path, stale: set[str]) -> None:
    """Delete the listed files of an earlier export (each checked to lie in the folder), then the folders they
    leave empty, up to the export's own."""
    emptied = set()
    for rel in sorted(stale):
        path = inside(folder, folder / rel)
        if path.is_file():
            path.unlink()
            emptied.update(p for p in path.parents if folder in p.parents)
    for path in sorted(emptied, key=lambda p: len(p.parts), reverse=True):
        if path.is_dir() and not any(path.iterdir()):
            path.rmdir()


def records_digest(doc: dict) -> str:
    """The sha256 of everything runs.json records (every run's params, tags, metrics, histories, status, times and
    artifact hashes, the study's name and kind) but the digest itself, as canonical JSON: written at export, checked
    at import, so that a record edited afterwards is refused. It proves integrity against edits, not authorship:
    whoever edits a record can recompute it."""
    body = {k: v for k, v in doc.items() if k != RECORDS_KEY}
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def size_text(n: int) -> str:
    return f"{n / 1e6:.2f} MB" if n >= 1e5 else f"{n / 1e3:.1f} kB"
