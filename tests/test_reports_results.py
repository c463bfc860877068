"""RESULTS.md generation (reports.results.writer, `python -m reports --results`) from a real smoke store: a smoke
ablation and a small smoke sweep run with the experiments CLI into a temporary MLflow store, then the
template rendered into a temporary folder (never reports/RESULTS.md)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
from cli_helpers import cli_env as _env
from cli_helpers import run_cli_in_process
from mlflow import MlflowClient
from PIL import Image

from reports import paper
from reports.results.provenance import duration
from reports.results.writer import MAX_FIGURE_WIDTH, ResultsError, parse_template, portable_uri, regeneration_command

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow

TEMPLATE = """# Results (test)

{{ provenance }}

{{ command }}

## Table I
{{ success_table }}

{{ circle_table }}

{{ train_time_table }}

{{ figure("success_bars") }}

{{ figure("circles") }}

## Sweep
{{ sweep_table("reacher") }}

{{ sweep_figure("reacher") }}

{{ figure("training_curves") }}

## Discussion
TODO
"""


@pytest.fixture(scope="module")
def store(results_store):
    return results_store  # conftest: a smoke ablation and a smoke sweep, shared with tests/test_reports_export.py


def _results(store: Path, out: Path, *args: str, template: str = TEMPLATE,
             here: bool = False) -> subprocess.CompletedProcess:
    """`python -m reports --results` in the store's folder (its default store); `here`: in this process."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "template.md").write_text(template)
    argv = ["--results", "--template", str(out / "template.md"), "--results-out", str(out / "docs" / "RESULTS.md"),
            "--figures-dir", str(out / "docs" / "figures"), *args]
    if here:
        return run_cli_in_process(argv, store, module="reports")
    return subprocess.run([sys.executable, "-m", "reports", *argv], cwd=store, env=_env(store),
                          capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def rendered(store, tmp_path_factory):
    out = tmp_path_factory.mktemp("results_out")
    proc = _results(store, out)
    assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
    return out, (out / "docs" / "RESULTS.md").read_text()


def _parents(store: Path) -> dict[str, object]:
    client = MlflowClient(f"sqlite:///{store / 'mlflow.db'}")
    out = {}
    for kind in ("ablation", "sweep"):
        exp = client.get_experiment_by_name(kind)
        out[kind] = client.search_runs([exp.experiment_id], "tags.role = 'parent'")[0]
    return out


def test_tables_carry_the_runs_numbers_and_the_papers(store, rendered):
    out, text = rendered
    assert "{{" not in text and "TODO" in text
    parents = _parents(store)
    abl, swp = parents["ablation"], parents["sweep"]
    # provenance: one row per study, with its commit (as git abbreviates it) and the study's own wall time
    assert abl.data.tags["study_name"] in text and swp.data.tags["study_name"] in text
    name, commit = re.escape(abl.data.tags["study_name"]), abl.data.params["git_commit"][:7]
    assert re.search(rf"^\| {name} +\| ablation +\| `{abl.info.run_id}` +\| `{commit}` ", text, re.M)
    assert f"| {duration(abl.data.metrics['time/study_seconds'])} " in text
    # the success table: Table I's value beside each row, ours with per-seed rates, both intervals and n
    success = text.split("### Success rate (Table I, extended)")[1].split("###")[0]
    assert re.search(r"\| paper +\|$", success.splitlines()[2]), success
    for variant in ("lstm", "ac-lstm-mdn"):
        cells = next([c.strip() for c in line.strip("|").split("|")] for line in success.splitlines()
                     if re.match(rf"\| reacher +\| {re.escape(paper.variant_label(variant))} +\|", line))
        task, _, rate, per_seed, seed_level, wilson, rollouts, seeds, paper_rate = cells
        assert paper_rate == f"{100 * paper.TABLE_I[variant]['reacher']:.0f}%"
        assert re.fullmatch(r"\d+%", rate) and re.fullmatch(r"\d+%", per_seed), cells  # smoke: one seed
        assert re.fullmatch(r"\d+–\d+%", wilson) and seed_level == "–", cells  # one seed: no seed-level interval
        assert (rollouts, seeds) == ("2", "1"), cells
    assert "### Circle drawing: radial error per radius" in text
    assert "### Training time per variant and task" in text
    # the sweep table: trial counts match the Optuna states logged on the trials, best = the parent's best
    sweep = text.split("### Sweep on reacher: top 5 trials")[1].split("##")[0]
    assert "trials: 2 (" in sweep
    best = swp.data.metrics["best_value"]
    assert f"objective {best:.4g}" in sweep
    assert f"m = {swp.data.tags['best.m']}" in sweep
    # the command pins the studies used; the store is the default one of the working directory: not named,
    # and no path of this machine anywhere in the file
    assert "--tracking-uri" not in text and str(store) not in text and str(Path.home()) not in text
    assert f"--ablation {abl.data.tags['study_name']}" in text and f"--sweep {swp.data.tags['study_name']}" in text


def test_figures_are_small_pngs_behind_relative_links(rendered):
    out, text = rendered
    docs = out / "docs"
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text)
    unavailable = re.findall(r"figure unavailable: (\w+)", text)
    assert "success_bars" not in unavailable and "figures/success_bars.png" in links
    assert "figures/reacher_sweep_history.png" in links
    assert "circles" in unavailable  # the smoke profile does not train the circle task: a visible gap line
    assert len(links) + len(unavailable) == 7  # success_bars, circles, 4 sweep figures, training_curves
    for link in links:
        assert not Path(link).is_absolute()
        path = docs / link
        assert path.exists(), link
        with Image.open(path) as im:
            assert im.format == "PNG" and im.width <= MAX_FIGURE_WIDTH
        assert path.stat().st_size < 400_000
    assert sorted(p.name for p in (docs / "figures").iterdir()) == sorted(Path(link).name for link in links)


