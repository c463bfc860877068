"""Study exports (reports.data.export, reports.data.studyimport): a real smoke ablation and smoke sweep (conftest's
results_store, built through the experiments CLI) exported through the reports CLI, checked for portability and
determinism, imported back, and RESULTS.md rendered from the exports alone against the original store."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import cli_env
from mlflow import MlflowClient

from reports.__main__ import main
from reports.data.export import FORMAT, FORMAT_UNVERIFIED, MAX_HISTORY, RECORDS_KEY, RUNS_FILE, records_digest, thin

pytestmark = pytest.mark.slow
REPO = Path(__file__).resolve().parents[1]

TABLES = """# Results (test)

{{ provenance }}

{{ command }}

{{ success_table }}

{{ circle_table }}

{{ train_time_table }}

{{ sweep_table("reacher") }}
"""


def _uri(folder: Path) -> str:
    return f"sqlite:///{folder / 'mlflow.db'}"


def _studies(store: Path) -> dict[str, object]:
    """kind -> the parent run of that kind's study in the store."""
    client = MlflowClient(_uri(store))
    return {kind: client.search_runs([client.get_experiment_by_name(kind).experiment_id], "tags.role = 'parent'")[0]
            for kind in ("ablation", "sweep")}


def _tree(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def exports(results_store, tmp_path_factory):
    """Both studies exported with `python -m reports export` (a subprocess, as a user runs it)."""
    out = tmp_path_factory.mktemp("exports") / "studies"
    for parent in _studies(results_store).values():
        proc = subprocess.run([sys.executable, "-m", "reports", "export", "--study", parent.data.tags["study_name"],
                               "--out", str(out)], cwd=results_store, env=cli_env(results_store),
                              capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
        assert re.fullmatch(r"export: .+ \(\d+ runs, \d+ artifacts, [\d.]+ [kM]B\) \[[\d.]+ s\]\n", proc.stdout)
    return out


def _export_of(exports: Path, kind: str) -> tuple[Path, dict]:
    for folder in sorted(exports.iterdir()):
        doc = json.loads((folder / RUNS_FILE).read_text())
        if doc["experiment"] == kind:
            return folder, doc
    raise AssertionError(f"no {kind} export in {exports}")


def test_export_holds_every_run_and_only_what_reports_read(results_store, exports):
    client = MlflowClient(_uri(results_store))
    for kind, parent in _studies(results_store).items():
        folder, doc = _export_of(exports, kind)
        assert folder.name == parent.data.tags["study_name"] and doc["study_name"] == folder.name
        dropped = set(doc["dropped"])
        # the sweep's Optuna storage is a journal beside the store, named by its absolute path: left out
        assert ("param sweep.storage" in dropped) == (kind == "sweep"), dropped
        children = client.search_runs([parent.info.experiment_id],
                                      f"tags.`mlflow.parentRunId` = '{parent.info.run_id}'")
        assert [r["run_id"] for r in doc["runs"]][0] == parent.info.run_id
        assert {r["run_id"] for r in doc["runs"][1:]} == {c.info.run_id for c in children} and children
        for run, orig in zip(doc["runs"], [parent, *sorted(children, key=lambda c: (c.info.start_time,
                                                                                    c.info.run_id))], strict=True):
            assert run["run_id"] == orig.info.run_id and run["status"] == orig.info.status
            assert (run["start_time"], run["end_time"]) == (orig.info.start_time, orig.info.end_time)
            for what, values in (("param", orig.data.params), ("tag", orig.data.tags)):
                assert all(str(results_store) in v for k, v in values.items() if f"{what} {k}" in dropped)
            assert run["params"] == {k: v for k, v in orig.data.params.items() if f"param {k}" not in dropped}
            assert run["metrics"] == orig.data.metrics
            assert run["parent_run_id"] == orig.data.tags.get("mlflow.parentRunId")
            assert run["tags"] == {k: v for k, v in orig.data.tags.items()
                                   if k not in ("mlflow.parentRunId", "mlflow.runName") and f"tag {k}" not in dropped}
            assert set(run["histories"]) == set(orig.data.metrics)
            for key, hist in run["histories"].items():
                logged = client.get_metric_history(orig.info.run_id, key)  # short: not thinned
                assert [tuple(p) for p in hist["points"]] == sorted((m.step, m.timestamp, m.value) for m in logged)
    # the artifacts: the rollouts the reports read, never the checkpoints or models the runs also logged
    folder, doc = _export_of(exports, "ablation")
    child = doc["runs"][1]["run_id"]
    assert {f.path for f in client.list_artifacts(child)} >= {"checkpoint", "rollouts"}
    files = [p for p in _tree(folder) if p != RUNS_FILE]
    assert files and all(re.fullmatch(r"artifacts/[0-9a-f]{32}/rollouts/[^/]+\.npz|"
                                      r"artifacts/[0-9a-f]{32}/rollouts/ik_timing\.json", p) for p in files), files
    with np.load(folder / f"artifacts/{child}/rollouts/reacher.npz") as ours, \
            np.load(client.download_artifacts(child, "rollouts/reacher.npz", tempfile.mkdtemp())) as orig:
        assert sorted(ours.files) == sorted(orig.files)
        for k in orig.files:
            if orig[k].dtype == np.float64:
                assert ours[k].dtype == np.float32 and np.allclose(ours[k], orig[k], rtol=1e-6, equal_nan=True), k
            else:
                assert ours[k].dtype == orig[k].dtype and np.array_equal(ours[k], orig[k]), k


def test_export_names_no_path_of_this_machine(results_store, exports):
    roots = {str(results_store), str(results_store.resolve()), str(Path.home()), str(Path.cwd()), str(REPO)}
    for path, data in _tree(exports).items():
        for root in roots:
            assert root.encode() not in data, (path, root)
        if path.endswith(".json"):
            assert tempfile.gettempdir() not in data.decode() and "file:" not in data.decode(), path


def test_reexport_gives_the_same_bytes_and_drops_stale_files(results_store, exports, tmp_path, capsys):
    """A re-export removes what the earlier export of the study listed and this one does not (and the folders that
    leaves empty), and nothing else: a file the export never wrote stays."""
    folder, doc = _export_of(exports, "ablation")
    out = tmp_path / "again"
    stale = out / folder.name / "artifacts" / "old" / "rollouts" / "gone.npz"
    stale.parent.mkdir(parents=True)
    stale.write_bytes(b"x")
    foreign = out / folder.name / "notes.txt"
    foreign.write_text("the user's")
    earlier = {**doc, "runs": [{**doc["runs"][0], "run_id": "old", "artifacts": {"rollouts/gone.npz": "0"}}]}
    (out / folder.name / RUNS_FILE).write_text(json.dumps(earlier))
    assert main(["export", "--study", doc["runs"][0]["run_id"], "--tracking-uri", _uri(results_store),
                 "--out", str(out)]) == 0
    foreign.unlink()
    assert _tree(out / folder.name) == _tree(folder)  # by run id, another process, the same bytes; stale gone
    assert not (out / folder.name / "artifacts" / "old").exists()
    assert str(out / folder.name) in capsys.readouterr().out
    assert main(["export", "--study", "nope", "--tracking-uri", _uri(results_store), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "unknown study 'nope'" in err and err.count("\n") == 1, err


@pytest.mark.parametrize("held", ["other", "none", "link"])
def test_an_export_never_replaces_what_is_not_its_own(results_store, exports, tmp_path, capsys, held):
    """The folder of the study's name holds another study's export, a folder without a readable runs.json, or a link
    out of --out: one line, exit 2, nothing written or deleted there."""
    folder, doc = _export_of(exports, "ablation")
    out = tmp_path / "out"
    target = out / folder.name
    if held == "link":
        (tmp_path / "elsewhere").mkdir()
        (tmp_path / "elsewhere" / "keep.txt").write_text("keep")
        out.mkdir()
        target.symlink_to(tmp_path / "elsewhere")
        message = "outside"
    else:
        shutil.copytree(folder, target)
        runs = target / RUNS_FILE
        if held == "other":
            runs.write_text(runs.read_text().replace(f'"study_name": "{doc["study_name"]}"', '"study_name": "other"'))
            message = "holds the export of study 'other'"
        else:
            runs.unlink()
            message = "is not a study export"
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    assert main(["export", "--study", doc["study_name"], "--tracking-uri", _uri(results_store),
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before


def test_an_export_carries_the_digest_of_its_records(exports):
    for kind in ("ablation", "sweep"):
        _, doc = _export_of(exports, kind)
        assert doc["format"] == FORMAT and doc[RECORDS_KEY] == records_digest(doc)


def test_the_committed_exports_are_read_as_they_are():
    """Every export in reports/studies/ lies in the folder of its study's name, a name by the rule, and is read: of
    the format from before the digest (their records unverified, and the import says so), never rewritten."""
    from experiments.runtime.study_names import is_study_name
    from reports.data.studyimport import export_folders, read_export

    for folder in export_folders(REPO / "reports" / "studies"):
        doc, _ = read_export(folder)
        assert doc["study_name"] == folder.name and is_study_name(folder.name), folder
        assert doc["format"] in (FORMAT_UNVERIFIED, FORMAT) and (doc["format"] == FORMAT) == (RECORDS_KEY in doc)


def test_an_unverified_export_imports_and_says_so(tmp_path, capsys):
    folder = REPO / "reports" / "studies" / "paper-reacher-15demos"
    assert _import(folder, tmp_path) == 0
    assert "records unverified" in capsys.readouterr().out


def test_long_histories_are_thinned_keeping_the_latest():
    pts = [[i, 1000 + i, float(i % 7)] for i in range(1234)]
    kept, n = thin(pts)
    assert n == 1234 and len(kept) <= MAX_HISTORY + 1 and kept[0] == pts[0] and kept[-1] == pts[-1]
    steps = [p[0] for p in kept]
    assert steps == sorted(steps) and len(set(np.diff(steps[:-1]))) == 1  # evenly spaced, then the last
    assert thin(pts[:MAX_HISTORY]) == (pts[:MAX_HISTORY], None)


def _import(exports: Path, store: Path, *more: Path) -> int:
    return main(["import", str(exports), *map(str, more), "--tracking-uri", _uri(store)])


def test_import_recreates_the_study_once(results_store, exports, tmp_path, capsys):
    assert _import(exports, tmp_path) == 0
    assert capsys.readouterr().out.count("imported (") == 2
    orig, new = MlflowClient(_uri(results_store)), MlflowClient(_uri(tmp_path))
    for kind in ("ablation", "sweep"):
        _, doc = _export_of(exports, kind)
        exp = new.get_experiment_by_name(kind)
        runs = {r.data.tags["export.run_id"]: r for r in new.search_runs([exp.experiment_id])}
        assert set(runs) == {r["run_id"] for r in doc["runs"]}
        for old_id, run in runs.items():
            was = orig.get_run(old_id)
            assert (run.info.status, run.info.start_time, run.info.end_time, run.info.run_name) == (
                was.info.status, was.info.start_time, was.info.end_time, was.info.run_name)
            exported = doc["runs"][[r["run_id"] for r in doc["runs"]].index(old_id)]
            # a cell's claim names a process of the exporting store: left behind
            assert run.data.params == {k: v for k, v in exported["params"].items() if not k.startswith("claim.")}
            assert run.data.metrics == was.data.metrics
            assert "claim.beat" not in run.data.tags
            assert {k: v for k, v in was.data.params.items() if f"param {k}" not in doc["dropped"]} == \
                exported["params"]
            old_parent = was.data.tags.get("mlflow.parentRunId")
            assert run.data.tags.get("mlflow.parentRunId") == (runs[old_parent].info.run_id if old_parent else None)
            for key in was.data.metrics:
                assert [(m.step, m.timestamp, m.value) for m in new.get_metric_history(run.info.run_id, key)] == \
                    [(m.step, m.timestamp, m.value) for m in orig.get_metric_history(old_id, key)]
            assert sorted(f.path for f in new.list_artifacts(run.info.run_id, "rollouts")) == sorted(
                exported["artifacts"])
    n_runs = len(new.search_runs([e.experiment_id for e in new.search_experiments()]))
    # again: skipped, nothing duplicated
    assert _import(exports, tmp_path) == 0
    assert capsys.readouterr().out.count("skipped (already imported") == 2
    assert len(new.search_runs([e.experiment_id for e in new.search_experiments()])) == n_runs
    # into the original store: the same study names with other content there -> one line, exit 2
    assert _import(exports, results_store) == 2
    err = capsys.readouterr().err
    assert "is already in" in err and err.count("\n") == 1, err


def _corrupt(src: Path, dst: Path, how: str) -> str:
    shutil.copytree(src, dst)
    npz = next(dst.rglob("*.npz"))
    if how == "truncated":
        (dst / RUNS_FILE).write_bytes((dst / RUNS_FILE).read_bytes()[:500])
        return "is not JSON"
    if how == "changed":
        data = bytearray(npz.read_bytes())
        data[len(data) // 2] ^= 0xFF
        npz.write_bytes(bytes(data))
        return "does not match its sha256"
    if how == "missing":
        npz.unlink()
        return "missing artifact"
    doc = json.loads((dst / RUNS_FILE).read_text())
    if how == "tampered":  # a record edited after the export: the learning rate the run did not train with
        doc["runs"][1]["params"]["train.lr"] = "0.5"
        (dst / RUNS_FILE).write_text(json.dumps(doc))
        return "its records do not match their digest"
    if how == "renamed":  # edited, digest recomputed: the name breaks the rule
        doc["study_name"] = doc["runs"][0]["tags"]["study_name"] = "../x"
        doc[RECORDS_KEY] = records_digest(doc)
        (dst / RUNS_FILE).write_text(json.dumps(doc))
        return "study_name '../x': a study name is"
    doc["runs"][2]["parent_run_id"] = "f" * 32
    doc[RECORDS_KEY] = records_digest(doc)  # (as an exporter with this bug would write it)
    (dst / RUNS_FILE).write_text(json.dumps(doc))
    return "has no parent before it"


@pytest.mark.parametrize("how", ["truncated", "changed", "missing", "orphan", "tampered", "renamed"])
def test_corrupt_export_is_one_line_and_imports_nothing(exports, tmp_path, capsys, how):
    src, _ = _export_of(exports, "ablation")
    bad = tmp_path / "exports" / "bad"
    message = _corrupt(src, bad, how)
    good, _ = _export_of(exports, "sweep")  # a valid export beside it is not imported either
    assert _import(good, tmp_path / "store", bad) == 2
    err = capsys.readouterr().err
    assert message in err and str(bad) in err and err.count("\n") == 1, err
    assert not (tmp_path / "store" / "mlflow.db").exists()
    out = tmp_path / "results"
    assert main(["--results", "--exports", str(tmp_path / "exports"), "--template",
                 str(REPO / "reports" / "RESULTS.template.md"), "--results-out", str(out / "R.md")]) == 2
    assert message in capsys.readouterr().err and not out.exists()


def test_failed_import_leaves_no_run_behind(exports, tmp_path, monkeypatch):
    from experiments.runtime import tracking
    from reports.data.export import ExportError
    from reports.data.studyimport import import_exports

    calls = []

    def broken(self, run_id, *args):  # the artifact store fails at the third artifact
        calls.append(run_id)
        if len(calls) == 3:
            raise OSError("disk full")
        return self._client.log_artifact(run_id, *args)
    monkeypatch.setattr(tracking.Client, "log_artifact", broken, raising=False)
    folder, _ = _export_of(exports, "ablation")
    with pytest.raises(ExportError, match=r"failed \(disk full\); the 2 run\(s\) it created were deleted"):
        import_exports([folder], _uri(tmp_path))
    client = MlflowClient(_uri(tmp_path))
    assert client.search_runs([e.experiment_id for e in client.search_experiments()]) == []


def _results(tmp_path: Path, template: str, *args: str) -> tuple[int, str]:
    tmp_path.mkdir(parents=True, exist_ok=True)
    (tmp_path / "t.md").write_text(template)
    out = tmp_path / "docs" / "RESULTS.md"
    rc = main(["--results", "--template", str(tmp_path / "t.md"), "--results-out", str(out), "--figures-dir",
               str(tmp_path / "docs" / "figures"), *args])
    return rc, out.read_text() if out.exists() else ""


def test_results_from_the_exports_equal_the_store(results_store, exports, tmp_path, monkeypatch):
    rc, from_store = _results(tmp_path / "a", TABLES, "--tracking-uri", _uri(results_store))
    assert rc == 0
    monkeypatch.chdir(exports.parent)  # as in the repository: `--exports studies` relative to it
    rc, from_exports = _results(tmp_path / "b", TABLES, "--exports", "studies")
    assert rc == 0
    command = re.compile(r"^nox -s report -- .*$", re.M)
    cmd = command.search(from_exports).group(0)
    assert command.sub("", from_store) == command.sub("", from_exports)
    assert cmd.startswith("nox -s report -- --results --exports studies --ablation ") and "sqlite" not in cmd
    parents = _studies(results_store)
    assert f"`{parents['ablation'].info.run_id}`" in from_exports  # the original parent run ids
    assert "### Success rate (Table I, extended)" in from_exports and "### Sweep on reacher" in from_exports
    assert str(tmp_path) not in cmd and str(exports) not in from_exports


def _renamed_copy(src: Path, dst: Path, name: str) -> None:
    """A second ablation study: the export under another study name, every success rate set to 1."""
    shutil.copytree(src, dst)
    doc = json.loads((dst / RUNS_FILE).read_text())
    doc["study_name"] = doc["runs"][0]["tags"]["study_name"] = doc["runs"][0]["params"]["study_name"] = name
    for run in doc["runs"]:
        for key in [k for k in run["metrics"] if k.endswith("/success_rate")]:
            run["metrics"][key] = 1.0
            run["histories"][key]["points"] = [[p[0], p[1], 1.0] for p in run["histories"][key]["points"]]
    doc[RECORDS_KEY] = records_digest(doc)  # a study of its own, not an edited one
    (dst / RUNS_FILE).write_text(json.dumps(doc))


def test_template_with_several_studies(exports, tmp_path):
    src, doc = _export_of(exports, "ablation")
    name = doc["study_name"]
    _renamed_copy(src, tmp_path / "studies" / "other", "other")
    shutil.copytree(src, tmp_path / "studies" / name)
    template = ('{{ provenance }}\n\n{{ success_table }}\n\n{{ success_table(study="other") }}\n\n'
                '{{ figure("success_bars", study="other") }}\n\n{{ command }}\n')
    rc, text = _results(tmp_path, template, "--exports", str(tmp_path / "studies"), "--ablation", name)
    assert rc == 0
    provenance = text.split("| study ")[1].split("\n\n")[0]
    assert f"| {name} " in provenance and "| other " in provenance  # provenance: one row per study, both
    tables = text.split("### Success rate (Table I, extended)")[1:]
    rates = [re.findall(r"^\| reacher +\| [^|]+\| (\d+%)", t, re.M) for t in tables]
    logged = [f"{100 * r['metrics']['reacher/success_rate']:.0f}%" for r in doc["runs"][1:]]
    assert len(rates) == 2 and sorted(rates[0]) == sorted(logged) and rates[1] == ["100%"] * len(logged), rates
    assert (tmp_path / "docs" / "figures" / "other_success_bars.png").exists()
    assert "](figures/other_success_bars.png)" in text
    # a study the store lacks: one line naming it and its line, nothing written
    rc, _ = _results(tmp_path / "bad", template.replace('study="other"', 'study="nope"', 1), "--exports",
                     str(tmp_path / "studies"))
    assert rc == 2 and not (tmp_path / "bad" / "docs").exists()


def test_unknown_study_is_one_line_naming_it(exports, tmp_path, capsys):
    rc, _ = _results(tmp_path, '# x\n\n{{ circle_table(study="nope") }}\n', "--exports", str(exports))
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1, err
    assert '{{ circle_table(study="nope") }} (line 3): unknown study \'nope\'' in err
    assert not (tmp_path / "docs").exists()
