"""The "Studies used" table of RESULTS.md: per study its kind, profile, parent run, git commit, machine and
software as the runs logged them, seeds, rollouts, runs, wall time and dates."""

from __future__ import annotations

import math
from collections.abc import Callable

import pandas as pd

from reports.data.store import Study
from reports.study_report import sweep_summary
from reports.study_report.tables import GAP, Table

# Machine facts a run may log (params or tags, bare or under machine.), in display order.
MACHINE_KEYS = ("host", "hostname", "machine", "platform", "cpu", "cpu_model", "cores", "cpu_count", "python")


def duration(seconds: float | None) -> str:
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


def _seeds(s: Study) -> str:
    if s.kind == "sweep":
        seed = s.parent.get("params.sweep.seed")
        return f"sampler seed {seed}" if seed is not None else "–"
    return ", ".join(map(str, s.seeds)) or "–"


def _rollouts_per_seed(s: Study) -> str:
    keys = ("params.sweep.eval_rollouts",) if s.kind == "sweep" else ("params.eval.rollouts",)
    return ", ".join(_values(s, *keys)) or "–"


def _runs(s: Study) -> str:
    ch = s.children
    if s.kind == "sweep":  # a pruned trial is a KILLED run, not a failure
        states = sweep_summary.sweep_frame(s)["trial_state"].value_counts()
        return f"{len(ch)} trials ({', '.join(f'{n} {k.lower()}' for k, n in sorted(states.items()))})"
    return f"{len(ch)} ({int((ch['status'] == 'FINISHED').sum())} finished, {int(ch['failed'].sum())} failed)"


def provenance_table(studies: list[Study], success: Callable[[Study], pd.DataFrame | None]) -> Table:
    """One column per study. success(study): its aggregated success rows (reports.study_report.tables.success_summary),
    or None for a study without a success table (the pooled-rollouts row then reads '–')."""
    def pooled(s: Study) -> str:
        agg = success(s)
        if agg is None or agg.empty:
            return "–"
        ok = agg[agg["status"] != GAP]
        return _range(ok["n"]) if len(ok) else "–"

    rows: list[tuple[str, Callable[[Study], str]]] = [
        ("kind", lambda s: s.kind),
        ("profile", lambda s: s.profile),
        ("parent run", lambda s: f"`{s.source_run_id}`"),
        ("git commit", _commits),
        ("machine", _machine),
        ("software", _software),
        ("seeds", _seeds),
        ("rollouts per seed", _rollouts_per_seed),
        ("pooled rollouts per cell", pooled),
        ("runs", _runs),
        ("study wall time", lambda s: duration(s.parent.get("metrics.time/study_seconds"))),
        ("dates (UTC)", lambda s: f"{_when(s.parent.get('start_time'))} – {_when(s.parent.get('end_time'))}"),
    ]
    return Table("provenance", "Studies used", ["", *[s.name for s in studies]],
                 [[label, *(f(s) for s in studies)] for label, f in rows],
                 ["study wall time: metric time/study_seconds of the study's parent run (the last session "
                  "of a resumed study); dates: start and end of the parent run.",
                  "machine: what the runs logged; software: the package versions the runs logged."])