def _main(store: Path, out: Path, *args: str, template: str = TEMPLATE) -> int:
    """`python -m reports --results ...` in this process (no interpreter start-up per call)."""
    from reports.__main__ import main

    out.mkdir(parents=True, exist_ok=True)
    (out / "template.md").write_text(template)
    return main(["--results", "--tracking-uri", f"sqlite:///{store / 'mlflow.db'}", "--template",
                 str(out / "template.md"), "--results-out", str(out / "docs" / "RESULTS.md"), "--figures-dir",
                 str(out / "docs" / "figures"), *args])


def test_twice_gives_the_same_bytes(store, rendered, tmp_path):
    assert _main(store, tmp_path) == 0
    text = (tmp_path / "docs" / "RESULTS.md").read_text()
    figs = {p.name: p.read_bytes() for p in (tmp_path / "docs" / "figures").iterdir()}
    assert _main(store, tmp_path) == 0
    assert (tmp_path / "docs" / "RESULTS.md").read_text() == text
    assert {p.name: p.read_bytes() for p in (tmp_path / "docs" / "figures").iterdir()} == figs
    # and the same figures as the CLI run in another process (MLflow's column order differs between processes)
    assert {p.name: p.read_bytes() for p in (rendered[0] / "docs" / "figures").iterdir()} == figs


def test_figure_that_cannot_be_drawn_is_a_visible_line(store, tmp_path, monkeypatch):
    from reports.results import writer

    template = '{{ figure("success_bars") }}\n\n{{ figure("train_time") }}\n'
    assert _main(store, tmp_path, template=template) == 0
    assert (tmp_path / "docs" / "figures" / "success_bars.png").exists()

    def broken(*_):
        raise RuntimeError("data the builder did not foresee")
    monkeypatch.setitem(writer.ABLATION_FIGURES, "success_bars", broken)
    assert _main(store, tmp_path, template=template) == 0
    text = (tmp_path / "docs" / "RESULTS.md").read_text()
    assert "figure unavailable: success_bars" in text and "RuntimeError: data the builder did not foresee" in text
    assert "](figures/train_time.png)" in text  # the rest of the file is still there
    assert not (tmp_path / "docs" / "figures" / "success_bars.png").exists()  # no stale figure beside the gap


