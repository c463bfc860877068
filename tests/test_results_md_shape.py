"""What a reader opens stays readable: RESULTS.md is at most 400 lines and each notebook page at most 600, none
repeats a heading, every notebook page is linked from RESULTS.md and rendered from its own template, "What is not
measured yet" names only studies that are not among the exports, every target says whose it is, and the README is
at most 120 lines with its two commands first and "Where to go next" before any figure. Reads the committed files
(tests/test_results_md_regenerates.py checks that they are what the exports render)."""

from __future__ import annotations

import re
from collections import Counter
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
REPORTS = REPO / "reports"
NOTEBOOK = REPORTS / "notebook"
RESULTS_LINES, PAGE_LINES, README_LINES = 400, 600, 120
PAGES = sorted(p for p in NOTEBOOK.glob("*.md") if not p.name.endswith(".template.md"))


def _prose(text: str) -> list[str]:
    """The lines outside code fences and HTML comments."""
    text = re.sub(r"<!--.*?-->", "", text, flags=re.S)
    out, fenced = [], False
    for line in text.splitlines():
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced:
            out.append(line)
    return out


def _headings(text: str) -> list[str]:
    return [line.strip() for line in _prose(text) if re.match(r"#{1,6} ", line)]


def _repeated(text: str) -> list[str]:
    return [h for h, n in Counter(_headings(text)).items() if n > 1]


def test_results_md_is_short_and_repeats_no_heading():
    text = (REPORTS / "RESULTS.md").read_text()
    assert len(text.splitlines()) <= RESULTS_LINES, f"RESULTS.md: {len(text.splitlines())} lines; move a topic to " \
                                                    "the notebook"
    assert not _repeated(text), f"RESULTS.md repeats headings: {_repeated(text)}"


def test_there_is_a_notebook():
    assert PAGES, "no notebook page in reports/notebook/"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_a_notebook_page_is_short_and_repeats_no_heading(page):
    text = page.read_text()
    assert len(text.splitlines()) <= PAGE_LINES, f"{page.name}: {len(text.splitlines())} lines; split the topic"
    assert not _repeated(text), f"{page.name} repeats headings: {_repeated(text)}"


def test_every_notebook_page_has_a_template_and_a_link_from_results_md():
    templates = {p.name.removesuffix(".template.md") for p in NOTEBOOK.glob("*.template.md")}
    linked = set(re.findall(r'\{\{ notebook\("([^"]+)"\) \}\}', (REPORTS / "RESULTS.template.md").read_text()))
    assert {p.stem for p in PAGES} == templates == linked
    results = (REPORTS / "RESULTS.md").read_text()
    assert all(f"](notebook/{p.name})" in results for p in PAGES)


def _section(text: str, heading: str) -> str:
    return text.split(f"\n{heading}\n", 1)[1].split("\n## ", 1)[0]


def test_what_is_not_measured_yet_names_only_studies_not_in_the_exports():
    section = _section((REPORTS / "RESULTS.md").read_text(), "## What is not measured yet")
    items = re.split(r"\n- ", "\n" + section.split("\n- ", 1)[1])[1:]
    assert items, "no items"
    exported = {p.name for p in (REPORTS / "studies").iterdir() if p.is_dir()}
    for item in items:
        named = re.search(r"Stud(?:y|ies):\s+((?:`[^`]+`(?:,\s+|\s+and\s+)?)+)", item)
        assert named, f"an item without the study it would create ('Study: `NAME`'): {item[:80]!r}"
        names = re.findall(r"`([^`]+)`", named.group(1))
        assert not set(names) & exported, f"measured already (exported): {sorted(set(names) & exported)}"


def _sentences(text: str) -> list[str]:
    prose = " ".join(line for line in _prose(text) if not line.lstrip().startswith(("|", "#")))
    return re.split(r"(?<=[.;:])\s+(?=[A-Z(])", prose)


@pytest.mark.parametrize("path", [REPORTS / "RESULTS.md", *PAGES], ids=lambda p: p.name)
def test_every_target_says_whose_it_is(path):
    """Our targets are ours, not the paper's (its Table I has no changing-goal numbers): a sentence that names a
    target says so ('our', 'ours') or names the paper's."""
    unowned = [s for s in _sentences(path.read_text()) if re.search(r"\btargets?\b", s)
               and not re.search(r"\bours?\b|\bpaper", s, re.I)]
    assert not unowned, f"{path.name}: targets without an owner: {unowned}"


def test_readme_is_short_commands_first_and_where_to_go_before_any_figure():
    text = (REPO / "README.md").read_text()
    lines = text.splitlines()
    assert len(lines) <= README_LINES, f"README.md: {len(lines)} lines; move reference material to docs/"
    assert "nox -s ablation" in lines[0] and "nox -s tests" in lines[1]
    assert text.index("## Where to go next") < text.index("!["), "a figure before 'Where to go next'"
    for doc in re.findall(r"\]\((docs/[\w-]+\.md)\)", text):
        assert (REPO / doc).is_file(), doc
