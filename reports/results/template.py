"""The RESULTS.md template language: Jinja2, restricted to the placeholders reports.results.writer fills, checked
before any study is read so that a typo is one line naming it (with its line), not a half-written file.

    {{ provenance }}  {{ command }}  {{ success_table }}  {{ circle_table }}  {{ train_time_table }}
    {{ figure("NAME") }}  {{ sweep_table("TASK") }}  {{ sweep_figure("TASK") }}  {{ sweep_figure("TASK", "NAME") }}
    {{ data_scaling("TASK", "STUDY", "STUDY", ...) }}  {{ lever("TASK", "STUDY", "STUDY", ...) }}
    {{ goal_switch("TASK", "STUDY", "STUDY", ...) }}  {{ stacking("TASK", "STUDY", "STUDY", ...) }}
    {{ pick_place_failures("TASK", "STUDY", "STUDY", ...) }}  {{ placement("TASK", "STUDY", "STUDY", ...) }}
    {{ comparisons("TASK", "STUDY", ...) }}  {{ compare("EVAL_TASK", "ROW", "ROW", ...) }}
    {{ difference("EVAL_TASK", "ROW", "ROW") }}  {{ rate("EVAL_TASK", "ROW") }}
    (a ROW is STUDY/VARIANT[+VARIANT...]: reports.results.comparisons)
    {{ table_one("TASK=STUDY", ...) }}  then {{ claims }}  {{ headline_train_time }}  (from its sources)
    {{ notebook("TOPIC") }}  (a link to a notebook page, rendered from its own template: reports.results.pages)

The ablation tables and figures take an optional study="NAME" (a study_name or parent run id), e.g.
{{ success_table(study="multimodal") }} or {{ figure("tip_paths", study="multimodal") }}; without it they show
the --ablation study. The names of the tables and figures are the caller's registries (reports.results.writer).
"""

from __future__ import annotations

import re
from collections.abc import Collection
from dataclasses import dataclass

from jinja2 import Environment, StrictUndefined, TemplateSyntaxError, nodes

FIXED = ("provenance", "command")
# placeholders without arguments that read the sources of the template's one {{ table_one("TASK=STUDY", ...) }}
# (Table I: each training task's cells from the study named for it; reports.study_report.table_one)
HEADLINE = ("claims", "headline_train_time")
SOURCE_SEPARATOR = "="
# placeholders whose arguments are a training task, then the studies (reports.results.across.ACROSS:
# reports.analyses.data_scaling, reports.analyses.levers, reports.analyses.goal_switch, reports.analyses.stacking,
# reports.analyses.pick_place_failures, reports.analyses.placement)
MULTI_STUDY = ("data_scaling", "lever", "goal_switch", "stacking", "pick_place_failures", "placement", "comparisons")
# placeholders whose arguments are an evaluated task, then pairs of rows STUDY/VARIANT[+VARIANT...]
# (reports.results.comparisons)
ROW_PAIRS = ("compare", "difference")
ROW_KINDS = (*ROW_PAIRS, "rate")  # placeholders whose arguments are an evaluated task, then rows
ROW_SEPARATOR = "/"
# name -> (min, max) arguments
WITH_ARG = {"figure": (1, 1), "sweep_table": (1, 1), "sweep_figure": (1, 2), **{k: (2, 12) for k in MULTI_STUDY},
            "compare": (3, 21), "difference": (3, 3), "rate": (2, 2), "table_one": (1, 8), "notebook": (1, 1)}
SWEEP_FIGURES = ("sweep_history", "sweep_params", "sweep_intermediate", "sweep_importance")
STUDY = "study"  # the keyword that picks an ablation-kind placeholder's study

# Markdown, not HTML: nothing is escaped; the file keeps its final newline.
ENV = Environment(undefined=StrictUndefined, autoescape=False, keep_trailing_newline=True)


class ResultsError(Exception):
    """Bad template or selection, reported as one line (exit code 2)."""