@pytest.mark.parametrize(("template", "message"), [
    ("x {{ success_tabel }} y", "unknown placeholder {{ success_tabel }} (line 1)"),
    ('a\n{{ figure("no_such_figure") }}',
     'unknown figure \'no_such_figure\' in {{ figure("no_such_figure") }} (line 2)'),
    ('{{ sweep_table("pick-place") }}', "no sweep study of task 'pick-place'"),
    ('{{ success_table("reacher") }}', '{{ success_table("reacher") }} (line 1): success_table takes only study='),
    ('{{ provenance(study="x") }}', "unknown placeholder call (line 1)"),
    ('\n{{ sweep_table("reacher", study="x") }}', "sweep_table(...) (line 2) takes no keyword"),
    ('{{ figure("circles", seed="1") }}', 'figure(...) (line 1) takes only study="NAME"'),
    ("{{ figure }}", "needs its argument"),
    ('{{ data_scaling("reacher") }}', 'data_scaling takes 2 or 12 argument(s)'),
    ('{{ data_scaling("reacher", "nope") }}', "unknown study 'nope'"),
    ('{{ compare("reacher", "a/lstm", "b/lstm", "c/lstm") }}', "compare takes an evaluated task, then pairs of rows"),
    ('{{ difference("reacher", "lstm", "ac-lstm") }}', "difference takes an evaluated task, then pairs of rows"),
    ('{{ difference("reacher", "nope/lstm", "nope/ac-lstm") }}', "unknown study 'nope'"),
    ("{{figure:success_bars}}", "template syntax error (line 1)"),
    ('{{ table_one("reacher") }}', "table_one takes TASK=STUDY, one per training task"),
    ('{{ table_one("reacher=a", "reacher=b") }}', "table_one takes TASK=STUDY, one per training task"),
    ("a\n\n{{ claims }}", "{{ claims }} (line 3) reads the sources of Table I"),
    ('{{ notebook("Bad Topic") }}', "a notebook topic is lower-case words joined by '-'"),
    ('{{ notebook("missing") }}', "cannot read the notebook page's template"),
])
def test_bad_template_is_a_one_line_error_and_writes_nothing(store, tmp_path, capsys, template, message):
    assert _main(store, tmp_path, template=template) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert not (tmp_path / "docs").exists()


def test_bad_selection_is_a_one_line_error(store, tmp_path, capsys):
    swp = _parents(store)["sweep"].data.tags["study_name"]
    for args, message in ((["--ablation", "nope"], "unknown study 'nope'"),
                          (["--ablation", swp], f"study {swp!r} is of kind 'sweep', not 'ablation'"),
                          (["--sweep", "nope"], "unknown study 'nope'"),
                          (["--template", str(tmp_path / "missing.md")], "cannot read the template")):
        assert _main(store, tmp_path, *args) == 2, args
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, (args, err)
        assert not (tmp_path / "docs").exists()


def test_parse_template_and_command(tmp_path, monkeypatch):
    phs = parse_template('{{provenance}}\n\n{{ sweep_figure("pick-place", "sweep_params") }} {{figure("tip_paths")}}')
    assert [(p.kind, p.args, p.line) for p in phs] == [
        ("provenance", (), 1), ("sweep_figure", ("pick-place", "sweep_params"), 3), ("figure", ("tip_paths",), 3)]
    phs = parse_template('{{ success_table(study="mm") }}\n{{ figure("tip_paths", study="mm") }}\n{{ circle_table }}')
    assert [(p.kind, p.args, p.study, p.text) for p in phs] == [
        ("success_table", (), "mm", '{{ success_table(study="mm") }}'),
        ("figure", ("tip_paths",), "mm", '{{ figure("tip_paths", study="mm") }}'),
        ("circle_table", (), None, "{{ circle_table }}")]
    with pytest.raises(ResultsError, match="sweep_table takes 1 argument"):
        parse_template('{{ sweep_table("reacher", "x") }}')
    cmd = regeneration_command(None, [], Path("reports/RESULTS.template.md"), Path("reports/RESULTS.md"),
                               Path("reports/figures"), None)
    assert cmd == "nox -s report -- --results"
    # stores named relative to the working directory, or by the environment variable: no path of this machine
    monkeypatch.chdir(tmp_path)
    assert portable_uri(f"sqlite:///{tmp_path / 'mlflow.db'}") is None  # the default store
    assert portable_uri(f"sqlite:///{tmp_path / 'stores' / 'a.db'}") == "sqlite:///stores/a.db"
    assert portable_uri("postgresql://user:secret@db/mlflow") == "$MLFLOW_TRACKING_URI"
    cmd = regeneration_command(None, [], tmp_path / "t.md", Path("reports/RESULTS.md"), Path("reports/figures"),
                               "http://user:secret@host:5000")
    assert cmd == 'nox -s report -- --results --tracking-uri "$MLFLOW_TRACKING_URI" --template t.md'


