"""The RESULTS.md template language: Jinja2, restricted to the placeholders reports.results fills, checked
before any study is read so that a typo is one line naming it (with its line), not a half-written file.

    {{ provenance }}  {{ command }}  {{ success_table }}  {{ circle_table }}  {{ train_time_table }}
    {{ figure("NAME") }}  {{ sweep_table("TASK") }}  {{ sweep_figure("TASK") }}  {{ sweep_figure("TASK", "NAME") }}
"""

from __future__ import annotations

from dataclasses import dataclass

from jinja2 import Environment, StrictUndefined, TemplateSyntaxError, nodes

NO_ARG = ("provenance", "command", "success_table", "circle_table", "train_time_table")
WITH_ARG = {"figure": (1, 1), "sweep_table": (1, 1), "sweep_figure": (1, 2)}  # name -> (min, max) arguments
ABLATION_KINDS = ("success_table", "circle_table", "train_time_table", "figure")
ABLATION_FIGURES = ("success_bars", "circles", "compute_time", "train_time", "training_curves", "tip_paths",
                    "changing_goal")
SWEEP_FIGURES = ("sweep_history", "sweep_params", "sweep_intermediate", "sweep_importance")
KNOWN = ", ".join([*(f"{{{{ {k} }}}}" for k in NO_ARG), '{{ figure("NAME") }}', '{{ sweep_table("TASK") }}',
                   '{{ sweep_figure("TASK"[, "NAME"]) }}'])

# Markdown, not HTML: nothing is escaped; the file keeps its final newline.
ENV = Environment(undefined=StrictUndefined, autoescape=False, keep_trailing_newline=True)


class ResultsError(Exception):
    """Bad template or selection, reported as one line (exit code 2)."""


@dataclass(frozen=True)
class Placeholder:
    kind: str
    args: tuple[str, ...]
    line: int

    @property
    def text(self) -> str:
        if self.kind in NO_ARG:
            return f"{{{{ {self.kind} }}}}"
        return f"{{{{ {self.kind}({', '.join(map(repr, self.args))}) }}}}".replace("'", '"')

    @property
    def arg(self) -> str | None:
        return self.args[0] if self.args else None

    def __str__(self) -> str:
        return f"{self.text} (line {self.line})"


def _call(node: nodes.Call) -> Placeholder:
    name = node.node.name if isinstance(node.node, nodes.Name) else None
    if name not in WITH_ARG or node.kwargs or node.dyn_args or node.dyn_kwargs:
        raise ResultsError(f"unknown placeholder call (line {node.lineno}); known: {KNOWN}")
    if not all(isinstance(a, nodes.Const) and isinstance(a.value, str) for a in node.args):
        raise ResultsError(f"{name}(...) (line {node.lineno}) takes quoted names only")
    lo, hi = WITH_ARG[name]
    ph = Placeholder(name, tuple(a.value for a in node.args), node.lineno)
    if not lo <= len(ph.args) <= hi:
        raise ResultsError(f"{ph}: {name} takes {lo}" + (f" or {hi}" if hi > lo else "") + " argument(s)")
    if name == "figure" and ph.arg not in ABLATION_FIGURES:
        raise ResultsError(f"unknown figure {ph.arg!r} in {ph}; known: {', '.join(ABLATION_FIGURES)}")
    if name == "sweep_figure" and len(ph.args) == 2 and ph.args[1] not in SWEEP_FIGURES:
        raise ResultsError(f"unknown sweep figure {ph.args[1]!r} in {ph}; known: {', '.join(SWEEP_FIGURES)}")
    return ph


def parse_template(text: str) -> list[Placeholder]:
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
            found.append(_call(node))
        elif id(node) not in calls:
            if node.name in WITH_ARG:
                raise ResultsError(f"{{{{ {node.name} }}}} (line {node.lineno}) needs its argument: "
                                   f"{{{{ {node.name}(\"...\") }}}}")
            if node.name not in NO_ARG:
                raise ResultsError(f"unknown placeholder {{{{ {node.name} }}}} (line {node.lineno}); known: {KNOWN}")
            found.append(Placeholder(node.name, (), node.lineno))
    return sorted(found, key=lambda p: p.line)  # find_all is depth-first; the file reads by line


def render(text: str, values: dict[Placeholder, str]) -> str:
    """The template with each placeholder replaced by its rendered text (values from parse_template's list)."""
    by_name = {p.kind: v for p, v in values.items() if p.kind in NO_ARG}
    by_call = {(p.kind, p.args): v for p, v in values.items() if p.kind in WITH_ARG}
    functions = {k: (lambda *args, k=k: by_call[(k, args)]) for k in WITH_ARG}
    return ENV.from_string(text).render(**by_name, **functions)
