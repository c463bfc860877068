"""index.html of a study's report (every table and figure, gaps listed) and the top-level index of studies."""

from __future__ import annotations

import html
from pathlib import Path

from reports.plotting import FigureResult
from reports.store import Study
from reports.tables import TABLE_CSS, Table

CSS = TABLE_CSS + ("img{max-width:100%;border:1px solid #ddd;margin:4px 0}.gapbox{color:#900}"
                   "section{margin-bottom:2em}code{background:#f4f4f4}")


def _e(s: object) -> str:
    return html.escape(str(s))


def study_index(study: Study, folder: Path, tables: list[Table], figures: list[FigureResult],
                seconds: float | None = None) -> Path:
    ch = study.children
    failed = ch[ch["failed"]]
    info = [("study", study.name), ("parent run", study.run_id), ("experiment", study.experiment),
            ("kind", study.kind), ("profile", study.profile), ("child runs", len(ch)),
            ("finished", int((ch["status"] == "FINISHED").sum())), ("failed", len(failed))]
    if study.kind in ("smoothing", "idm"):  # one run, no children: its own status and plan source
        info += [("run status", study.parent.get("status") or "?"),
                 ("skeletons", study.parent.get("tags.skeleton_source") or "?")]
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>Report: {_e(study.name)}</title>",
             f"<style>{CSS}</style></head><body><h1>Report: {_e(study.name)}</h1>",
             "<table>" + "".join(f"<tr><th>{_e(k)}</th><td>{_e(v)}</td></tr>" for k, v in info) + "</table>"]
    gaps = [f"figure <b>{_e(f.name)}</b>: {_e(f.gap)}" for f in figures if f.gap]
    gaps += [f"figure <b>{_e(f.name)}</b> panels without data: {_e(', '.join(f.partial))}"
             for f in figures if f.partial and not f.gap]
    gaps += [f"run {_e(r.run_id)} ({_e(r.task)}, {_e(r.variant)}, seed {_e(r.seed)}) {_e(r.status)}"
             for r in failed.itertuples()]
    if gaps:
        parts.append("<section><h2>Gaps</h2><ul class='gapbox'>" + "".join(f"<li>{g}</li>" for g in gaps)
                     + "</ul></section>")
    parts.append("<section><h2>Tables</h2>")
    for t in tables:
        links = " · ".join(f"<a href='{t.name}.{ext}'>{ext}</a>" for ext in ("md", "html", "tex", "csv")
                           if (folder / f"{t.name}.{ext}").exists())
        parts.append(t.to_html(standalone=False) + f"<p>{links}</p>")
    parts.append("</section><section><h2>Figures</h2>")
    for f in figures:
        parts.append(f"<h3>{_e(f.title)}</h3>")
        if f.gap:
            parts.append(f"<p class='gapbox'>gap: {_e(f.gap)}</p>")
            continue
        png, pdf = (p.name for p in f.paths)
        parts.append(f"<a href='{png}'><img src='{png}' alt='{_e(f.title)}'></a>"
                     f"<p><a href='{png}'>png</a> · <a href='{pdf}'>pdf</a></p>")
    footer = "Built from the MLflow store by <code>python -m reports</code>"
    footer += f" in {seconds:.1f} s." if seconds is not None else "."
    parts.append(f"</section><p><small>{footer}</small></p></body></html>\n")
    path = folder / "index.html"
    path.write_text("\n".join(parts))
    return path


def root_index(out_root: Path, studies: list[tuple[Study, Path]]) -> Path:
    """reports/out/index.html: one line per study report (rebuilt from the folders present)."""
    out_root.mkdir(parents=True, exist_ok=True)
    path = out_root / "index.html"
    rows = []
    for study, index in studies:
        rows.append(f"<tr><td><a href='{_e(index.relative_to(out_root).as_posix())}'>{_e(study.name)}</a></td>"
                    f"<td>{_e(study.kind)}</td><td>{_e(study.profile)}</td><td>{_e(study.run_id)}</td></tr>")
    known = {i.parent.name for _, i in studies}
    for other in sorted(out_root.glob("*/index.html")):
        if other.parent.name not in known:
            rows.append(f"<tr><td><a href='{_e(other.relative_to(out_root).as_posix())}'>{_e(other.parent.name)}"
                        "</a></td><td colspan=3>(earlier build)</td></tr>")
    path.write_text(f"<!doctype html><html><head><meta charset='utf-8'><title>Reports</title><style>{CSS}</style>"
                    "</head><body><h1>Study reports</h1><table><tr><th>study</th><th>kind</th><th>profile</th>"
                    f"<th>parent run</th></tr>{''.join(rows)}</table></body></html>\n")
    return path
