"""reports/RESULTS.md from a hand-written template and the MLflow store: the prose lives in the template
(reports/RESULTS.template.md), every number, table and figure comes from the tracked studies.

Regenerate with ONE command (from the repository root, over the store that holds the final studies):

    nox -s report -- --results                  # = python -m reports --results
    python -m reports --results [--ablation NAME_OR_RUN_ID] [--sweep NAME_OR_RUN_ID ...]
        [--template reports/RESULTS.template.md] [--results-out reports/RESULTS.md]
        [--figures-dir reports/figures] [--tracking-uri URI]

Defaults: the latest ablation study of the store and every sweep study in it (the latest one per task).
The command written into RESULTS.md ({{command}}) pins the studies that were used, so it regenerates the
same file later even when newer studies have been added to the store.

Placeholders of the template (`{{name}}` or `{{name:ARG}}`):
    {{provenance}}           per study used: name, kind, profile, git commit, machine/software, seeds,
                             rollouts per seed, pooled rollouts per cell, study wall time, dates
    {{command}}              the exact regeneration command (a fenced code block)
    {{success_table}}        success rates with Wilson 95% intervals beside the paper's Table I
    {{circle_table}}         circle drawing radial errors beside the paper's
    {{train_time_table}}     training wall time per variant and task
    {{sweep_table:TASK}}     the sweep study of TASK: trial counts, best trial (params, objective), top 5
    {{sweep_figure:TASK}}    its figures (sweep_history, sweep_params, sweep_intermediate);
    {{sweep_figure:TASK:NAME}} one of them
    {{figure:NAME}}          a figure of the ablation report (success_bars, circles, compute_time,
                             train_time, training_curves, tip_paths, changing_goal)

Figures are re-saved as small PNGs (width <= 1000 px, palette colours) under --figures-dir and linked
relative to --results-out. An unknown placeholder or a missing study or figure name is an error that
names it (nothing is written); a figure the data cannot draw becomes a visible "figure unavailable" line.
The output depends on the store only (no timestamps other than the studies' own).
"""

from __future__ import annotations

import logging
import math
import os
import re
import shlex
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from reports import figures, sweeps, tables, trajectories
from reports.plotting import FigureResult, plt
from reports.store import DEFAULT_TRACKING_URI, Store, StoreError, Study
from reports.tables import Table, num

log = logging.getLogger(__name__)

DEFAULT_TEMPLATE = Path("reports/RESULTS.template.md")
DEFAULT_RESULTS = Path("reports/RESULTS.md")
DEFAULT_FIGURES = Path("reports/figures")
MAX_FIGURE_WIDTH = 1000  # px
MAX_FIGURE_BYTES = 300_000
TOP_TRIALS = 5

PLACEHOLDER = re.compile(r"\{\{(.*?)\}\}")
TOKEN = re.compile(r"^\s*(?P<kind>[a-z_]+)(?::(?P<arg>[A-Za-z0-9_.\-]+(?::[A-Za-z0-9_.\-]+)?))?\s*$")
NO_ARG = ("provenance", "command", "success_table", "circle_table", "train_time_table")
WITH_ARG = ("sweep_table", "sweep_figure", "figure")
ABLATION_KINDS = ("success_table", "circle_table", "train_time_table", "figure")
SWEEP_FIGURES = ("sweep_history", "sweep_params", "sweep_intermediate")
# Machine facts a run may log (params or tags, bare or under machine.), in display order.
MACHINE_KEYS = ("host", "hostname", "machine", "platform", "cpu", "cpu_model", "cores", "cpu_count", "python")


class ResultsError(Exception):
    """Bad template or selection, reported as one line (exit code 2)."""


@dataclass(frozen=True)
class Placeholder:
    kind: str
    arg: str | None
    line: int
    text: str

    def __str__(self) -> str:
        return f"{self.text} (line {self.line})"


