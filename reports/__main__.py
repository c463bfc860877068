"""`python -m reports [--experiment NAME] [--study RUN_ID] [--out DIR]`: regenerate every table and
figure from the MLflow store alone (default: the latest study of each kind).

`python -m reports --results [--ablation NAME_OR_RUN_ID] [--sweep NAME_OR_RUN_ID ...]`: regenerate
reports/RESULTS.md (+ its small PNGs in reports/figures/) from reports/RESULTS.template.md and the store;
`nox -s report -- --results` is the one command (see reports/results/writer.py for the placeholders).
`--results --exports reports/studies` builds it from the study exports in the repository instead of a store.

`python -m reports export --study NAME_OR_RUN_ID [--out reports/studies] [--with-models [--models-at N ...]]
[--with-checkpoints]`: write a study's compact export (with its models' weights on request), or a resumable snapshot
(reports/data/export.py); `python -m reports import FOLDER [...]`: read exports into a store
(reports/data/studyimport.py)."""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

log = logging.getLogger("reports")

DEFAULT_OUT = Path("reports/out")


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line and exit code 2, like every other bad input
        self.exit(2, f"reports: error: {message} (see `python -m reports --help`)\n")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = _Parser(prog="python -m reports", description=__doc__.split("\n\n")[0])
    p.add_argument("--experiment", help="only the latest study of this experiment (study kind), e.g. ablation")
    p.add_argument("--study", help="a parent run id (or study_name) instead of the latest study")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output root; reports go to OUT/<study>/")
    p.add_argument("--tracking-uri", help="MLflow tracking URI (default: $MLFLOW_TRACKING_URI or "
                                          "sqlite:///mlflow.db in the working directory)")
    p.add_argument("--no-log-artifacts", action="store_true", help="do not log the report to the parent run")
    p.add_argument("-v", "--verbose", action="store_true")
    r = p.add_argument_group("RESULTS.md (--results)")
    r.add_argument("--results", action="store_true", help="write RESULTS.md from the template instead of the "
                                                          "per-study reports")
    r.add_argument("--ablation", help="the ablation study (parent run id or study_name; default: the latest)")
    r.add_argument("--sweep", action="extend", nargs="+", metavar="NAME_OR_RUN_ID",
                   help="sweep studies (default: every sweep study, the latest per task)")
    r.add_argument("--template", type=Path, default=Path("reports/RESULTS.template.md"))
    r.add_argument("--results-out", type=Path, default=Path("reports/RESULTS.md"))
    r.add_argument("--figures-dir", type=Path, default=Path("reports/figures"))
    r.add_argument("--exports", type=Path, metavar="DIR", help="build from the study exports in DIR (e.g. "
                   "reports/studies), read directly, instead of --tracking-uri's store")
    args = p.parse_args(argv)
    if not args.results and (args.ablation or args.sweep or args.exports):
        p.error("--ablation, --sweep and --exports select the studies of --results; add --results")
    if args.exports and args.tracking_uri:
        p.error("--exports builds its own store: drop --tracking-uri")
    return args


def parse_export_args(argv: list[str]) -> argparse.Namespace:
    p = _Parser(prog="python -m reports export", description="Write a compact export of one study (its runs' "
                "params, metrics, tags and the rollouts the reports read) to OUT/<study>/ "
                "(see reports/data/export.py).")
    p.add_argument("--study", required=True, metavar="NAME_OR_RUN_ID", help="study_name or parent run id")
    p.add_argument("--tracking-uri", help="MLflow tracking URI (default: $MLFLOW_TRACKING_URI or sqlite:///mlflow.db)")
    p.add_argument("--out", type=Path, help="root of the exports (default: reports/studies; snapshots/ with "
                   "--with-checkpoints)")
    p.add_argument("--with-checkpoints", action="store_true", help="a resumable snapshot: each unfinished cell's "
                   "last checkpoint and every kept checkpoint too (megabytes per cell; kept out of git)")
    p.add_argument("--with-models", action="store_true", help="each finished cell's final model too, as weights "
                   "alone (a few MB per model); remembered: later exports of the study carry them as well")
    p.add_argument("--models-at", type=int, nargs="+", metavar="N", help="with --with-models: also the weights of "
                   "the checkpoints the cells kept at these iterations (keep_checkpoints; default: none)")
    args = p.parse_args(argv)
    if args.models_at and not args.with_models:
        p.error("--models-at chooses the models of --with-models; add --with-models")
    if args.models_at and min(args.models_at) < 1:
        p.error(f"--models-at takes iterations >= 1, got {min(args.models_at)}")
    return args


