"""index.html of a study's report and the top-level index of studies, rendered with Jinja2
(reports/study_report/templates/*.html.j2). A study's page reads in RESULTS.md's order: Table I and its figure
first, then the paper's comparisons, the circles, the compute, each table followed by its figures; the catch-all
metric dump comes last, folded."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from jinja2 import Environment, FileSystemLoader, StrictUndefined, select_autoescape
from markupsafe import Markup, escape

from reports.data.store import Study
from reports.plotting import FigureResult
from reports.study_report.tables import TABLE_CSS, Table

CSS = TABLE_CSS + ("img{max-width:100%;border:1px solid #ddd;margin:4px 0}.gapbox{color:#900}"
                   "section{margin-bottom:2em}code{background:#f4f4f4}details{margin:1em 0}"
                   "summary{cursor:pointer;font-weight:bold}.lead{color:#444}")
# The figures shown right under each table, in this order (those the study drew); the others follow the tables.
FIGURES_OF = {"table_one": ("table_one",), "circle_table": ("circles",),
              "train_time_table": ("compute_time", "train_time", "training_curves"),
              "success_table": ("success_bars", "tip_paths", "changing_goal")}
FOLDED_TABLES = ("metrics_table",)  # the dump of every logged metric: last and folded

_ENV = Environment(loader=FileSystemLoader(Path(__file__).parent / "templates"),
                   autoescape=select_autoescape(["html", "j2"]), undefined=StrictUndefined,
                   keep_trailing_newline=True)


@dataclass
class _Section:
    table: _TableView
    figures: list[FigureResult]


@dataclass
class _TableView:
    name: str
    title: str
    html: Markup
    rows: int
    folder: Path


def _view(t: Table, folder: Path) -> _TableView:
    return _TableView(t.name, t.title, Markup(t.to_html(standalone=False)), len(t.rows), folder)


def _links(t: _TableView) -> Markup:
    return Markup(" · ").join(Markup('<a href="{0}.{1}">{1}</a>').format(t.name, ext)
                              for ext in ("md", "html", "tex", "csv") if (t.folder / f"{t.name}.{ext}").exists())


def _figure(f: FigureResult) -> Markup:
    head = Markup("<h3>{}</h3>").format(f.title)
    if f.gap:
        return head + Markup("<p class='gapbox'>gap: {}</p>").format(f.gap)
    png, pdf = (p.name for p in f.paths)
    return head + Markup("<a href='{0}'><img src='{0}' alt='{2}'></a><p><a href='{0}'>png</a> · "
                         "<a href='{1}'>pdf</a></p>").format(png, pdf, f.title)


def _gaps(figures: list[FigureResult], failed) -> list[Markup]:
    gaps = [Markup("figure <b>{}</b>: {}").format(f.name, f.gap) for f in figures if f.gap]
    gaps += [Markup("figure <b>{}</b> panels without data: {}").format(f.name, ", ".join(f.partial))
             for f in figures if f.partial and not f.gap]
    gaps += [escape(f"run {r.run_id} ({r.task}, {r.variant}, seed {r.seed}) {r.status}") for r in failed.itertuples()]
    return gaps


def study_index(study: Study, folder: Path, tables: list[Table], figures: list[FigureResult],
                seconds: float | None = None) -> Path:
    ch = study.children
    failed = ch[ch["failed"]]
    info = [("study", study.name), ("parent run", study.run_id), ("experiment", study.experiment),
            ("kind", study.kind), ("profile", study.profile)]
    if study.kind in ("smoothing", "idm"):  # one run, no children: its own status and plan source
        info += [("run status", study.parent.get("status") or "?"),
                 ("skeletons", study.parent.get("tags.skeleton_source") or "?")]
    folded = [t for t in tables if t.name in FOLDED_TABLES]
    drawn = {f.name: f for f in figures if not f.gap}
    sections = [_Section(_view(t, folder), [drawn.pop(n) for n in FIGURES_OF.get(t.name, ()) if n in drawn])
                for t in tables if t.name not in FOLDED_TABLES]
    top = [] if sections and sections[0].figures else list(drawn.values())[:1]  # a page without Table I: one figure
    rest = [f for f in drawn.values() if f not in top]
    html = _ENV.get_template("study_index.html.j2").render(
        css=CSS, study=study, n_children=len(ch), n_finished=int((ch["status"] == "FINISHED").sum()),
        n_failed=len(failed), info=info, seconds=seconds, headline=sections[0] if sections else None,
        sections=sections[1:], folded=[_view(t, folder) for t in folded], headline_figures=top, figures=rest,
        gaps=_gaps(figures, failed), links=_links, figure=_figure)
    path = folder / "index.html"
    path.write_text(html)
    return path


def root_index(out_root: Path, studies: list[tuple[Study, Path]]) -> Path:
    """<out>/index.html: one line per study report (rebuilt from the folders present)."""
    out_root.mkdir(parents=True, exist_ok=True)
    rows = [{"href": index.relative_to(out_root).as_posix(), "name": study.name, "kind": study.kind,
             "profile": study.profile, "run_id": study.run_id, "earlier": False} for study, index in studies]
    known = {i.parent.name for _, i in studies}
    rows += [{"href": other.relative_to(out_root).as_posix(), "name": other.parent.name, "earlier": True}
             for other in sorted(out_root.glob("*/index.html")) if other.parent.name not in known]
    path = out_root / "index.html"
    path.write_text(_ENV.get_template("root_index.html.j2").render(css=CSS, rows=rows))
    return path
