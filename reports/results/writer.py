"""reports/RESULTS.md from a hand-written template and the MLflow store: the prose lives in the template
(reports/RESULTS.template.md, Jinja2 placeholders checked by reports.results.template), every number, table and
figure comes from the tracked studies (chosen by reports.results.selection).

Regenerate with ONE command (from the repository root, over the store that holds the final studies):

    nox -s report -- --results                  # = python -m reports --results
    nox -s report -- --results --exports reports/studies   # from the study exports in the repository
    python -m reports --results [--ablation NAME_OR_RUN_ID] [--sweep NAME_OR_RUN_ID ...]
        [--template reports/RESULTS.template.md] [--results-out reports/RESULTS.md]
        [--figures-dir reports/figures] [--tracking-uri URI | --exports DIR]

Defaults: the latest ablation study of the store and every sweep study in it (the latest one per task).
With --exports, the studies are read from the exports of DIR themselves (reports.data.export_store; no MLflow store in
between): a session without the original store regenerates the same tables. The command written into RESULTS.md
({{ command }}) pins the studies that were used, so it regenerates the same file later even when newer studies
have been added to the store; it names the store relative to the working directory (a SQLite file, or the
exports folder) or by $MLFLOW_TRACKING_URI (a server), never by a path of this machine.

Placeholders of the template:
    {{ table_one("TASK=STUDY", ...) }}  Table I with its bar figure, each training task's cells from the study named
                             for it (reports.study_report.table_one); {{ claims }}: the paper's comparisons on those
                             cells (reports.results.paper_claims); {{ headline_train_time }}: their training time
    {{ notebook("TOPIC") }}  a link to the notebook page notebook/TOPIC.md, rendered with RESULTS.md from
                             notebook/TOPIC.template.md beside the template (reports.results.pages)
    {{ provenance }}         one row per study used, by RESULTS.md and its notebook pages: kind, parent run,
                             commits, dates, wall time, runs, seeds; the machines and software the runs logged
    {{ command }}            the exact regeneration command (a fenced code block)
    {{ success_table }}      success rates (per seed, seed-level and Wilson intervals) beside the paper's Table I
    {{ circle_table }}       circle drawing radial errors beside the paper's
    {{ train_time_table }}   training wall time per variant and task
    {{ sweep_table("TASK") }}  the sweep study of TASK: trial counts, best trial (params, objective), top 5
    {{ sweep_figure("TASK") }} its figures (sweep_history, sweep_params, sweep_intermediate, sweep_importance);
    {{ sweep_figure("TASK", "NAME") }} one of them
    {{ figure("NAME") }}     a figure of the ablation report (success_bars, circles, compute_time,
                             train_time, training_curves, tip_paths, changing_goal)
    {{ success_table(study="NAME") }}, {{ figure("NAME", study="NAME") }}, ...: the same of another study
                             (study_name or parent run id) than the --ablation one; provenance lists them all
    {{ data_scaling("TASK", "STUDY", ...) }}  success vs number of demonstrations of TASK's models across
                             ablation studies that differ in it: a table and a figure (reports.analyses.data_scaling)
    {{ lever("TASK", "STUDY", ...) }}  TASK's models across ablation studies that differ in some settings (read
                             from their params): a table and a figure (reports.analyses.levers)
    {{ goal_switch("TASK", "STUDY", ...) }}  where the changing-goal reacher's episodes of TASK's models fail,
                             per study and variant: a table and a figure (reports.analyses.goal_switch)
    {{ stacking("TASK", "STUDY", ...) }}  which block the stacking episodes of TASK's models get to, per
                             study and variant: a table and a figure (reports.analyses.stacking)
    {{ pick_place_failures("TASK", "STUDY", ...) }}  the stage each pick-and-place and changing-goal
                             pick-and-place episode of TASK's models fails at, per study and variant: a table and a
                             figure (reports.analyses.pick_place_failures)
    {{ placement("TASK", "STUDY", ...) }}  pick-and-place success judged on the block (placed) beside the strict
                             criterion (the last grip command open too), per study and variant: a table
                             (reports.analyses.placement)
    {{ comparisons("TASK", "STUDY", ...) }}  the paper's comparisons of the variants within each study, and each
                             study against the first per variant: differences, intervals, p
                             (reports.results.comparisons)
    {{ compare("EVAL_TASK", "STUDY/VARIANT", "STUDY/VARIANT", ...) }}  those of any pairs of rows, as a table;
    {{ difference("EVAL_TASK", "STUDY/VARIANT", "STUDY/VARIANT") }}  one of them inline, for a sentence
    {{ rate("EVAL_TASK", "STUDY/VARIANT") }}  a row's mean success and seed-level interval inline (a target sentence)

New ablation-kind placeholders are one entry in ABLATION_TABLES (name -> builder(results, study) returning a
Table or DataFrame; {{ name }}) or ABLATION_FIGURES (name -> builder(results, study, folder) -> FigureResult;
{{ figure("name") }}).

Figures are re-saved as small PNGs (reports.results.pngs) under --figures-dir and linked relative to the page that
shows them.
An unknown placeholder or a missing study or figure name is an error that names it (nothing is written); a
figure the data cannot draw becomes a visible "figure unavailable" line. The output depends on the store only
(no timestamps other than the studies' own).
"""

