"""The models a study export carries (`python -m reports export --study NAME --with-models [--models-at N ...]`), so
that a study's trained models outlive the machine of its MLflow store and can be evaluated anew elsewhere.

Per run: artifacts/<run_id>/weights_at/<iteration>/weights.pt (stm.training.weights: the state dict as float32, the
model and train configs, no optimiser, RNG or history; the same weights give the same bytes) for each finished
cell's final model and for the checkpoints it kept (checkpoint_at/, StudyConfig.keep_checkpoints) at the iterations
of --models-at, plus the run's config/config.json (canonical JSON), which an evaluation reads. runs.json lists them
among the run's artifacts with their sha256, and records the choice as {"models": {"at": [N, ...]}}.

The choice is remembered: a later export into the same folder carries models as the earlier one did (its --models-at
joins the earlier iterations), and refuses to go on if the store no longer holds a model the earlier export
carries, rather than drop it from git. Imported (reports.data.studyimport), the weights become the run's artifacts
at the same paths, where `python -m experiments milestones` finds and evaluates them; an export of such a store
takes its models from there, byte for byte.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from experiments.cell_run import CHECKPOINT_DIR, CHECKPOINT_NAME, KEPT_CHECKPOINT_DIR, WEIGHTS_DIR, WEIGHTS_NAME
from reports.data.export import RUNS_FILE, ExportError, dumps

MODELS_KEY = "models"  # runs.json: {"at": [iterations]} when the export carries models
CONFIG_FILE = "config/config.json"  # a cell's resolved config: what its evaluation reads
FINAL_ITERATION = "train/iterations"  # a finished cell's metric: the iteration of its final model


@dataclass(frozen=True)
class ModelChoice:
    """Every finished cell's final model, and the kept checkpoints at these iterations."""

    at: tuple[int, ...] = ()


def weights_path(iteration: int) -> str:
    return f"{WEIGHTS_DIR}/{iteration}/{WEIGHTS_NAME}"


def earlier_export(folder: Path) -> dict | None:
    """The runs.json of the export already in `folder`, or None (none, or unreadable: it is replaced whole)."""
    try:
        doc = json.loads((folder / RUNS_FILE).read_text())
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None


def model_choice(with_models: bool, models_at: list[int] | None, earlier: dict | None) -> ModelChoice | None:
    """What the export carries: models when asked now or when the earlier export carried them (its iterations and
    today's together); None: no models."""
    before = earlier.get(MODELS_KEY) if earlier else None
    if not with_models and not isinstance(before, dict):
        return None
    at = {int(i) for i in (before or {}).get("at", [])} | set(models_at or [])
    return ModelChoice(tuple(sorted(at)))


def _by_iteration(paths: list[str], name: str) -> dict[int, str]:
    """<folder>/<iteration>/<name> artifact paths by iteration."""
    out = {}
    for p in paths:
        parts = p.split("/")
        if len(parts) == 3 and parts[1].isdigit() and parts[2] == name:
            out[int(parts[1])] = p
    return out


def held_iterations(exporter, run_id: str) -> set[int]:
    """The iterations of the models a run holds besides its resume checkpoint: the checkpoints it kept and the
    weights imported with it. `exporter`: reports.data.export's, for its listing."""
    return (set(_by_iteration(exporter.listed(run_id, KEPT_CHECKPOINT_DIR), CHECKPOINT_NAME))
            | set(_by_iteration(exporter.listed(run_id, WEIGHTS_DIR), WEIGHTS_NAME)))


def run_models(exporter, run, choice: ModelChoice, tmp: Path) -> dict[str, bytes]:
    """The model files of one run as exported bytes ({} without models): weights_at/<iteration>/weights.pt from the
    run's weights (imported earlier), kept checkpoints or, for the final model, its resume checkpoint; and its
    config. `exporter`: reports.data.export's, for its listing and client."""
    from stm.training.checkpoint import CheckpointError
    from stm.training.weights import weights_file_bytes

    rid = run.info.run_id
    weights = _by_iteration(exporter.listed(rid, WEIGHTS_DIR), WEIGHTS_NAME)
    kept = _by_iteration(exporter.listed(rid, KEPT_CHECKPOINT_DIR), CHECKPOINT_NAME)
    sources = {it: weights.get(it) or kept[it] for it in choice.at if it in weights or it in kept}
    final = run.data.metrics.get(FINAL_ITERATION)
    if run.info.status == "FINISHED" and final is not None and run.data.tags.get("role") == "cell":
        final = int(final)
        resume = [p for p in exporter.listed(rid, CHECKPOINT_DIR) if Path(p).name == CHECKPOINT_NAME]
        source = weights.get(final) or kept.get(final) or next(iter(resume), None)
        if source is None:
            raise ExportError(f"finished run {run.info.run_name or rid} has no final model in the store "
                              f"({CHECKPOINT_DIR}/{CHECKPOINT_NAME} or {weights_path(final)})")
        sources[final] = source
    out = {}
    for it, path in sorted(sources.items()):
        local = Path(exporter.client.download_artifacts(rid, path, str(tmp / rid / str(it))))
        try:
            data, iteration = weights_file_bytes(local)
        except CheckpointError as exc:
            raise ExportError(f"model {path} of run {rid}: {exc}") from None
        if iteration != it:
            raise ExportError(f"model {path} of run {rid} holds iteration {iteration}, not {it}")
        out[weights_path(it)] = data
    if out:
        try:
            config = Path(exporter.client.download_artifacts(rid, CONFIG_FILE, str(tmp / rid / "config")))
            out[CONFIG_FILE] = (dumps(json.loads(config.read_text())) + "\n").encode()
        except Exception as exc:  # noqa: BLE001 - missing from the store, or not JSON
            raise ExportError(f"run {rid} has models but no readable {CONFIG_FILE} "
                              f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
    return out


def _models(doc: dict) -> set[tuple[str, str]]:
    """(run name, weights path) of every model an export's runs.json lists."""
    return {(str(r.get("run_name")), p) for r in doc.get("runs", []) if isinstance(r, dict)
            for p in r.get("artifacts", {}) if p.startswith(f"{WEIGHTS_DIR}/")}


def check_models(doc: dict, choice: ModelChoice | None, earlier: dict | None, folder: Path) -> int:
    """How many models the export (runs.json `doc`) carries; an ExportError when it was asked for models none of its
    cells has, or when it would drop a model the earlier export in `folder` carries."""
    mine = _models(doc)
    if choice is None:
        return 0
    found = {int(p.split("/")[1]) for _, p in mine}
    missing = [it for it in choice.at if it not in found]
    if missing:
        raise ExportError(f"no cell of study {doc['study_name']!r} kept a checkpoint at iteration {missing[0]} "
                          f"({KEPT_CHECKPOINT_DIR}/{missing[0]}/); choose --models-at among the kept ones")
    if not mine:
        raise ExportError(f"study {doc['study_name']!r} has no models to export: no finished cell, and no kept "
                          "checkpoint chosen by --models-at")
    dropped = sorted(_models(earlier or {}) - mine)
    if dropped:
        name, path = dropped[0]
        raise ExportError(f"the export in {folder} carries {len(dropped)} model(s) the store no longer holds "
                          f"(e.g. {path} of {name}); export into another --out, or delete that folder to drop them")
    return len(mine)
