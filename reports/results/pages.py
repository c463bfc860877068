"""RESULTS.md's notebook: {{ notebook("TOPIC") }} in the RESULTS template links the page notebook/TOPIC.md beside
RESULTS.md and renders it from its own template, notebook/TOPIC.template.md beside the RESULTS template, with the
same placeholders, studies and figures folder. RESULTS.md keeps the headline; a notebook page keeps one topic's
measurements (levers, data scaling, milestones, ...) whole. The pages are written with RESULTS.md or not at all."""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from reports.results.template import Placeholder, ResultsError

NOTEBOOK_DIR = "notebook"  # beside the RESULTS template (the pages' templates) and beside RESULTS.md (the pages)
TEMPLATE_SUFFIX = ".template.md"


@dataclass(frozen=True)
class Page:
    """One notebook page: its template, where it is written, the template's text and its placeholders."""

    topic: str
    template: Path
    out: Path
    text: str
    placeholders: list[Placeholder]

    @property
    def title(self) -> str:
        """The page's first level-1 heading (its topic when it has none)."""
        return next((line[2:].strip() for line in self.text.splitlines() if line.startswith("# ")), self.topic)


def page_template(template: Path, topic: str) -> Path:
    return template.parent / NOTEBOOK_DIR / f"{topic}{TEMPLATE_SUFFIX}"


def page_out(results_out: Path, topic: str) -> Path:
    return results_out.parent / NOTEBOOK_DIR / f"{topic}.md"


def notebook_pages(template: Path, results_out: Path, placeholders: list[Placeholder],
                   parse: Callable[[str], list[Placeholder]]) -> dict[str, Page]:
    """The pages the RESULTS template links, in its order, each read and its placeholders checked (an error names
    the page's template); a page links no further pages."""
    pages: dict[str, Page] = {}
    for ph in placeholders:
        if ph.kind != "notebook" or ph.arg in pages:
            continue
        path = page_template(template, ph.arg)
        try:
            text = path.read_text()
        except OSError as exc:
            raise ResultsError(f"{ph}: cannot read the notebook page's template {path}: {exc.strerror or exc}") \
                from None
        found = in_page(path, parse, text)
        if nested := [p for p in found if p.kind == "notebook"]:
            raise ResultsError(f"{path.name}: {nested[0]}: a notebook page links no further pages (RESULTS.md does)")
        pages[ph.arg] = Page(ph.arg, path, page_out(results_out, ph.arg), text, found)
    return pages


def in_page(path: Path, call: Callable, *args):
    """call(*args), its ResultsError naming the page's template."""
    try:
        return call(*args)
    except ResultsError as exc:
        raise ResultsError(f"{path.name}: {exc}") from None


def link(page: Page, results_out: Path) -> str:
    """The Markdown link from RESULTS.md to the page, titled by the page's heading."""
    return f"[{page.title}]({Path(os.path.relpath(page.out, results_out.parent)).as_posix()})"