def parse_template(text: str) -> list[Placeholder]:
    """Every placeholder of the template, checked: an unknown or malformed one is a ResultsError naming it."""
    found = []
    for m in PLACEHOLDER.finditer(text):
        line = text.count("\n", 0, m.start()) + 1
        tok = TOKEN.match(m.group(1))
        kind, arg = (tok.group("kind"), tok.group("arg")) if tok else (None, None)
        if kind in NO_ARG and arg is None or kind in WITH_ARG and arg is not None:
            if kind == "figure" and arg not in ABLATION_FIGURES:
                raise ResultsError(f"unknown figure {arg!r} in {m.group(0)} (line {line}); known: "
                                   f"{', '.join(ABLATION_FIGURES)}")
            if kind == "sweep_figure" and ":" in arg and arg.split(":", 1)[1] not in SWEEP_FIGURES:
                raise ResultsError(f"unknown sweep figure in {m.group(0)} (line {line}); known: "
                                   f"{', '.join(SWEEP_FIGURES)}")
            if kind == "sweep_table" and ":" in arg:
                raise ResultsError(f"{m.group(0)} (line {line}): sweep_table takes a task only")
            found.append(Placeholder(kind, arg, line, m.group(0)))
            continue
        known = ", ".join([*(f"{{{{{k}}}}}" for k in NO_ARG), "{{sweep_table:TASK}}", "{{sweep_figure:TASK}}",
                           "{{figure:NAME}}"])
        raise ResultsError(f"unknown placeholder {m.group(0)} (line {line}); known: {known}")
    return found


# ------------------------------------------------------------------------------------------ selection
def _kind_of(parents: pd.DataFrame) -> pd.Series:
    kind = parents["tags.kind"] if "tags.kind" in parents else pd.Series(None, index=parents.index, dtype=object)
    return kind.fillna(parents["experiment"])


def sweep_task(study: Study) -> str:
    return str(study.parent.get("params.sweep.task") or study.parent.get("tags.task") or "?")


def _load(store: Store, parent: dict) -> Study:
    """A study with its children's columns in sorted order: MLflow returns them in an order that changes from
    one process to the next, and figures that iterate over columns (e.g. sweep panels) would follow it."""
    study = store.load(parent)
    study.children = study.children[sorted(study.children.columns)]
    return study


def select_studies(store: Store, ablation: str | None, sweep_ids: list[str] | None) -> tuple[Study | None, list[Study]]:
    """The ablation study (given, else the latest; None when the store has none) and the sweep studies
    (given, else the latest one per task)."""
    parents = store.parents()
    if parents.empty:
        raise StoreError(f"no studies in the store at {store.uri}")
    kinds = _kind_of(parents)

    def pick(ident: str, kind: str) -> Study:
        hit = parents[parents["run_id"] == ident]
        if hit.empty and "tags.study_name" in parents:
            hit = parents[parents["tags.study_name"] == ident].head(1)
        if hit.empty:
            raise StoreError(f"unknown study {ident!r} (not a parent run id or study_name) in {store.uri}")
        if kinds[hit.index[0]] != kind:
            raise StoreError(f"study {ident!r} is of kind {kinds[hit.index[0]]!r}, not {kind!r}")
        return _load(store, hit.iloc[0].to_dict())

    if ablation:
        abl = pick(ablation, "ablation")
    else:
        rows = parents[kinds == "ablation"]
        abl = _load(store, rows.iloc[0].to_dict()) if len(rows) else None
    if sweep_ids:
        chosen = [pick(s, "sweep") for s in dict.fromkeys(sweep_ids)]
        by_task: dict[str, Study] = {}
        for s in chosen:
            task = sweep_task(s)
            if task in by_task:
                raise StoreError(f"two sweep studies of task {task!r} selected ({by_task[task].name!r}, "
                                 f"{s.name!r}); pass one --sweep per task")
            by_task[task] = s
    else:
        rows = parents[kinds == "sweep"]  # newest first: the first of each task wins
        by_task = {}
        for row in rows.to_dict("records"):
            task = row.get("params.sweep.task") or row.get("tags.task") or "?"
            if isinstance(task, str) and task not in by_task:
                by_task[task] = _load(store, row)
    return abl, [by_task[t] for t in sorted(by_task)]


