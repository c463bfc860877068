"""Build one study's report: tables + figures into <out>/<study>/ (the study's name, checked to stay inside <out>),
index.html, artifacts of the parent run. A build removes only what the previous build wrote there (MANIFEST)."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import matplotlib.pyplot as plt

from experiments.runtime.backend_internals import artifact_repository
from experiments.runtime.study_names import inside, study_folder
from reports.data.store import Study
from reports.plotting import FigureResult
from reports.study_report import ablation_figures, control_report, sweep_summary, table_one, tables, trajectories
from reports.study_report.html import study_index
from reports.study_report.tables import Table

log = logging.getLogger(__name__)

ARTIFACT_PATH = "report"  # folder of the parent run's artifacts that holds the report
MANIFEST = ".report-files"  # in a study's report folder: the files the last build wrote there, one path a line


@dataclass
class Report:
    study: Study
    folder: Path
    index: Path
    tables: list[Table]
    figures: list[FigureResult]
    seconds: float

    @property
    def gaps(self) -> list[str]:
        return [f"{f.name}: {f.gap}" for f in self.figures if f.gap]


def nothing_to_report(study: Study) -> str | None:
    """Why the study has nothing a report could show (no finished run), or None when it has."""
    ch = study.children
    if study.kind in ("smoothing", "idm"):  # one run, no children: its own metrics are the report
        if any(k.startswith("metrics.") and v is not None for k, v in study.parent.items()):
            return None
        return f"{study.kind} study {study.name!r} logged no metric (run {study.parent.get('status') or '?'})"
    done = ("FINISHED", "KILLED") if study.kind == "sweep" else ("FINISHED",)  # a pruned trial is KILLED
    if ch["status"].isin(done).any():
        return None
    counts = ", ".join(f"{n} {s}" for s, n in ch["status"].value_counts().sort_index().items()) or "no child run"
    return f"{study.kind} study {study.name!r} has no finished run ({counts})"


def _figure(name: str, build: Callable[[], FigureResult]) -> FigureResult:
    """One figure; data the builder did not foresee makes it a gap of the report, not the end of it."""
    try:
        return build()
    except Exception as exc:  # noqa: BLE001
        log.warning("figure %s failed", name, exc_info=True)
        plt.close("all")
        return FigureResult(name, name, gap=f"could not be drawn: {type(exc).__name__}: {exc}")


def _ablation_parts(study: Study, folder: Path) -> tuple[list[Table], list[FigureResult]]:
    """In RESULTS.md's order: Table I, the paper's comparisons, the circles, the compute, then the extended success
    table and the metric dump."""
    from reports.results.paper_claims import claims_rows, claims_table  # the comparisons RESULTS.md quotes too

    success = tables.success_summary(study)
    circle = tables.circle_summary(study)
    train = tables.train_time_summary(study)
    sources = table_one.own_sources(study)
    rows = table_one.table_one_rows(sources)
    tabs = [table_one.table_one_table(rows, sources), claims_table(claims_rows(sources)),
            tables.circle_table(circle, study), tables.train_time_table(train, study),
            tables.paper_success_table(success, study), tables.generic_metrics_table(study)]
    figs = [_figure(table_one.NAME, lambda: table_one.table_one_figure(rows, folder)),
            _figure("success_bars", lambda: ablation_figures.success_bars(success, study, folder)),
            _figure("circles", lambda: trajectories.circles(study, folder)),
            _figure("compute_time", lambda: ablation_figures.compute_time(study, folder)),
            _figure("train_time", lambda: ablation_figures.train_time(train, study, folder)),
            _figure("training_curves", lambda: ablation_figures.training_curves(study, folder)),
            _figure("tip_paths", lambda: trajectories.tip_paths(study, folder)),
            _figure("changing_goal", lambda: trajectories.changing_goal(study, folder))]
    return tabs, figs


def _sweep_parts(study: Study, folder: Path) -> tuple[list[Table], list[FigureResult]]:
    tabs = [tables.generic_metrics_table(study)]
    figs = [_figure("sweep_history", lambda: sweep_summary.sweep_history(study, folder)),
            _figure("sweep_params", lambda: sweep_summary.sweep_params(study, folder)),
            _figure("sweep_intermediate", lambda: sweep_summary.sweep_intermediate(study, folder)),
            _figure("sweep_importance", lambda: sweep_summary.sweep_importance(study, folder))]
    return tabs, figs


def _files(folder: Path) -> set[Path]:
    return {p for p in folder.rglob("*") if p.is_file()} if folder.is_dir() else set()


def _clear(folder: Path) -> None:
    """Remove the files an earlier build wrote, so that a figure that became a gap does not linger: those its
    manifest lists, each checked to lie in the folder; anything else there (a file of the user's, a report
    from before manifests) is left alone."""
    manifest = folder / MANIFEST
    if not manifest.is_file():
        return
    for rel in manifest.read_text().splitlines():
        if rel:
            path = inside(folder, folder / rel)
            if path.is_file():
                path.unlink()
    manifest.unlink()


def _write_manifest(folder: Path, ours: set[Path]) -> None:
    base = folder.resolve()
    rels = sorted({p.resolve().relative_to(base).as_posix() for p in ours if base in p.resolve().parents})
    (folder / MANIFEST).write_text("".join(f"{rel}\n" for rel in rels))


def _log_report(study: Study, folder: Path) -> None:
    """Copy the report to the parent run's artifacts under report/, replacing an earlier copy (only that
    folder, which only this module writes) so that the copy matches the folder exactly."""
    try:
        repo = artifact_repository(study.client.get_run(study.run_id).info.artifact_uri)
        try:
            repo.delete_artifacts(ARTIFACT_PATH)
        except NotImplementedError:  # some artifact stores cannot delete: files are then overwritten only
            pass
        study.client.log_artifacts(study.run_id, str(folder), ARTIFACT_PATH)
    except Exception as exc:  # noqa: BLE001 - the files on disk are the report; the upload is a copy
        log.warning("could not log the report as artifacts of run %s: %s", study.run_id, exc)


def build_report(study: Study, out_root: Path, log_artifacts: bool = True) -> Report:
    start = time.perf_counter()
    folder = study_folder(out_root, study.name)  # out_root/<name>, resolved inside out_root
    _clear(folder)
    folder.mkdir(parents=True, exist_ok=True)
    before = _files(folder)
    parts = {"sweep": _sweep_parts, "smoothing": control_report.parts, "idm": control_report.parts}.get(
        study.kind, _ablation_parts)
    tabs, figs = parts(study, folder)
    written = {p for t in tabs for p in t.write(folder)}
    seconds = time.perf_counter() - start
    index = study_index(study, folder, tabs, figs, seconds)
    # what this build wrote: the next build removes exactly these (a figure a builder saved before it failed too)
    _write_manifest(folder, {*written, *(p for f in figs for p in f.paths), index, *(_files(folder) - before)})
    if log_artifacts:
        _log_report(study, folder)
    return Report(study, folder, index, tabs, figs, time.perf_counter() - start)
