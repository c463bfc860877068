"""Tables of the report (success rates, circle errors, timings) and their Markdown/HTML/LaTeX renderings."""

from __future__ import annotations

import html
import math
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from reports import paper
from reports.stats import aggregate_success, mean_over_seeds
from reports.store import Study

GAP = "gap"


@dataclass
class Table:
    """A rendered table: header, string cells, notes under it, and the numbers behind it (CSV)."""

    name: str
    title: str
    columns: list[str]
    rows: list[list[str]]
    notes: list[str] = field(default_factory=list)
    data: pd.DataFrame | None = None

    def to_markdown(self) -> str:
        def esc(s: str) -> str:
            return s.replace("|", "\\|")
        lines = [f"### {self.title}", "", "| " + " | ".join(map(esc, self.columns)) + " |",
                 "|" + "---|" * len(self.columns)]
        lines += ["| " + " | ".join(map(esc, r)) + " |" for r in self.rows]
        if self.notes:
            lines += [""] + [f"- {n}" for n in self.notes]
        return "\n".join(lines) + "\n"

    def to_html(self, standalone: bool = True) -> str:
        head = "".join(f"<th>{html.escape(c)}</th>" for c in self.columns)
        body = "".join(
            "<tr>" + "".join(f'<td class="{"gap" if GAP in c else ""}">{html.escape(c)}</td>' for c in r) + "</tr>"
            for r in self.rows)
        notes = "".join(f"<li>{html.escape(n)}</li>" for n in self.notes)
        table = (f"<h3>{html.escape(self.title)}</h3><table><thead><tr>{head}</tr></thead>"
                 f"<tbody>{body}</tbody></table>" + (f"<ul class='notes'>{notes}</ul>" if notes else ""))
        if not standalone:
            return table
        return (f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(self.title)}</title>"
                f"<style>{TABLE_CSS}</style></head><body>{table}</body></html>\n")

    def to_latex(self) -> str:
        def esc(s: str) -> str:
            s = s.replace("\\", "\x00")  # backslashes last, so the escapes below stay intact
            for a, b in LATEX_ESCAPES:
                s = s.replace(a, b)
            return s.replace("\x00", r"\textbackslash{}")
        spec = "l" + "r" * (len(self.columns) - 1)
        lines = [r"\begin{table}[t]", r"\centering", r"\small", rf"\caption{{{esc(self.title)}}}",
                 rf"\begin{{tabular}}{{{spec}}}", r"\toprule", " & ".join(map(esc, self.columns)) + r" \\",
                 r"\midrule"]
        lines += [" & ".join(map(esc, r)) + r" \\" for r in self.rows]
        lines += [r"\bottomrule", r"\end{tabular}"]
        if self.notes:
            lines.append(r"\par\footnotesize " + " ".join(esc(n) for n in self.notes))
        lines.append(r"\end{table}")
        return "\n".join(lines) + "\n"

    def write(self, folder: Path) -> list[Path]:
        """<name>.md, .html, .tex (+ .csv of the numbers); returns the paths."""
        folder.mkdir(parents=True, exist_ok=True)
        paths = []
        for ext, text in (("md", self.to_markdown()), ("html", self.to_html()), ("tex", self.to_latex())):
            p = folder / f"{self.name}.{ext}"
            p.write_text(text)
            paths.append(p)
        if self.data is not None:
            p = folder / f"{self.name}.csv"
            self.data.to_csv(p, index=False)
            paths.append(p)
        return paths


# Order matters: braces before the replacements that introduce braces, "$" before those that introduce "$".
LATEX_ESCAPES = (("&", r"\&"), ("%", r"\%"), ("_", r"\_"), ("#", r"\#"), ("$", r"\$"), ("{", r"\{"), ("}", r"\}"),
                 ("~", r"\textasciitilde{}"), ("^", r"\textasciicircum{}"), ("±", r"$\pm$"), ("–", "--"),
                 ("†", r"$^\dagger$"))
TABLE_CSS = ("body{font-family:sans-serif}table{border-collapse:collapse;margin:0.5em 0}"
             "td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}th{background:#eee}"
             "td:first-child{text-align:left}td.gap{background:#fde2e2;color:#900}.notes{font-size:90%}")


def pct(x: float) -> str:
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{100 * x:.0f}%"


def num(x: float, digits: int = 3) -> str:
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}g}"