# ----------------------------------------------------------------------------------------- formatting
def _duration(seconds: float | None) -> str:
    if seconds is None or (isinstance(seconds, float) and math.isnan(seconds)):
        return "not logged"
    if seconds < 120:
        return f"{seconds:.1f} s"
    h, rem = divmod(int(round(seconds)), 3600)
    return f"{h} h {rem // 60:02d} min" if h else f"{rem // 60} min {rem % 60:02d} s"


def _when(ts) -> str:
    return "running" if ts is None or pd.isna(ts) else pd.Timestamp(ts).tz_convert("UTC").strftime("%Y-%m-%d %H:%M")


def _values(study: Study, *keys: str) -> list[str]:
    """Distinct non-empty values of these columns over the parent and the children, in sorted order."""
    out = set()
    for key in keys:
        v = study.parent.get(key)
        if v is not None and str(v) != "":
            out.add(str(v))
        if key in study.children:
            out |= {str(x) for x in study.children[key].dropna() if str(x) != ""}
    return sorted(out)


def _machine(study: Study) -> str:
    facts = []
    for key in MACHINE_KEYS:
        vals = _values(study, *(f"{p}{key}" for p in ("params.", "tags.", "params.machine.", "tags.machine.")))
        if vals:
            facts.append(f"{key} {', '.join(vals)}")
    return "; ".join(facts) or "not logged by the runs"


def _software(study: Study) -> str:
    names = sorted({c.removeprefix("params.version.") for c in study.parent if c.startswith("params.version.")
                    and study.parent[c]} | {c.removeprefix("params.version.") for c in study.children.columns
                                            if c.startswith("params.version.")})
    parts = [f"{n} {'/'.join(_values(study, f'params.version.{n}'))}" for n in names
             if _values(study, f"params.version.{n}")]
    return ", ".join(parts) or "not logged"


def _commits(study: Study) -> str:
    parent = study.parent.get("params.git_commit")
    others = [c for c in _values(study, "params.git_commit", "tags.changed.git_commit") if c != parent]
    text = f"`{parent}`" if parent else "not logged"
    if others:
        text += " (also in runs: " + ", ".join(f"`{c}`" for c in others) + ")"
    return text


def _range(values) -> str:
    vals = sorted({int(v) for v in values if v is not None and not pd.isna(v)})
    if not vals:
        return "–"
    return str(vals[0]) if len(vals) == 1 else f"{vals[0]}–{vals[-1]}"