def parse_import_args(argv: list[str]) -> argparse.Namespace:
    p = _Parser(prog="python -m reports import", description="Recreate exported studies in an MLflow store (a "
                "study already imported from the same export is skipped; see reports/data/studyimport.py).")
    p.add_argument("exports", nargs="+", type=Path, help="export folders, or folders of them")
    p.add_argument("--tracking-uri", help="MLflow tracking URI (default: $MLFLOW_TRACKING_URI or sqlite:///mlflow.db)")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in ("export", "import"):
        logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
        return export_main(parse_export_args(argv[1:])) if argv[0] == "export" else \
            import_main(parse_import_args(argv[1:]))
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    if args.results:
        return results_main(args)
    from experiments.runtime import study_names as names
    from reports.data.store import Store, StoreError
    from reports.study_report.build import build_report, nothing_to_report
    from reports.study_report.html import root_index

    start = time.perf_counter()
    try:
        if args.study is not None:  # a parent run id (hex) obeys the study name rule too
            names.check_study_name(args.study, "--study")
        store = Store(args.tracking_uri)
        studies = store.studies(args.experiment, args.study)
    except (StoreError, names.StudyNameError) as exc:
        print(f"reports: error: {exc}", file=sys.stderr)
        return 2
    # a study the store holds under a name from before the rule has no folder of its own: left out, never cleaned
    empty = {s.run_id: nothing_to_report(s) if names.is_study_name(s.name) else
             f"{s.kind} study {names.shown(s.name)}: its name breaks the rule ({names.RULE})" for s in studies}
    if all(empty.values()):  # nothing to show: say why, and leave no empty output folder behind
        print(f"reports: error: nothing to report: {'; '.join(empty.values())}", file=sys.stderr)
        return 2
    for reason in filter(None, empty.values()):
        print(f"reports: skipped: {reason}", file=sys.stderr)
    studies = [s for s in studies if not empty[s.run_id]]
    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        print(f"reports: error: cannot write to --out {args.out}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    built = []
    for study in studies:
        try:
            report = build_report(study, args.out, log_artifacts=not args.no_log_artifacts)
        except names.UnsafeFolder as exc:
            print(f"reports: error: {exc}", file=sys.stderr)
            return 2
        built.append((study, report.index))
        gaps = f", {len(report.gaps)} gap(s)" if report.gaps else ""
        print(f"{study.kind} study {study.name!r} ({study.profile}): {report.index}{gaps} "
              f"[{report.seconds:.1f} s]")
    root = root_index(args.out, built)
    print(f"index: {root} [{time.perf_counter() - start:.1f} s total]")
    return 0


def _quiet_mlflow() -> None:
    logging.getLogger("mlflow.store.db.utils").setLevel(logging.WARNING)  # "Creating initial MLflow database tables"


def _error(exc: Exception | str) -> int:
    print(f"reports: error: {exc}", file=sys.stderr)
    return 2


def results_main(args: argparse.Namespace) -> int:
    from experiments.runtime.study_names import StudyNameError, check_study_name
    from reports.data.store import Store, StoreError
    from reports.results.writer import ResultsError, write_results

    start = time.perf_counter()
    try:
        for flag, ident in [("--ablation", args.ablation), *(("--sweep", name) for name in args.sweep or [])]:
            if ident is not None:  # a study name or a parent run id (hex): the rule holds for both
                check_study_name(ident, flag)
        if args.exports:
            from reports.data.export_store import ExportStore

            store = ExportStore(args.exports)
        else:
            store = Store(args.tracking_uri)
        out = write_results(store, args.template, args.results_out, args.figures_dir, args.ablation, args.sweep,
                            exports=args.exports)
    except (StoreError, ResultsError, StudyNameError) as exc:
        return _error(exc)
    print(f"results: {out} (figures in {args.figures_dir}) [{time.perf_counter() - start:.1f} s]")
    return 0


def export_main(args: argparse.Namespace) -> int:
    from experiments.cell_run import WEIGHTS_DIR
    from experiments.runtime.study_names import StudyNameError, UnsafeFolder, check_study_name
    from reports.data.export import ExportError, export_study, size_text
    from reports.data.store import Store, StoreError

    start = time.perf_counter()
    try:
        check_study_name(args.study, "--study")  # a study name or a parent run id (hex): the rule holds for both
        folder, doc, size = export_study(Store(args.tracking_uri), args.study, args.out, args.with_checkpoints,
                                         args.with_models, args.models_at)
    except (StoreError, ExportError, StudyNameError, UnsafeFolder) as exc:
        return _error(exc)
    except OSError as exc:
        return _error(f"cannot write the export under {args.out or 'its folder'}: {exc.strerror or exc}")
    if doc["runs"][0]["status"] != "FINISHED" and not args.with_checkpoints:
        print(f"reports: warning: the study's parent run is {doc['runs'][0]['status']}: export it again once it "
              "finished", file=sys.stderr)
    n_art = sum(len(r["artifacts"]) for r in doc["runs"])
    n_models = sum(p.startswith(f"{WEIGHTS_DIR}/") for r in doc["runs"] for p in r["artifacts"])
    models = f", {n_models} models" if n_models else ""
    print(f"export: {folder} ({len(doc['runs'])} runs, {n_art} artifacts{models}, {size_text(size)}) "
          f"[{time.perf_counter() - start:.1f} s]")
    return 0


def import_main(args: argparse.Namespace) -> int:
    from experiments.runtime.tracking import tracking_uri
    from reports.data.export import FORMAT_UNVERIFIED, ExportError
    from reports.data.store import StoreError
    from reports.data.studyimport import import_exports

    uri = args.tracking_uri or tracking_uri()
    _quiet_mlflow()
    try:
        done = import_exports(args.exports, uri)
    except (StoreError, ExportError) as exc:
        return _error(exc)
    for folder, doc, new in done:
        what = f"imported ({len(doc['runs'])} runs)" if new else "skipped (already imported from this export)"
        unverified = ", records unverified (an export from before their digest)" \
            if doc["format"] == FORMAT_UNVERIFIED else ""
        print(f"import: {doc['study_name']!r} from {folder}: {what}{unverified}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