# ------------------------------------------------------------------------------------------- success
def success_summary(study: Study, tasks: list[str] | None = None) -> pd.DataFrame:
    """Aggregated success cells (see stats.aggregate_success) for the study's variants x tasks."""
    tasks = tasks or list(paper.SUCCESS_TASKS)
    agg = aggregate_success(study.eval_metrics(), study.children, study.variants, tasks,
                            study.model_task_of, study.seeds)
    if not agg.empty:
        agg["paper"] = [paper.paper_success(v, t) for v, t in zip(agg["variant"], agg["eval_task"], strict=True)]
    return agg


def success_cell(row: pd.Series) -> str:
    if row["status"] == GAP:
        return f"{GAP} ({row['note']})" if row["note"] else GAP
    mark = "†" if row["status"] == "partial" else ""
    return f"{pct(row['mean'])}{mark} [{pct(row['ci_low'])}–{pct(row['ci_high'])}] n={row['n']}"


def success_table(agg: pd.DataFrame, study: Study) -> Table:
    tasks = list(dict.fromkeys(agg["eval_task"])) if not agg.empty else list(paper.SUCCESS_TASKS)
    columns = ["variant"]
    for t in tasks:
        columns.append(paper.task_label(t))
        if t in paper.TABLE_I_SETTING:
            columns.append(f"{paper.task_label(t)} (paper)")
    rows = []
    for variant, cells in agg.groupby("variant", sort=False):
        row = [paper.variant_label(variant)]
        for t in tasks:
            cell = cells[cells["eval_task"] == t].iloc[0]
            row.append(success_cell(cell))
            if t in paper.TABLE_I_SETTING:
                row.append(pct(cell["paper"]) if cell["paper"] is not None else "–")
        rows.append(row)
    notes = [f"Ours: mean success over {len(study.seeds)} seed(s) of study {study.name!r} ({study.profile} profile); "
             "[low–high] is the Wilson 95% interval over the pooled rollouts, n the number of rollouts.",
             f"Paper: Table I of Zhang et al. 2019, {paper.TABLE_I_ROLLOUTS} rollouts; reacher in simulation, "
             "pick-and-place and stacking on the real robot; the paper has no changing-goal numbers.",
             "† some seeds missing or failed (mean over the rest); gap: no finished run logged the cell."]
    notes += [f"{paper.variant_label(r.variant)} / {paper.task_label(r.eval_task)}: {r.note}"
              for r in agg.itertuples() if r.note]
    return Table("success_table", "Success rate (Table I, extended)", columns, rows, notes, agg)


# -------------------------------------------------------------------------------------------- circle
def circle_summary(study: Study) -> pd.DataFrame:
    """Per (radius, variant): mean/std over seeds of radial RMSE (m) and max radial error (% of r);
    gaps for variants without a finished run that logged the radius."""
    cm = study.circle_metrics()
    cols = ["radius_cm", "variant", "rmse_mean", "rmse_std", "maxerr_mean", "maxerr_std", "seeds", "status"]
    radii = sorted(set(cm["radius_cm"]) if not cm.empty else set())
    if not radii:
        return pd.DataFrame(columns=cols)
    ok = cm[cm["status"] == "FINISHED"]
    rmse = mean_over_seeds(ok, ["radius_cm", "variant"], "radial_rmse") if "radial_rmse" in ok else None
    mx = mean_over_seeds(ok, ["radius_cm", "variant"], "max_radial_error_pct") if "max_radial_error_pct" in ok \
        else None
    rows = []
    for r in radii:
        for v in study.variants:
            a, b = _cell(rmse, r, v), _cell(mx, r, v)
            seeds = max(a[2], b[2])
            rows.append({"radius_cm": r, "variant": v, "rmse_mean": a[0], "rmse_std": a[1],
                         "maxerr_mean": b[0], "maxerr_std": b[1], "seeds": seeds,
                         "status": "ok" if seeds else GAP})
    return pd.DataFrame(rows, columns=cols)


def _cell(df: pd.DataFrame | None, radius: float, variant: str) -> tuple[float, float, int]:
    """(mean, std, count) of one (radius, variant) group of mean_over_seeds output; NaNs and 0 if absent."""
    if df is None or df.empty:
        return math.nan, math.nan, 0
    hit = df[(df["radius_cm"] == radius) & (df["variant"] == variant)]
    if not len(hit):
        return math.nan, math.nan, 0
    return float(hit["mean"].iloc[0]), float(hit["std"].iloc[0]), int(hit["count"].iloc[0])