# --------------------------------------------------------------------------------------------- builder
@dataclass
class Results:
    ablation: Study | None
    sweeps: list[Study]
    results_out: Path
    figures_dir: Path
    command: str
    _cache: dict = field(default_factory=dict)
    _tmp: tempfile.TemporaryDirectory = field(
        default_factory=lambda: tempfile.TemporaryDirectory(prefix="results-"), repr=False)

    # ------------------------------------------------------------------ studies
    def need_ablation(self, ph: Placeholder) -> Study:
        if self.ablation is None:
            raise ResultsError(f"{ph} needs an ablation study, and the store has none (run one, or pass --ablation)")
        return self.ablation

    def sweep_of(self, ph: Placeholder) -> Study:
        task = ph.arg.split(":", 1)[0]
        hit = [s for s in self.sweeps if sweep_task(s) == task]
        if not hit:
            have = ", ".join(f"{sweep_task(s)} ({s.name})" for s in self.sweeps) or "none"
            raise ResultsError(f"{ph}: no sweep study of task {task!r} selected (sweep studies: {have})")
        return hit[0]

    def used(self, placeholders: list[Placeholder]) -> tuple[Study | None, list[Study]]:
        """The studies the template refers to (all selected ones when it names none specifically)."""
        abl = self.ablation if any(p.kind in ABLATION_KINDS for p in placeholders) else None
        swp = list(dict.fromkeys(self.sweep_of(p).run_id for p in placeholders if p.kind.startswith("sweep_")))
        if abl is None and not swp:
            return self.ablation, self.sweeps
        return abl, [s for s in self.sweeps if s.run_id in swp]

    def check(self, placeholders: list[Placeholder]) -> None:
        """Every study the template needs is there, before anything is drawn or written."""
        for ph in placeholders:
            if ph.kind in ABLATION_KINDS:
                self.need_ablation(ph)
            elif ph.kind.startswith("sweep_"):
                self.sweep_of(ph)

    # ------------------------------------------------------------------- tables
    def summary(self, name: str) -> pd.DataFrame:
        if name not in self._cache:
            build = {"success": tables.success_summary, "circle": tables.circle_summary,
                     "train": tables.train_time_summary}[name]
            self._cache[name] = build(self.ablation)
        return self._cache[name]

    def provenance(self, studies: list[Study]) -> str:
        rows: list[tuple[str, Callable[[Study], str]]] = [
            ("kind", lambda s: s.kind),
            ("profile", lambda s: s.profile),
            ("parent run", lambda s: f"`{s.run_id}`"),
            ("git commit", _commits),
            ("machine", _machine),
            ("software", _software),
            ("seeds", self._seeds),
            ("rollouts per seed", self._rollouts_per_seed),
            ("pooled rollouts per cell", self._pooled),
            ("runs", self._runs),
            ("study wall time", lambda s: _duration(s.parent.get("metrics.time/study_seconds"))),
            ("dates (UTC)", lambda s: f"{_when(s.parent.get('start_time'))} – {_when(s.parent.get('end_time'))}"),
        ]
        columns = ["", *[s.name for s in studies]]
        table = Table("provenance", "Studies used", columns, [[label, *(f(s) for s in studies)] for label, f in rows],
                      ["study wall time: metric time/study_seconds of the study's parent run (the last session "
                       "of a resumed study); dates: start and end of the parent run.",
                       "machine: what the runs logged; software: the package versions the runs logged."])
        return table.to_markdown()

    def _seeds(self, s: Study) -> str:
        if s.kind == "sweep":
            seed = s.parent.get("params.sweep.seed")
            return f"sampler seed {seed}" if seed is not None else "–"
        return ", ".join(map(str, s.seeds)) or "–"

    def _rollouts_per_seed(self, s: Study) -> str:
        keys = ("params.sweep.eval_rollouts",) if s.kind == "sweep" else ("params.eval.rollouts",)
        return ", ".join(_values(s, *keys)) or "–"

    def _pooled(self, s: Study) -> str:
        if s is not self.ablation:
            return "–"
        agg = self.summary("success")
        ok = agg[agg["status"] != tables.GAP] if not agg.empty else agg
        return _range(ok["n"]) if len(ok) else "–"

    def _runs(self, s: Study) -> str:
        ch = s.children
        if s.kind == "sweep":  # a pruned trial is a KILLED run, not a failure
            states = sweeps.sweep_frame(s)["trial_state"].value_counts()
            return f"{len(ch)} trials ({', '.join(f'{n} {k.lower()}' for k, n in sorted(states.items()))})"
        return f"{len(ch)} ({int((ch['status'] == 'FINISHED').sum())} finished, {int(ch['failed'].sum())} failed)"

    def sweep_table(self, study: Study) -> str:
        df = sweeps.sweep_frame(study)
        direction = sweeps.direction(study)
        states = df["trial_state"].value_counts()
        space = str(study.parent.get("params.sweep.space") or "").split(",")
        sampled = [c.removeprefix("params.trial.") for c in df.columns if c.startswith("params.trial.")]
        params = [p for p in space if p in sampled] + sorted(p for p in sampled if p not in space)
        done = df[(df["trial_state"] == "COMPLETE") & df["objective"].notna()]
        done = done.assign(_key=done["objective"] if direction == "minimize" else -done["objective"])
        top = done.sort_values(["_key", "trial_no"]).head(TOP_TRIALS)
        found = sweeps.objective_label(study)
        rows = [[str(i + 1), str(r["trial_no"]), num(r["objective"], 4),
                 *(_fmt_param(r.get(f"params.trial.{p}")) for p in params)] for i, (_, r) in enumerate(top.iterrows())]
        if not rows:
            rows = [[tables.GAP, "–", "no complete trial with an objective", *("–" for _ in params)]]
        best_trial = study.parent.get("metrics.best_trial")
        best_value = study.parent.get("metrics.best_value")
        best_params = {p: study.parent.get(f"tags.best.{p}") for p in params}
        if best_value is None and len(top):  # a sweep that did not log its best on the parent
            r = top.iloc[0]
            best_trial, best_value = r["trial_no"], r["objective"]
            best_params = {p: r.get(f"params.trial.{p}") for p in params}
        if best_value is None:
            best = "best trial: none (no complete trial)"
        else:
            best = ("best trial: " + (f"#{int(best_trial)}, " if best_trial is not None else "")
                    + f"objective {num(best_value, 4)}; "
                    + ", ".join(f"{p} = {_fmt_param(v)}" for p, v in best_params.items()))
        notes = [f"Study {study.name!r} ({study.profile} profile), variant "
                 f"{study.parent.get('params.sweep.variant') or study.parent.get('tags.variant') or '?'}, sampler "
                 f"{study.parent.get('params.sweep.sampler') or '?'}; {found} ({direction}d).",
                 f"trials: {len(df)} (complete {int(states.get('COMPLETE', 0))}, pruned "
                 f"{int(states.get('PRUNED', 0))}, failed {int(states.get('FAIL', 0))}, other "
                 f"{len(df) - int(states.get('COMPLETE', 0) + states.get('PRUNED', 0) + states.get('FAIL', 0))}).",
                 best]
        table = Table(f"sweep_{sweep_task(study)}", f"Sweep on {sweep_task(study)}: top {TOP_TRIALS} trials",
                      ["rank", "trial", "objective", *params], rows, notes)
        return table.to_markdown()

    # ------------------------------------------------------------------ figures
    def figure(self, study: Study, name: str, out_name: str, build: Callable[[Path], FigureResult]) -> str:
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
            return f"> **figure unavailable: {name}** ({study.name}): {res.gap or 'no PNG written'}\n"
        small_png(png, dst)
        link = Path(os.path.relpath(dst, self.results_out.parent)).as_posix()
        text = f"![{res.title} ({study.name})]({link})\n"
        if res.partial:
            text += f"\n*Panels without data: {'; '.join(res.partial)}.*\n"
        return text

    def ablation_figure(self, ph: Placeholder) -> str:
        study = self.need_ablation(ph)
        build = ABLATION_FIGURES[ph.arg]
        return self.figure(study, ph.arg, ph.arg, lambda folder: build(self, study, folder))

    def sweep_figures(self, ph: Placeholder) -> str:
        study = self.sweep_of(ph)
        names = [ph.arg.split(":", 1)[1]] if ":" in ph.arg else list(SWEEP_FIGURES)
        task = re.sub(r"[^A-Za-z0-9_.-]+", "_", sweep_task(study))
        return "\n".join(self.figure(study, n, f"{task}_{n}", lambda folder, n=n: getattr(sweeps, n)(study, folder))
                         for n in names)

    # ------------------------------------------------------------------- render
    def render_one(self, ph: Placeholder, placeholders: list[Placeholder]) -> str:
        if ph.kind == "provenance":
            abl, swp = self.used(placeholders)
            return self.provenance([s for s in (abl, *swp) if s is not None])
        if ph.kind == "command":
            return f"```sh\n{self.command}\n```\n"
        if ph.kind == "success_table":
            return tables.success_table(self.summary("success"), self.need_ablation(ph)).to_markdown()
        if ph.kind == "circle_table":
            return tables.circle_table(self.summary("circle"), self.need_ablation(ph)).to_markdown()
        if ph.kind == "train_time_table":
            return tables.train_time_table(self.summary("train"), self.need_ablation(ph)).to_markdown()
        if ph.kind == "sweep_table":
            return self.sweep_table(self.sweep_of(ph))
        if ph.kind == "sweep_figure":
            return self.sweep_figures(ph)
        return self.ablation_figure(ph)

    def render(self, template: str) -> str:
        placeholders = parse_template(template)
        self.check(placeholders)
        by_text = {}
        for ph in placeholders:
            if ph.text not in by_text:
                by_text[ph.text] = self.render_one(ph, placeholders).rstrip("\n")
        return PLACEHOLDER.sub(lambda m: by_text[m.group(0)], template)


