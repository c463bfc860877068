"""reports/RESULTS.md and its notebook pages (reports/notebook/*.md) regenerate from the repository alone: rendering
the committed templates from the committed study exports (reports/studies/) gives the committed files, byte for
byte, apart from the output paths in RESULTS.md's command line."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from reports.__main__ import main

REPO = Path(__file__).resolve().parents[1]
COMMAND = re.compile(r"```sh\nnox -s report -- --results .*?\n```", re.S)
NOTEBOOK = REPO / "reports" / "notebook"


@pytest.mark.slow
def test_committed_results_md_and_notebook_are_what_the_committed_exports_render(tmp_path):
    committed = (REPO / "reports" / "RESULTS.md").read_text()
    pins = re.findall(r"(--(?:ablation|sweep) \S+)", COMMAND.search(committed).group(0))
    out = tmp_path / "reports" / "RESULTS.md"
    assert main(["--results", "--exports", str(REPO / "reports" / "studies"), *" ".join(pins).split(),
                 "--template", str(REPO / "reports" / "RESULTS.template.md"), "--results-out", str(out),
                 "--figures-dir", str(tmp_path / "reports" / "figures")]) == 0
    rendered = out.read_text()
    assert COMMAND.sub("", rendered) == COMMAND.sub("", committed)
    pages = sorted(p.name for p in NOTEBOOK.glob("*.md") if not p.name.endswith(".template.md"))
    assert pages == sorted(p.name for p in (tmp_path / "reports" / "notebook").glob("*.md")), \
        "the committed notebook pages are not those RESULTS.template.md links"
    for name in pages:
        assert (tmp_path / "reports" / "notebook" / name).read_text() == (NOTEBOOK / name).read_text(), name