from __future__ import annotations

import logging
import os
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from envs.fileio import atomic_write_text
from reports import paper
from reports.analyses import mode_use, multimodal, success_vs_iterations
from reports.data.store import Store, StoreError, Study, file_safe
from reports.plotting import FigureResult, plt
from reports.results import comparisons, headline, pages
from reports.results.across import ACROSS, at_iteration, whole_study
from reports.results.command import portable_uri, regeneration_command
from reports.results.pages import Page
from reports.results.pngs import MAX_FIGURE_WIDTH, small_png
from reports.results.provenance import provenance_table
from reports.results.selection import Selection, headline_study, select_studies
from reports.results.template import (
    HEADLINE,
    ROW_KINDS,
    SWEEP_FIGURES,
    Placeholder,
    ResultsError,
    Vocabulary,
    parse,
    render,
)
from reports.study_report import ablation_figures, sweep_summary, tables, trajectories
from reports.study_report.sweep_summary import sweep_task
from reports.study_report.tables import Table

log = logging.getLogger(__name__)


@dataclass
class Results:
    ablation: Study | None
    sweeps: list[Study]
    results_out: Path
    figures_dir: Path
    command: str
    named: dict[str, Study] = field(default_factory=dict)  # study="NAME" of the template -> its study
    pages: dict[str, Page] = field(default_factory=dict)  # {{ notebook("TOPIC") }}: TOPIC -> its page
    context: list[Placeholder] = field(default_factory=list)  # those of the template and its pages (provenance)
    page_out: Path | None = None  # the file being rendered, when not results_out: figure links are relative to it
    _cache: dict = field(default_factory=dict)
    _tmp: tempfile.TemporaryDirectory = field(
        default_factory=lambda: tempfile.TemporaryDirectory(prefix="results-"), repr=False)

    # ------------------------------------------------------------------ studies
    def need_ablation(self, ph: Placeholder) -> Study:
        if ph.study is not None:
            return self.named[ph.study]
        if self.ablation is None:
            raise ResultsError(f"{ph} needs an ablation study, and the store has none (run one, or pass --ablation)")
        return self.ablation

    def sweep_of(self, ph: Placeholder) -> Study:
        hit = [s for s in self.sweeps if sweep_task(s) == ph.arg]
        if not hit:
            have = ", ".join(f"{sweep_task(s)} ({s.name})" for s in self.sweeps) or "none"
            raise ResultsError(f"{ph}: no sweep study of task {ph.arg!r} selected (sweep studies: {have})")
        return hit[0]

    def used(self, placeholders: list[Placeholder]) -> tuple[Study | None, list[Study], list[Study]]:
        """The default ablation study if the template uses it, the ablation studies it uses (in order) and the
        sweep studies it uses (all selected ones when the template names none specifically)."""
        abl = [self.need_ablation(p) for p in placeholders if is_ablation_kind(p.kind)]
        abl = [self.named.get(whole_study(s.name), s) for s in abl]  # a stage NAME@ITERATION: its whole study
        abl += [self.named[whole_study(name)] for p in placeholders if not is_ablation_kind(p.kind)
                for name in p.studies]
        default = self.ablation if any(is_ablation_kind(p.kind) and p.study is None for p in placeholders) else None
        abl = list({s.run_id: s for s in abl}.values())
        swp = list(dict.fromkeys(self.sweep_of(p).run_id for p in placeholders if p.kind.startswith("sweep_")))
        if not abl and not swp:
            return self.ablation, [self.ablation] if self.ablation else [], self.sweeps
        return default, abl, [s for s in self.sweeps if s.run_id in swp]

    def check(self, placeholders: list[Placeholder]) -> None:
        """Every study the template needs is there, before anything is drawn or written."""
        for ph in placeholders:
            if is_ablation_kind(ph.kind):
                self.need_ablation(ph)
            elif ph.kind.startswith("sweep_"):
                self.sweep_of(ph)
            elif ph.kind in ("table_one", *HEADLINE):
                headline.check(ph, self.context or placeholders, self.named)

    # ------------------------------------------------------------------- tables
    def summary(self, name: str, study: Study) -> pd.DataFrame:
        key = (name, study.run_id, study.name)  # the stages NAME@ITERATION of a study share its parent run
        if key not in self._cache:
            build = {"success": tables.success_summary, "circle": tables.circle_summary,
                     "train": tables.train_time_summary}[name]
            self._cache[key] = build(study)
        return self._cache[key]

    # ------------------------------------------------------------------ figures
    def figure(self, study: Study, name: str, out_name: str, build: Callable[[Path], FigureResult],
               label: str | None = None) -> str:
        """The figure's Markdown link (or its gap line), labelled with the study's name unless `label`."""
        label = study.name if label is None else label
        folder = Path(self._tmp.name) / study.slug
        dst = self.figures_dir / f"{out_name}.png"
        try:
            res = build(folder)
        except Exception as exc:  # noqa: BLE001 - data the builder did not foresee: a visible gap, not a crash
            log.warning("figure %s failed", name, exc_info=True)
            plt.close("all")
            res = FigureResult(name, name, gap=f"could not be drawn: {type(exc).__name__}: {exc}")
        png = next((p for p in res.paths if p.suffix == ".png"), None)
        if res.gap or png is None:
            dst.unlink(missing_ok=True)  # our own output name: no stale figure beside the gap
            return f"> **figure unavailable: {name}** ({label}): {res.gap or 'no PNG written'}\n"
        small_png(png, dst)
        link = Path(os.path.relpath(dst, (self.page_out or self.results_out).parent)).as_posix()
        text = f"![{res.title} ({label})]({link})\n"
        if res.partial:
            text += f"\n*Panels without data: {'; '.join(res.partial)}.*\n"
        return text

    def ablation_figure(self, ph: Placeholder) -> str:
        study = self.need_ablation(ph)
        build = ABLATION_FIGURES[ph.arg]
        out_name = ph.arg if ph.study is None else f"{file_safe(study.name)}_{ph.arg}"  # another study: its own file
        return self.figure(study, ph.arg, out_name, lambda folder: build(self, study, folder))

    def sweep_figures(self, ph: Placeholder) -> str:
        study = self.sweep_of(ph)
        names = list(ph.args[1:]) or list(SWEEP_FIGURES)
        task = file_safe(sweep_task(study))
        return "\n".join(self.figure(study, n, f"{task}_{n}",
                                      lambda folder, n=n: getattr(sweep_summary, n)(study, folder))
                         for n in names)

    def across(self, ph: Placeholder) -> str:
        """A placeholder over several studies of one training task (ACROSS): its table, the table's note and a
        figure."""
        kind, task, studies = ACROSS[ph.kind], ph.arg, [self.named[name] for name in ph.studies]
        try:
            rows = kind.rows(studies, task)
        except kind.error as exc:
            raise ResultsError(f"{ph}: {exc}") from None
        table = kind.table(rows)
        text = markdown(table) if not table.empty else f"*No finished runs of {task} in the named studies.*\n"
        text += f"\n- Studies: {', '.join(s.name for s in studies)}; {kind.note(task)}\n\n"
        if kind.figure is None:  # a long table of its own: folded under a summary line
            return f"<details><summary>{kind.name} ({len(table)} rows; {task} models)</summary>\n\n{text}</details>\n"
        return text + self.figure(studies[0], kind.name, kind.out_name(task, studies),
                                  lambda folder: kind.figure(rows, task, folder),
                                  label=f"{task}: {len(studies)} stud{'y' if len(studies) == 1 else 'ies'}")

    def comparison(self, ph: Placeholder) -> str:
        """{{ compare(...) }} (a table) or {{ difference(...) }} (inline) of rows of the named studies."""
        eval_task, rows = ph.arg, ph.args[1:]
        try:
            if ph.kind == "difference":
                return comparisons.sentence(comparisons.between(self.named, eval_task, *rows))
            if ph.kind == "rate":
                return comparisons.rate_sentence(self.named, eval_task, rows[0])
            return comparisons.compare_table(self.named, eval_task, rows)
        except comparisons.ComparisonError as exc:
            raise ResultsError(f"{ph}: {exc}") from None

    # ------------------------------------------------------------------- render
    def render_one(self, ph: Placeholder, placeholders: list[Placeholder]) -> str:
        if ph.kind == "provenance":
            _, abl, swp = self.used(placeholders)
            return provenance_table([*sorted(abl, key=lambda s: s.name), *swp]).to_markdown(heading=False)
        if ph.kind == "command":
            return f"```sh\n{self.command}\n```\n"
        if ph.kind in ABLATION_TABLES:
            return markdown(ABLATION_TABLES[ph.kind](self, self.need_ablation(ph)))
        if ph.kind == "sweep_table":
            return sweep_summary.sweep_table(self.sweep_of(ph)).to_markdown()
        if ph.kind == "sweep_figure":
            return self.sweep_figures(ph)
        if ph.kind in ACROSS:
            return self.across(ph)
        if ph.kind in ROW_KINDS:
            return self.comparison(ph)
        if ph.kind in ("table_one", *HEADLINE):
            return headline.render(self, ph, placeholders)
        if ph.kind == "notebook":
            return pages.link(self.pages[ph.arg], self.results_out)
        return self.ablation_figure(ph)

    def render(self, template: str) -> str:
        """The template rendered; provenance, the command and Table I's sources read self.context (the template's
        placeholders and its notebook pages') when set."""
        placeholders = parse_template(template)
        self.check(placeholders)
        context = self.context or placeholders
        values: dict[Placeholder, str] = {}
        done: dict[tuple, str] = {}  # a placeholder used twice is drawn once
        for ph in placeholders:
            if ph.key not in done:
                done[ph.key] = self.render_one(ph, context).rstrip("\n")
            values[ph] = done[ph.key]
        return render(template, values)