def _fmt_param(v) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "–"
    try:
        f = float(v)
    except (TypeError, ValueError):
        return str(v)
    return str(int(f)) if f.is_integer() and "." not in str(v) else num(f, 3)


ABLATION_FIGURES: dict[str, Callable[[Results, Study, Path], FigureResult]] = {
    "success_bars": lambda r, s, f: figures.success_bars(r.summary("success"), s, f),
    "circles": lambda r, s, f: trajectories.circles(s, f),
    "compute_time": lambda r, s, f: figures.compute_time(s, f),
    "train_time": lambda r, s, f: figures.train_time(r.summary("train"), s, f),
    "training_curves": lambda r, s, f: figures.training_curves(s, f),
    "tip_paths": lambda r, s, f: trajectories.tip_paths(s, f),
    "changing_goal": lambda r, s, f: trajectories.changing_goal(s, f),
}


def small_png(src: Path, dst: Path, max_width: int = MAX_FIGURE_WIDTH, max_bytes: int = MAX_FIGURE_BYTES) -> Path:
    """Re-save a figure as a small PNG: on white, at most max_width px wide, 256 palette colours; narrower
    still while it is over max_bytes. No metadata, so the same figure gives the same bytes."""
    from PIL import Image

    dst.parent.mkdir(parents=True, exist_ok=True)
    with Image.open(src) as im:
        rgba = im.convert("RGBA")
    flat = Image.new("RGB", rgba.size, "white")
    flat.paste(rgba, mask=rgba.getchannel("A"))
    width = min(max_width, flat.width)
    while True:
        img = flat if width == flat.width else flat.resize((width, round(flat.height * width / flat.width)),
                                                          Image.Resampling.LANCZOS)
        tmp = dst.with_name(dst.name + ".tmp")
        img.quantize(256).save(tmp, format="PNG", optimize=True)
        if tmp.stat().st_size <= max_bytes or width <= 400:
            tmp.replace(dst)
            return dst
        width = int(width * 0.8)