@dataclass(frozen=True)
class Placeholder:
    kind: str
    args: tuple[str, ...]
    line: int
    study: str | None = None  # study="NAME" of an ablation table or figure

    @property
    def text(self) -> str:
        args = [f'"{a}"' for a in self.args] + ([f'{STUDY}="{self.study}"'] if self.study is not None else [])
        return f"{{{{ {self.kind}({', '.join(args)}) }}}}" if args else f"{{{{ {self.kind} }}}}"

    @property
    def arg(self) -> str | None:
        return self.args[0] if self.args else None

    @property
    def studies(self) -> tuple[str, ...]:
        """The studies it names: those after the task of a MULTI_STUDY one, those of the rows of a ROW_PAIRS one,
        else its study="NAME" if any."""
        if self.kind in MULTI_STUDY:
            return self.args[1:]
        if self.kind == "table_one":
            return tuple(dict.fromkeys(a.partition(SOURCE_SEPARATOR)[2] for a in self.args))
        if self.kind in ROW_KINDS:
            return tuple(dict.fromkeys(row.rpartition(ROW_SEPARATOR)[0] for row in self.args[1:]))
        return () if self.study is None else (self.study,)

    @property
    def key(self) -> tuple:
        """Equal for the same placeholder written twice (drawn once)."""
        return self.kind, self.args, self.study

    def __str__(self) -> str:
        return f"{self.text} (line {self.line})"


@dataclass(frozen=True)
class Vocabulary:
    """The ablation-kind tables ({{ NAME }}) and figures ({{ figure("NAME") }}) a template may use."""

    tables: Collection[str]
    figures: Collection[str]

    @property
    def known(self) -> str:
        return ", ".join([*(f"{{{{ {k} }}}}" for k in (*FIXED, *HEADLINE, *self.tables)), '{{ figure("NAME") }}',
                          '{{ sweep_table("TASK") }}', '{{ sweep_figure("TASK"[, "NAME"]) }}',
                          *(f'{{{{ {k}("TASK", "STUDY", ...) }}}}' for k in MULTI_STUDY),
                          '{{ compare("EVAL_TASK", "STUDY/VARIANT", "STUDY/VARIANT", ...) }}',
                          '{{ difference("EVAL_TASK", "STUDY/VARIANT", "STUDY/VARIANT") }}',
                          '{{ rate("EVAL_TASK", "STUDY/VARIANT") }}', '{{ table_one("TASK=STUDY", ...) }}',
                          '{{ notebook("TOPIC") }}'])