def markdown(table: Table | pd.DataFrame | str) -> str:
    if isinstance(table, str):  # a builder that renders its own Markdown
        return table
    if isinstance(table, Table):
        return table.to_markdown()
    return table.to_markdown(index=not isinstance(table.index, pd.RangeIndex)) + "\n"


# The ablation-kind placeholders: {{ NAME }} / {{ NAME(study="...") }} and {{ figure("NAME"[, study="..."]) }}.
ABLATION_TABLES: dict[str, Callable[[Results, Study], Table | pd.DataFrame | str]] = {
    "success_table": lambda r, s: tables.paper_success_table(r.summary("success", headline_study(s, "success_table")),
                                                             s),
    "circle_table": lambda r, s: tables.circle_table(r.summary("circle", s), s),
    "train_time_table": lambda r, s: tables.train_time_table(r.summary("train", s), s),
    "budget_table": lambda r, s: tables.budget_table(s),
    "multimodal_table": lambda r, s: multimodal.multimodal_markdown(multimodal.multimodal_table(s),
                                                                    paper.variant_label),
    "mode_use_table": lambda r, s: mode_use.mode_use_markdown(s, paper.variant_label),
}
ABLATION_FIGURES: dict[str, Callable[[Results, Study, Path], FigureResult]] = {
    "success_bars": lambda r, s, f: ablation_figures.success_bars(r.summary("success", s), s, f),
    "circles": lambda r, s, f: trajectories.circles(s, f),
    "compute_time": lambda r, s, f: ablation_figures.compute_time(s, f),
    "train_time": lambda r, s, f: ablation_figures.train_time(r.summary("train", s), s, f),
    "training_curves": lambda r, s, f: ablation_figures.training_curves(s, f),
    "tip_paths": lambda r, s, f: trajectories.tip_paths(s, f),
    "changing_goal": lambda r, s, f: trajectories.changing_goal(s, f),
    "mode_paths": lambda r, s, f: multimodal.mode_paths(s, f),
    "mode_entropy": lambda r, s, f: mode_use.mode_entropy(s, f),
    "success_vs_iterations": lambda r, s, f: success_vs_iterations.success_vs_iterations(s, f),  # of a milestones study
}


