"""`python -m envs`: list, describe, render, and the unknown-task error."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from envs.__main__ import main


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("cli_cache")


def test_list_names_every_task(capsys):
    assert main(["list"]) == 0
    out = capsys.readouterr().out.splitlines()
    names = [line.split()[0] for line in out]
    for name in ("reacher", "reacher-changing-goal", "circle"):
        assert name in names
    assert any("reacher-changing-goal" in line and "trained on reacher" in line for line in out)


@pytest.mark.slow
def test_unknown_task_is_one_line_and_exit_status_2(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "envs", "describe", "nope"], capture_output=True, text=True,
                          cwd=tmp_path)
    assert proc.returncode == 2
    assert proc.stdout == ""
    errors = [line for line in proc.stderr.splitlines() if not line.startswith("pybullet build time")]
    assert len(errors) == 1 and "unknown task 'nope'" in errors[0] and "reacher" in errors[0]


def test_unknown_task_for_render_writes_nothing(tmp_path, capsys):
    assert main(["render", "nope", "--out", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "known tasks" in err[0]
    assert not list(tmp_path.iterdir())


@pytest.mark.slow
def test_describe_json(capsys, cache):
    assert main(["describe", "circle", "--json", "--cache-dir", str(cache)]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["task"] == "circle" and d["demonstrations"] == 10
    assert d["lengths"] == {"min": 100, "max": 100, "mean": 100.0}
    assert d["state"]["dim"] == 11 and d["state"]["names"][-1] == "radius"
    assert d["expert_success"] == 1.0 and d["generation_seconds"] > 0
    assert d["rejections"] == {"ik": 0, "physics": 0}


@pytest.mark.slow
def test_describe_text(capsys, cache):
    assert main(["describe", "circle", "--cache-dir", str(cache)]) == 0  # cached by the test above, or made now
    out = capsys.readouterr().out
    assert "demonstrations: 10" in out and "expert success in physics: 100%" in out and "generation time" in out


@pytest.mark.slow
@pytest.mark.parametrize("task", ["circle", "reacher-changing-goal"])
def test_render_writes_png_and_pdf(task, cache, tmp_path, capsys):
    out = tmp_path / "figs" / f"{task}.png"
    assert main(["render", task, "--out", str(out), "--cache-dir", str(cache)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 20_000
    pdf = out.with_suffix(".pdf")
    assert pdf.read_bytes()[:5] == b"%PDF-"
    assert capsys.readouterr().out.split() == [str(out), str(pdf)]


def test_render_needs_an_output_path():
    with pytest.raises(SystemExit) as exc:
        main(["render", "circle"])
    assert exc.value.code == 2