def regeneration_command(ablation: Study | None, sweeps_used: list[Study], template: Path, results_out: Path,
                         figures_dir: Path, tracking_uri: str | None) -> str:
    """`nox -s report -- --results ...` with the studies pinned by name (non-default paths and an explicit
    --tracking-uri kept)."""
    args = ["nox", "-s", "report", "--", "--results"]
    if tracking_uri:
        args += ["--tracking-uri", tracking_uri]
    if ablation is not None:
        args += ["--ablation", ablation.name]
    for s in sweeps_used:
        args += ["--sweep", s.name]
    for flag, value, default in (("--template", template, DEFAULT_TEMPLATE), ("--results-out", results_out,
                                 DEFAULT_RESULTS), ("--figures-dir", figures_dir, DEFAULT_FIGURES)):
        if Path(value) != default:
            args += [flag, str(value)]
    return shlex.join(args)


def write_results(store: Store, template: Path, results_out: Path, figures_dir: Path,
                  ablation: str | None = None, sweep_ids: list[str] | None = None) -> Path:
    """Render the template from the store into results_out (written only once everything rendered)."""
    try:
        text = template.read_text()
    except OSError as exc:
        raise ResultsError(f"cannot read the template {template}: {exc.strerror or exc}") from None
    placeholders = parse_template(text)  # a template error before the store is read
    abl, swp = select_studies(store, ablation, sweep_ids)
    results = Results(abl, swp, results_out, figures_dir, command="")
    results.check(placeholders)
    used_abl, used_swp = results.used(placeholders)
    # the store's URI goes into the command unless it is the default (given by --tracking-uri or the environment)
    uri = store.uri if store.uri != DEFAULT_TRACKING_URI else None
    results.command = regeneration_command(used_abl, used_swp, template, results_out, figures_dir, uri)
    out = results.render(text)
    try:
        results_out.parent.mkdir(parents=True, exist_ok=True)
        tmp = results_out.with_name(results_out.name + ".tmp")
        tmp.write_text(out)
        tmp.replace(results_out)
    except OSError as exc:
        raise ResultsError(f"cannot write {results_out}: {exc.strerror or exc}") from None
    return results_out


__all__ = ["ResultsError", "StoreError", "parse_template", "select_studies", "small_png", "write_results",
           "regeneration_command", "Results"]