def is_ablation_kind(kind: str) -> bool:
    """A placeholder of an ablation study (the registries are read at call time: they may grow after import)."""
    return kind == "figure" or kind in ABLATION_TABLES


def parse_template(text: str) -> list[Placeholder]:
    """reports.results.template.parse with this module's tables and figures."""
    return parse(text, Vocabulary(ABLATION_TABLES, ABLATION_FIGURES))


NAMED_KINDS = ("ablation", "milestones")  # what study="NAME" may name (a milestones study: its runs are cells too)


def _named_studies(selection: Selection, placeholders: list[Placeholder]) -> dict[str, Study]:
    """The studies the template names (study="NAME", and those of the MULTI_STUDY placeholders), each checked to
    be of a NAMED_KINDS kind in the store; NAME@ITERATION: a milestones study's checkpoints kept at that
    iteration (reports.results.across.at_iteration), beside the whole study under NAME (what provenance lists)."""
    named: dict[str, Study] = {}
    for ph in placeholders:
        for name in ph.studies:
            base, _, iteration = name.partition("@")
            try:
                if base not in named:
                    named[base] = selection.pick(base, NAMED_KINDS)
                if iteration and name not in named:
                    if not iteration.isdigit():
                        raise StoreError(f"{name!r}: the iteration after '@' must be a whole number")
                    named[name] = at_iteration(named[base], int(iteration))
            except StoreError as exc:
                raise ResultsError(f"{ph}: {exc}") from None
    return named