def _call(node: nodes.Call, vocab: Vocabulary) -> Placeholder:
    name = node.node.name if isinstance(node.node, nodes.Name) else None
    if (name not in WITH_ARG and name not in vocab.tables) or node.dyn_args or node.dyn_kwargs:
        raise ResultsError(f"unknown placeholder call (line {node.lineno}); known: {vocab.known}")
    values = [*node.args, *(k.value for k in node.kwargs)]
    if not all(isinstance(a, nodes.Const) and isinstance(a.value, str) for a in values):
        raise ResultsError(f"{name}(...) (line {node.lineno}) takes quoted names only")
    kwargs = {k.key: k.value.value for k in node.kwargs}
    ablation_kind = name == "figure" or name in vocab.tables
    if set(kwargs) - {STUDY} or (kwargs and not ablation_kind):
        allowed = f'only {STUDY}="NAME"' if ablation_kind else "no keyword"
        raise ResultsError(f"{name}(...) (line {node.lineno}) takes {allowed}")
    ph = Placeholder(name, tuple(a.value for a in node.args), node.lineno, kwargs.get(STUDY))
    if name in vocab.tables and ph.args:
        raise ResultsError(f'{ph}: {name} takes only {STUDY}="NAME"')
    lo, hi = WITH_ARG.get(name, (0, 0))
    if not lo <= len(ph.args) <= hi:
        raise ResultsError(f"{ph}: {name} takes {lo}" + (f" or {hi}" if hi > lo else "") + " argument(s)")
    if name == "figure" and ph.arg not in vocab.figures:
        raise ResultsError(f"unknown figure {ph.arg!r} in {ph}; known: {', '.join(vocab.figures)}")
    if name in ROW_PAIRS and (len(ph.args) % 2 == 0 or not all(ROW_SEPARATOR in a.strip(ROW_SEPARATOR)
                                                                for a in ph.args[1:])):
        raise ResultsError(f"{ph}: {name} takes an evaluated task, then pairs of rows STUDY{ROW_SEPARATOR}VARIANT")
    if name == "rate" and ROW_SEPARATOR not in ph.args[1].strip(ROW_SEPARATOR):
        raise ResultsError(f"{ph}: rate takes an evaluated task, then a row STUDY{ROW_SEPARATOR}VARIANT")
    if name == "table_one":
        tasks = [a.partition(SOURCE_SEPARATOR)[0] for a in ph.args]
        if not all(t and s for t, _, s in (a.partition(SOURCE_SEPARATOR) for a in ph.args)) or \
                len(set(tasks)) < len(tasks):
            raise ResultsError(f"{ph}: table_one takes TASK{SOURCE_SEPARATOR}STUDY, one per training task (and "
                              "per evaluated task that names its own)")
    if name == "notebook" and not re.fullmatch(r"[a-z0-9]+(-[a-z0-9]+)*", ph.arg):
        raise ResultsError(f"{ph}: a notebook topic is lower-case words joined by '-', e.g. \"data-scaling\"")
    if name == "sweep_figure" and len(ph.args) == 2 and ph.args[1] not in SWEEP_FIGURES:
        raise ResultsError(f"unknown sweep figure {ph.args[1]!r} in {ph}; known: {', '.join(SWEEP_FIGURES)}")
    return ph


def parse(text: str, vocab: Vocabulary) -> list[Placeholder]:
    """Every placeholder of the template in document order, checked: a syntax error, an unknown name or a bad
    argument is a ResultsError naming it and its line."""
    try:
        tree = ENV.parse(text)
    except TemplateSyntaxError as exc:
        raise ResultsError(f"template syntax error (line {exc.lineno}): {exc.message}") from None
    found = []
    calls = {id(n.node) for n in tree.find_all(nodes.Call)}  # the Name nodes that are called
    for node in tree.find_all((nodes.Call, nodes.Name)):
        if isinstance(node, nodes.Call):
            found.append(_call(node, vocab))
        elif id(node) not in calls:
            if node.name in WITH_ARG:
                raise ResultsError(f"{{{{ {node.name} }}}} (line {node.lineno}) needs its argument: "
                                   f"{{{{ {node.name}(\"...\") }}}}")
            if node.name not in (*FIXED, *HEADLINE) and node.name not in vocab.tables:
                raise ResultsError(f"unknown placeholder {{{{ {node.name} }}}} (line {node.lineno}); known: "
                                   f"{vocab.known}")
            found.append(Placeholder(node.name, (), node.lineno))
    return sorted(found, key=lambda p: p.line)  # find_all is depth-first; the file reads by line


class _Value(str):
    """A rendered placeholder name: printed as is ({{ success_table }}) or called ({{ success_table(study=...) }})."""

    def __new__(cls, text: str, kind: str, by_key: dict):
        value = super().__new__(cls, text)
        value.kind, value.by_key = kind, by_key
        return value

    def __call__(self, *args: str, study: str | None = None) -> str:
        return self.by_key[(self.kind, args, study)]


def render(text: str, values: dict[Placeholder, str]) -> str:
    """The template with each placeholder replaced by its rendered text (values from parse's list)."""
    by_key = {p.key: v for p, v in values.items()}
    names = {p.kind for p in values}
    return ENV.from_string(text).render({k: _Value(by_key.get((k, (), None), ""), k, by_key) for k in names})
