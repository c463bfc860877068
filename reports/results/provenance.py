"""The "Studies used" table of RESULTS.md: one row per study with its kind, its parent run, the commits it ran at,
its dates and wall time, its runs and seeds; the machines and software its runs logged, merged over the studies,
under it."""

from __future__ import annotations

import math

import pandas as pd

from reports.data.store import Study
from reports.study_report import sweep_summary
from reports.study_report.tables import Table

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


COMMIT_CHARS = 7  # commits as git abbreviates them


def _commits(study: Study) -> str:
    """The parent run's commit first, then the others the runs logged (a study resumed or extended later)."""
    parent = study.parent.get("params.git_commit")
    others = [c for c in _values(study, "params.git_commit", "tags.changed.git_commit") if c != parent]
    return ", ".join(f"`{c[:COMMIT_CHARS]}`" for c in [*([parent] if parent else []), *others]) or "not logged"


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


def _runs(s: Study) -> str:
    ch = s.children
    if s.kind == "sweep":  # a pruned trial is a KILLED run, not a failure
        states = sweep_summary.sweep_frame(s)["trial_state"].value_counts()
        return f"{len(ch)} trials ({', '.join(f'{n} {k.lower()}' for k, n in sorted(states.items()))})"
    stopped = int((ch["status"] == "KILLED").sum())  # Ctrl-C: resumable, not a failure
    return (f"{len(ch)} ({int((ch['status'] == 'FINISHED').sum())} finished, "
            + (f"{stopped} stopped, " if stopped else "") + f"{int(ch['failed'].sum()) - stopped} failed)")


def _software_of(studies: list[Study]) -> str:
    """Every package version the runs of the studies logged, merged: 'name v1/v2, ...'."""
    versions: dict[str, set[str]] = {}
    for s in studies:
        for part in filter(None, _software(s).removeprefix("not logged").split(", ")):
            name, _, vals = part.partition(" ")
            versions.setdefault(name, set()).update(vals.split("/"))
    return ", ".join(f"{n} {'/'.join(sorted(v))}" for n, v in sorted(versions.items())) or "not logged"


def provenance_table(studies: list[Study]) -> Table:
    """One row per study: its kind, parent run, the commits it ran at, its dates and wall time, its runs and seeds; the
    machines and software the runs logged, merged over the studies, in the notes."""
    rows = [[s.name, s.kind, f"`{s.source_run_id}`", _commits(s),
             f"{_when(s.parent.get('start_time'))} – {_when(s.parent.get('end_time'))}",
             duration(s.parent.get("metrics.time/study_seconds")), _runs(s), _seeds(s)] for s in studies]
    machines = sorted({_machine(s) for s in studies})
    return Table("provenance", "Studies used", ["study", "kind", "parent run", "commits", "dates (UTC)", "wall time",
                                                "runs", "seeds"], rows,
                 ["parent run: its id in the store the study ran in; commits: the parent run's first, then any "
                  "other the runs logged (a study resumed or extended at a later commit); dates: start and end of "
                  "the parent run; wall time: metric time/study_seconds of the parent run (the last session of a "
                  "resumed study).",
                  f"machines the runs logged: {' | '.join(machines)}.",
                  f"software the runs logged: {_software_of(studies)}."])
