"""Comparisons of two rows of success tables, computed, so that a sentence of RESULTS.md that says "above",
"separates" or "no effect" can quote one:

    {{ compare("EVAL_TASK", "ROW", "ROW", ...) }}    a table, one line per pair of rows (A, B, A, B, ...)
    {{ difference("EVAL_TASK", "ROW", "ROW") }}      the same comparison, inline in a sentence
    {{ rate("EVAL_TASK", "ROW") }}                   one row's mean success and seed-level interval, inline
    {{ comparisons("TASK", "STUDY", ...) }}          the paper's comparisons within each named study, and each
                                                     study against the first for every variant they share

A ROW is STUDY/VARIANT, or STUDY/VARIANT+VARIANT for models of several variants pooled (e.g. the
auto-conditioned ones). Every training seed is evaluated on episodes drawn from the seed the evaluation derives
from it (experiments.evaluation.episode_seed: eval seed + training seed, whatever the variant), so seed k of one
variant and seed k of another saw the same episodes when the runs logged the same episode seed and count and
their task's episode options (envs: Task.episode_options, e.g. the start range) agree. Two single-variant rows
whose seeds pair that way are compared seed by seed (experiments.stats.paired_comparison: the per-seed
differences, their seed-level interval, the exact sign-flip p); pooled rows, or rows whose seeds did not see the
same episodes, as independent groups of models (group_comparison: Welch's interval, the exact permutation p). The
paired interval is widened where the two rows' seed-level intervals, combined (experiments.stats.paired_interval),
reach further: near 0 and 100 % a t-interval over the differences alone under-covers or shrinks to a point."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pandas as pd

from experiments.stats import group_comparison, interval, p_value, paired_comparison, points, rate_interval
from reports import paper
from reports.data.store import Study, order_variants
from reports.results.template import ROW_SEPARATOR

TITLE = "Comparisons of the variants and settings: differences, 95 % intervals, p"
POOL = "+"  # STUDY/VARIANT+VARIANT: the models of both variants as one group
# the paper's comparisons within one study: (variants A, variants B); an a.c. LSTM-MDN row against each other
PAPER_PAIRS = (
    (("ac-lstm", "ac-lstm-mdn"), ("lstm", "lstm-mdn")),  # auto-conditioning, both heads pooled
    (("lstm-mdn", "ac-lstm-mdn"), ("lstm", "ac-lstm")),  # the mixture head, both trainings pooled
    (("ac-lstm",), ("lstm",)),
    (("lstm-mdn",), ("lstm",)),
    (("ac-lstm-mdn",), ("ac-lstm",)),
    (("ac-lstm-mdn",), ("lstm-mdn",)),
    (("ac-lstm-mdn",), ("lstm",)),
)
COLUMNS = ["task", "A", "B", "A − B (points)", "95% interval", "p", "test"]
NOTE = ("A − B: difference of the mean success over seeds, in percentage points. paired: seed k of A and of B "
        "were evaluated on the same episodes; the interval is the t-interval over the per-seed differences and p "
        "the exact sign-flip p (with 3 seeds never below 0.25). groups: the models' rates as two independent "
        "groups (pooled variants, or seeds that saw different episodes); Welch's t-interval and the exact "
        "permutation p. A paired interval is widened where A's and B's seed-level intervals, combined, reach "
        "further (near 0 and 100 %, where a t-interval over the differences alone shrinks to a point). No "
        "correction for the number of comparisons.")


class ComparisonError(ValueError):
    """A row that names no finished runs, or is not STUDY/VARIANT[+VARIANT...]."""


def parse_row(text: str) -> tuple[str, tuple[str, ...]]:
    """'STUDY/VARIANT+VARIANT' -> (STUDY, (VARIANT, VARIANT))."""
    study, sep, variants = text.rpartition(ROW_SEPARATOR)
    names = tuple(v for v in variants.split(POOL) if v)
    if not sep or not study or not names:
        raise ComparisonError(f"{text!r} is not STUDY{ROW_SEPARATOR}VARIANT[{POOL}VARIANT...]")
    return study, names


@dataclass(frozen=True)
class Side:
    """The finished runs of one row on one evaluated task: one line per model (variant, seed)."""

    label: str
    variants: tuple[str, ...]
    runs: pd.DataFrame  # variant, seed, success_rate, n_rollouts, episode_seed, episodes (episode options)
    split: str = "test"  # "validation" when a study of the row was evaluated on the validation episodes

    def rates(self) -> dict[int, float]:
        return {int(s): float(r) for s, r in zip(self.runs["seed"], self.runs["success_rate"], strict=True)}

    def rollouts(self) -> dict[int, float]:
        """seed -> the episodes its rate is over."""
        return {int(s): float(n) for s, n in zip(self.runs["seed"], self.runs["n_rollouts"], strict=True)}

    def episodes(self) -> dict[int, tuple]:
        """seed -> what identifies its episodes (episode seed, count, the task's episode options)."""
        return {int(r.seed): (r.episode_seed, r.n_rollouts, r.episodes) for r in self.runs.itertuples()}


def _runs(study: Study, variant: str, eval_task: str) -> pd.DataFrame:
    """The study's finished runs of `variant` with a success rate on `eval_task`, and what identifies their
    episodes."""
    from envs.tasks import task_class  # imported only here: it pulls in torch and pybullet

    evals = study.eval_metrics()
    if evals.empty or not {"success_rate", "n_rollouts"} <= set(evals.columns):
        runs = evals.iloc[:0]
    else:
        runs = evals[(evals["status"] == "FINISHED") & (evals["eval_task"] == eval_task)
                     & (evals["variant"] == variant) & evals["success_rate"].notna()]
    if runs.empty:
        raise ComparisonError(f"study {study.name!r} has no finished {variant} run evaluated on {eval_task}")
    options = [f"params.data.{k}" for k in task_class(eval_task).episode_options]
    params = study.children.set_index("run_id")
    keys = [tuple(None if c not in params or pd.isna(params.at[r, c]) else str(params.at[r, c]) for c in options)
            for r in runs["run_id"]]
    seeds = runs["episode_seed"] if "episode_seed" in runs else pd.Series(math.nan, index=runs.index)
    return pd.DataFrame({"variant": variant, "seed": runs["seed"].astype(int).to_numpy(),
                         "success_rate": runs["success_rate"].to_numpy(float),
                         "n_rollouts": runs["n_rollouts"].to_numpy(float), "episode_seed": seeds.to_numpy(float),
                         "episodes": keys})


def side(sources: dict[str, Study], eval_task: str, with_study: bool = True) -> Side:
    """A row from each of its variants' study (variant -> study), labelled with its variants and, if
    `with_study`, their studies."""
    variants = tuple(sources)
    label = " + ".join(paper.variant_label(v) for v in variants)
    if with_study:
        label += f" ({', '.join(dict.fromkeys(s.name for s in sources.values()))})"
    runs = pd.concat([_runs(study, v, eval_task) for v, study in sources.items()], ignore_index=True)
    split = "validation" if any(s.split == "validation" for s in sources.values()) else "test"
    return Side(label, variants, runs, split)


def _same_episodes(a: Side, b: Side) -> bool:
    """Seed by seed, A and B saw the same episodes (see the module's docstring), on at least two seeds."""
    ea, eb = a.episodes(), b.episodes()
    common = set(ea) & set(eb)
    return len(common) >= 2 and all(ea[s] == eb[s] and not math.isnan(ea[s][0]) for s in common)


def compare(a: Side, b: Side) -> dict:
    """experiments.stats' paired comparison when A and B are single variants whose seeds pair, else the group
    comparison of their models; plus the rows' labels."""
    if len(a.variants) == len(b.variants) == 1 and _same_episodes(a, b):
        out = paired_comparison(a.rates(), b.rates(), a.rollouts(), b.rollouts())
    else:
        out = group_comparison(list(a.runs["success_rate"]), list(b.runs["success_rate"]))
    return {"A": a.label, "B": b.label, **out, "validation": "validation" in (a.split, b.split)}


def _test(c: dict) -> str:
    """How the rows were compared, and that a row was evaluated on the validation episodes where one was."""
    label = f"paired, {c['n']} seeds" if c["test"] == "paired" else f"groups, {c['n']} models"
    return label + (", validation episodes" if c.get("validation") else "")


def table_row(eval_task: str, c: dict) -> list[str]:
    return [paper.task_label(eval_task), c["A"], c["B"], points(c["difference"]), _points_interval(c),
            p_value(c["p"]), _test(c)]


def _points_interval(c: dict) -> str:
    return "–" if math.isnan(c["low"]) else f"{points(c['low'])} to {points(c['high'])}"


def sentence(c: dict) -> str:
    """One comparison inline: '+35 points (95 % interval +12 to +58; paired, 3 seeds; p = 0.25)'."""
    p = p_value(c["p"])
    return (f"{points(c['difference'])} points (95 % interval {_points_interval(c)}; {_test(c)}; "
            f"p {p if p.startswith('<') else '= ' + p})")


def rate_sentence(studies: dict[str, Study], eval_task: str, row: str) -> str:
    """{{ rate(...) }}: a row's mean success over its seeds inline, with the seed-level interval a sentence
    about a target quotes: '96 % (seed-level 95 % interval 89-100 %; 5 seeds)'."""
    study, variants = parse_row(row)
    row_side = side(dict.fromkeys(variants, studies[study]), eval_task)
    rates = list(row_side.runs["success_rate"])
    low, high = rate_interval(rates, list(row_side.runs["n_rollouts"]))
    where = "; validation episodes" if row_side.split == "validation" else ""
    return f"{100 * np.mean(rates):.0f} % (seed-level 95 % interval {interval(low, high)}; {len(rates)} seeds{where})"


def between(studies: dict[str, Study], eval_task: str, a: str, b: str) -> dict:
    """The comparison of two ROWs (STUDY/VARIANT[+VARIANT...]) on `eval_task`; `studies` by name."""
    (sa, va), (sb, vb) = parse_row(a), parse_row(b)
    return compare(side(dict.fromkeys(va, studies[sa]), eval_task), side(dict.fromkeys(vb, studies[sb]), eval_task))


def compare_table(studies: dict[str, Study], eval_task: str, rows: tuple[str, ...]) -> str:
    """{{ compare(...) }}: one table row per pair of ROWs (A, B, A, B, ...), with the note."""
    lines = [table_row(eval_task, between(studies, eval_task, a, b)) for a, b in zip(rows[::2], rows[1::2],
                                                                                     strict=True)]
    return pd.DataFrame(lines, columns=COLUMNS).to_markdown(index=False) + f"\n\n- {NOTE}\n"


def _finished(study: Study, task: str) -> pd.DataFrame:
    """The study's finished runs of training task `task` with a success rate, one row per evaluated task."""
    evals = study.eval_metrics()
    if evals.empty or "success_rate" not in evals:
        return evals.iloc[:0]
    return evals[(evals["task"] == task) & (evals["status"] == "FINISHED") & evals["success_rate"].notna()]


def paper_rows(studies: list[Study], task: str) -> pd.DataFrame:
    """{{ comparisons(...) }}: for every task TASK's models were evaluated on, the PAPER_PAIRS within each named
    study, then each later study against the first for every variant both trained; one row per comparison, the
    columns of the table (COLUMNS). Studies that share no variant (e.g. the auto-conditioned models of one and
    the plain ones of another, on the same protocol) are read as one table instead."""
    out = []
    finished = {s.name: _finished(s, task) for s in studies}
    eval_tasks = dict.fromkeys(t for f in finished.values() for t in f["eval_task"])
    variant_sets = [set(f["variant"]) for f in finished.values()]
    one_table = len(studies) > 1 and sum(map(len, variant_sets)) == len(set().union(*variant_sets))
    tables = [studies] if one_table else [[s] for s in studies]
    for eval_task in eval_tasks:
        for group in tables:
            where = {v: s for s in group for v in finished[s.name].loc[finished[s.name]["eval_task"] == eval_task,
                                                                         "variant"]}
            for va, vb in PAPER_PAIRS:
                if set(va) | set(vb) <= set(where):
                    a, b = ({v: where[v] for v in vs} for vs in (va, vb))
                    out.append(table_row(eval_task, compare(side(a, eval_task, len(studies) > 1),
                                                            side(b, eval_task, len(studies) > 1))))
        if one_table:
            continue
        have = {name: set(f.loc[f["eval_task"] == eval_task, "variant"]) for name, f in finished.items()}
        first = studies[0]
        for study in studies[1:]:
            for variant in order_variants(have[study.name] & have[first.name]):
                out.append(table_row(eval_task, compare(side({variant: study}, eval_task),
                                                        side({variant: first}, eval_task))))
    return pd.DataFrame(out, columns=COLUMNS)


def paper_table(rows: pd.DataFrame) -> pd.DataFrame:
    """paper_rows are already the table's rows."""
    return rows