def circle_table(summary: pd.DataFrame, study: Study) -> Table:
    unseen = study.unseen_radii_cm()
    columns = ["radius (cm)", "variant", "radial RMSE (m)", "max radial error (% of r)", "seeds",
               "paper RMSE", "paper max error"]
    rows = []
    for r in summary.itertuples():
        paper_rmse = paper.CIRCLE_RMSE.get(float(r.radius_cm))
        if r.status == GAP:
            ours = [GAP, GAP]
        else:
            ours = [f"{r.rmse_mean:.4f} ± {r.rmse_std:.4f}" if not math.isnan(r.rmse_mean) else GAP,
                    f"{r.maxerr_mean:.1f} ± {r.maxerr_std:.1f}" if not math.isnan(r.maxerr_mean) else GAP]
        label = f"{r.radius_cm:g}" + (" (unseen)" if round(float(r.radius_cm), 1) in unseen else "")
        rows.append([label, paper.variant_label(r.variant), *ours, str(r.seeds),
                     f"{paper_rmse:.3f}" if paper_rmse is not None else "–",
                     f"< {paper.CIRCLE_MAX_RADIAL_ERROR_PCT:g}%" if paper_rmse is not None else "–"])
    notes = ["Mean ± std over seeds of finished runs; RMSE of the measured tip's distance from the centre vs r.",
             f"Paper: average RMSE at 5/10/15 cm ({paper.CIRCLE_RMSE_UNIT_NOTE}); the radial error never "
             f"exceeded {paper.CIRCLE_MAX_RADIAL_ERROR_PCT:g}% of r. (unseen): a radius the runs list in "
             "eval.circle_unseen_radii."]
    if summary.empty:
        rows = [[GAP, "–", GAP, GAP, "0", "–", "–"]]
        notes.insert(0, "gap: no run of this study logged circle/r{R}/* metrics.")
    return Table("circle_table", "Circle drawing: radial error per radius", columns, rows, notes, summary)


# ------------------------------------------------------------------------------------------- timings
def train_time_summary(study: Study) -> pd.DataFrame:
    col = "metrics.time/train_seconds"
    ok = study.ok
    if col not in ok.columns:
        return pd.DataFrame(columns=["task", "variant", "mean", "std", "count"])
    return mean_over_seeds(ok.rename(columns={col: "train_seconds"}), ["task", "variant"], "train_seconds")


def train_time_table(summary: pd.DataFrame, study: Study) -> Table:
    tasks = sorted(study.children["task"].dropna().unique())
    columns = ["variant", *[f"{t} (s)" for t in tasks]]
    rows = []
    for v in study.variants:
        row = [paper.variant_label(v)]
        for t in tasks:
            hit = summary[(summary["task"] == t) & (summary["variant"] == v)] if not summary.empty else summary
            row.append(f"{hit['mean'].iloc[0]:.1f} ± {hit['std'].iloc[0]:.1f} ({int(hit['count'].iloc[0])})"
                       if len(hit) else GAP)
        rows.append(row)
    notes = ["Training wall time per run (metric time/train_seconds), mean ± std over seeds (count) of finished runs."]
    return Table("train_time_table", "Training time per variant and task", columns, rows, notes, summary)


def generic_metrics_table(study: Study) -> Table:
    """Every final child metric, mean ± std over seeds, per (task, variant): the catch-all for any kind."""
    ok = study.ok
    mcols = [c for c in ok.columns if c.startswith("metrics.")]
    long = ok.melt(id_vars=["task", "variant"], value_vars=mcols, var_name="metric", value_name="value") \
        if mcols and len(ok) else pd.DataFrame(columns=["task", "variant", "metric", "value"])
    long["metric"] = long["metric"].str.removeprefix("metrics.")
    agg = mean_over_seeds(long, ["metric", "task", "variant"], "value")
    rows = [[r.metric, str(r.task), paper.variant_label(str(r.variant)), f"{num(r.mean, 4)} ± {num(r.std, 2)}",
             str(r.count)] for r in agg.sort_values(["metric", "task", "variant"]).itertuples()]
    if not rows:
        rows = [[GAP, "–", "–", "–", "0"]]
    return Table("metrics_table", "All logged metrics (final values)", ["metric", "task", "variant",
                                                                      "mean ± std", "runs"], rows,
                 ["Last logged value per run, over finished runs only."], agg)