def write_results(store: Store, template: Path, results_out: Path, figures_dir: Path,
                  ablation: str | None = None, sweep_ids: list[str] | None = None,
                  exports: Path | None = None) -> Path:
    """Render the template, and the notebook pages it links (reports.results.pages), from the store into
    results_out and the notebook folder beside it, all written only once everything rendered; `exports`: the
    folder the store was imported from (named in the regeneration command instead of the store)."""
    try:
        text = template.read_text()
    except OSError as exc:
        raise ResultsError(f"cannot read the template {template}: {exc.strerror or exc}") from None
    placeholders = parse_template(text)  # a template error before the store is read
    linked = pages.notebook_pages(template, results_out, placeholders, parse_template)
    context = [*placeholders, *(p for page in linked.values() for p in page.placeholders)]
    selection = Selection(store)
    abl, swp = select_studies(selection, ablation, sweep_ids)
    named = _named_studies(selection, placeholders)
    for page in linked.values():
        named.update(pages.in_page(page.template, _named_studies, selection, page.placeholders))
    results = Results(abl, swp, results_out, figures_dir, command="", named=named, pages=linked, context=context)
    results.check(placeholders)
    for page in linked.values():
        pages.in_page(page.template, results.check, page.placeholders)
    default, _, used_swp = results.used(context)
    results.command = regeneration_command(default, used_swp, template, results_out, figures_dir, store.uri,
                                           exports)
    outputs = {results_out: results.render(text)}
    for page in linked.values():
        results.page_out = page.out
        outputs[page.out] = pages.in_page(page.template, results.render, page.text)
    for path, out in outputs.items():
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_text(path, out)
        except OSError as exc:
            raise ResultsError(f"cannot write {path}: {exc.strerror or exc}") from None
    return results_out


__all__ = ["ABLATION_FIGURES", "ABLATION_TABLES", "MAX_FIGURE_WIDTH", "Results", "ResultsError", "StoreError",
           "parse_template", "portable_uri", "regeneration_command", "select_studies", "small_png", "write_results"]
