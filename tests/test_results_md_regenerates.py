"""reports/RESULTS.md regenerates from the repository alone: rendering the committed template from the committed
study exports (reports/studies/) gives the committed file, apart from the output paths in its command line."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from reports.__main__ import main

REPO = Path(__file__).resolve().parents[1]
COMMAND = re.compile(r"```sh\nnox -s report -- --results .*?\n```", re.S)


@pytest.mark.slow
def test_committed_results_md_is_what_the_committed_exports_render(tmp_path):
    committed = (REPO / "reports" / "RESULTS.md").read_text()
    pins = re.findall(r"(--(?:ablation|sweep) \S+)", COMMAND.search(committed).group(0))
    out = tmp_path / "reports" / "RESULTS.md"
    assert main(["--results", "--exports", str(REPO / "reports" / "studies"), *" ".join(pins).split(),
                 "--template", str(REPO / "reports" / "RESULTS.template.md"), "--results-out", str(out),
                 "--figures-dir", str(tmp_path / "reports" / "figures")]) == 0
    rendered = out.read_text()
    assert COMMAND.sub("", rendered) == COMMAND.sub("", committed)