def test_comparisons_render_from_the_store(store, tmp_path):
    name = _parents(store)["ablation"].data.tags["study_name"]
    template = (f'{{{{ compare("reacher", "{name}/lstm", "{name}/ac-lstm-mdn") }}}}\n\n'
                f'In a sentence: {{{{ difference("reacher", "{name}/lstm", "{name}/ac-lstm-mdn") }}}}.\n\n'
                f'{{{{ comparisons("reacher", "{name}") }}}}\n')
    proc = _results(store, tmp_path, template=template, here=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
    text = (tmp_path / "docs" / "RESULTS.md").read_text()
    # one seed per variant: no interval, and two models as groups of one
    study = re.escape(f"({name})")
    row = (rf"\| reacher +\| LSTM {study} +\| a\.c\. LSTM-MDN {study} +\| +[-+]?\d+ +\| – +\| +[\d.]+ +"
           r"\| groups, 1\+1 models \|")
    assert re.search(row, text), text[:1200]
    assert re.search(r"In a sentence: [-+]?\d+ points \(95 % interval –; groups, 1\+1 models; p = [\d.]+\)\.", text)
    assert "<details><summary>Comparisons of the variants" in text and "</details>" in text


def test_repository_template_and_its_notebook_pages_parse():
    main = parse_template((REPO / "reports" / "RESULTS.template.md").read_text())
    assert {("table_one", "reacher=paper"), ("claims", None), ("headline_train_time", None), ("provenance", None),
            ("command", None), ("notebook", "milestones")} <= {(p.kind, p.arg) for p in main}
    pages = [parse_template((REPO / "reports" / "notebook" / f"{p.arg}.template.md").read_text())
             for p in main if p.kind == "notebook"]
    kinds = {(p.kind, p.arg) for p in main + [p for page in pages for p in page]}
    assert {("budget_table", None), ("success_table", None), ("multimodal_table", None), ("figure", "mode_paths"),
            ("comparisons", "reacher"), ("difference", "reacher"), ("lever", "pick-place")} <= kinds


def test_table_one_claims_and_a_notebook_page_render_from_the_store(store, tmp_path):
    """Table I takes each training task's cells from the study named for it, with the paper's value beside them and
    its figure; {{ claims }} reads the same sources; a notebook page renders from its own template beside the
    RESULTS template, with figure links relative to the page, and RESULTS.md links it by its title."""
    name = _parents(store)["ablation"].data.tags["study_name"]
    (tmp_path / "notebook").mkdir()
    (tmp_path / "notebook" / "a-topic.template.md").write_text(
        '# A topic\n\n{{ success_table }}\n\n{{ figure("success_bars") }}\n')
    template = (f'# R\n\n{{{{ table_one("reacher={name}") }}}}\n\n{{{{ claims }}}}\n\n{{{{ headline_train_time }}}}\n\n'
                'See {{ notebook("a-topic") }}.\n\n{{ provenance }}\n')
    proc = _results(store, tmp_path, template=template, here=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
    text = (tmp_path / "docs" / "RESULTS.md").read_text()
    row = next(line for line in text.splitlines() if re.match(r"\| reacher +\| a\.c\. LSTM-MDN +\|", line))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[-2:] == [f"{100 * paper.TABLE_I['ac-lstm-mdn']['reacher']:.0f}%", name], cells
    assert "strict criterion" not in text  # the smoke rollouts record one criterion only
    assert "](figures/table_one.png)" in text and (tmp_path / "docs" / "figures" / "table_one.png").is_file()
    assert re.search(r"^\| a\.c\. LSTM-MDN − a\.c\. LSTM +\|", text, re.M)  # the claims
    assert "See [A topic](notebook/a-topic.md)." in text
    page = (tmp_path / "docs" / "notebook" / "a-topic.md").read_text()
    assert "### Success rate (Table I, extended)" in page and "](../figures/success_bars.png)" in page
    assert re.search(rf"^\| {re.escape(name)} +\| ablation +\|", text, re.M)  # provenance: one row for the study


def test_table_one_names_an_evaluated_task_only_of_a_listed_training_task(store, tmp_path, capsys):
    name = _parents(store)["ablation"].data.tags["study_name"]
    template = f'{{{{ table_one("reacher={name}", "stack={name}") }}}}\n'
    assert _main(store, tmp_path, template=template) == 2
    assert "'stack' is neither a training task" in capsys.readouterr().err


def test_a_notebook_page_error_names_its_template(store, tmp_path, capsys):
    (tmp_path / "notebook").mkdir()
    (tmp_path / "notebook" / "t.template.md").write_text("# T\n\n{{ success_tabel }}\n")
    assert _main(store, tmp_path, template='{{ notebook("t") }}\n') == 2
    err = capsys.readouterr().err
    assert "t.template.md: unknown placeholder {{ success_tabel }} (line 3)" in err and err.count("\n") == 1, err
    assert not (tmp_path / "docs").exists()
