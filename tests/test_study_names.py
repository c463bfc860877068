"""The study name rule (experiments/runtime/study_names.py) at every entry point, and a property test (hypothesis)
over study names and --set values: each command exits 0 or 2, says why in one stderr line when it exits 2, and
creates, changes or deletes no file but the working folder's own outputs (its store, reports/out/<name>/,
reports/studies/<name>/). The commands stop before any training (--dry-run; the reports' commands on a store that
holds no trained study), so that the examples take seconds."""

from __future__ import annotations

import hashlib
import json
import logging
import uuid
from pathlib import Path

import pytest
from cli_helpers import run_in_process
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from experiments.runtime.study_names import (
    RULE,
    StudyNameError,
    UnsafeFolder,
    check_study_name,
    is_study_name,
    study_folder,
)

VALID = ["paper-pickplace-30k-milestones@5000", "x+y", "a", "A9", "multimodal-120demos-feedback-sample_component",
         "v1.2", "x" * 100]
INVALID = ["..", ".", "", "../x", "a/b", "/abs", "a b", 'a"b', "a'b", "a\nb", "-x", "_x", ".hidden", "x" * 101, "ä",
           "a\\b", "a*", "a:b", "~"]


@pytest.mark.parametrize("name", VALID)
def test_valid_names(name):
    assert check_study_name(name) == name


@pytest.mark.parametrize("name", INVALID)
def test_invalid_names_are_one_line_saying_the_rule(name):
    with pytest.raises(StudyNameError) as err:
        check_study_name(name, "--study-name")
    text = str(err.value)
    assert text.startswith("--study-name ") and text.endswith(RULE) and "\n" not in text


def test_a_study_folder_stays_inside_its_root(tmp_path):
    assert study_folder(tmp_path / "out", "s") == tmp_path / "out" / "s"
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "s").symlink_to(tmp_path)
    with pytest.raises(UnsafeFolder, match="outside"):
        study_folder(tmp_path / "out", "s")
    with pytest.raises(StudyNameError):
        study_folder(tmp_path / "out", "..")


@pytest.mark.parametrize("argv,flag", [
    (["ablation", "--profile", "smoke", "--study-name", ".."], "--study-name '..'"),
    (["sweep", "--profile", "smoke", "--study-name", "a'b"], "--study-name \"a'b\""),
    (["ablation", "--profile", "smoke", "--set", "study_name=a b"], "study_name: 'a b' is not allowed"),
    (["sweep", "--profile", "smoke", "--set", "sweep.study_name=."], "sweep.study_name: '.' is not allowed"),
    (["milestones", "--study", "a/b"], "--study 'a/b'"),
    (["milestones", "--study", "x" * 95], "the milestones study's name"),  # <study>-milestones: 106 characters
    (["smoothing", "--profile", "smoke", "--set", "study_name=.."], "study_name: '..' is not allowed"),
    (["idm", "--profile", "smoke", "--set", "study_name=a\nb"], "study_name: 'a\\nb' is not allowed"),
])
def test_every_experiments_entry_point_refuses_a_bad_name(tmp_path, monkeypatch, capsys, argv, flag):
    from experiments.cli import main

    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"error: {flag}") and RULE in err, err
    assert not list(tmp_path.iterdir())


def test_a_derived_name_obeys_the_rule_too(tmp_path, monkeypatch, capsys):
    """A profile file whose stem is no study name gives none: --study-name, or rename the file."""
    from experiments.cli import main

    monkeypatch.chdir(tmp_path)
    smoke = Path(__file__).parents[1] / "experiments" / "profiles" / "smoke.toml"
    (tmp_path / "my profile.toml").write_text(smoke.read_text())
    assert main(["ablation", "--profile", "my profile.toml", "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: profile: the study name it gives, 'my profile', is not allowed") and \
        err.count("\n") == 1, err
    assert main(["ablation", "--profile", "my profile.toml", "--study-name", "mine", "--dry-run"]) == 0


@pytest.mark.parametrize("argv,flag", [
    (["--study", ".."], "--study '..'"),
    (["export", "--study", "."], "--study '.'"),
    (["export", "--study", "a b", "--with-checkpoints"], "--study 'a b'"),
    (["--results", "--ablation", "../x"], "--ablation '../x'"),
])
def test_every_reports_entry_point_refuses_a_bad_name(tmp_path, monkeypatch, capsys, argv, flag):
    from reports.__main__ import main

    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"reports: error: {flag}") and RULE in err, err
    assert not list(tmp_path.iterdir())


# ------------------------------------------------------------------------------------------------ property test
def _export_doc(name: str) -> dict:
    """A study export (reports.data.export) of one parent run, study `name`: what `reports import` reads."""
    from reports.data.export import FORMAT, HISTORY_NOTE, RECORDS_KEY, records_digest

    run = {"run_id": uuid.uuid4().hex, "run_name": name, "status": "FINISHED", "start_time": 1, "end_time": 2,
           "parent_run_id": None, "params": {"study_name": name}, "tags": {"study_name": name, "role": "parent",
                                                                           "kind": "ablation"},
           "metrics": {}, "histories": {}, "artifacts": {}}
    doc = {"format": FORMAT, "study_name": name, "experiment": "ablation", "history_thinning": HISTORY_NOTE,
           "dropped": [], "runs": [run]}
    return {**doc, RECORDS_KEY: records_digest(doc)}


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A parent folder with files that are nobody's output, and in it the working folder, which holds what the
    probes found deleted or overwritten (RESULTS.md and its template, a package's files, another study's export)."""
    root = tmp_path_factory.mktemp("world")
    work = root / "work"
    files = {root / "RESULTS.md": "beside", root / "keep" / "data.txt": "keep", work / "reports" / "RESULTS.md": "r",
             work / "reports" / "RESULTS.template.md": "t", work / "stm" / "x.py": "x", work / "tests" / "y.py": "y",
             work / "snapshots" / "other" / "runs.json": json.dumps(_export_doc("other")),
             work / "reports" / "studies" / "other" / "runs.json": json.dumps(_export_doc("other"))}
    for path, text in files.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return root, work


def _tree(root: Path) -> dict[str, str]:
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir"
            for p in sorted(root.rglob("*"))}


def _own_output(rel: str, name: str) -> bool:
    """What the commands may write in the working folder: the store, and the report and export of `name`."""
    parts = rel.split("/")
    if parts[0] != "work":
        return False
    inner = parts[1:]
    if inner and (inner[0] in ("mlflow.db", "mlflow.db.lock", "mlflow.db-journal", "mlartifacts")):
        return True
    if inner[:2] in (["reports", "out"], ["reports", "studies"]):
        return len(inner) == 2 or inner[2] == name or inner[1:] == ["out", "index.html"]
    return False


def _run(module: str, argv: list[str], cwd: Path) -> tuple[int, list[str]]:
    """`python -m <module> ARGV` in this process, in `cwd`: exit code, stderr lines (log lines included, at the level
    the command logs at)."""
    code, err = run_in_process(module, argv, cwd, logging.INFO if module == "experiments" else logging.WARNING)
    return code, [line for line in err.splitlines() if line.strip()]


text = st.text(alphabet=st.characters(codec="utf-8", exclude_categories=("Cs",), exclude_characters="\x00"),
               min_size=1, max_size=30)
names = st.one_of(st.from_regex(r"[A-Za-z0-9][A-Za-z0-9_.@+-]{0,20}", fullmatch=True), st.sampled_from(INVALID[:-1]),
                  st.sampled_from(["other", "x" * 100, "x" * 95]), text)
set_values = st.one_of(
    st.tuples(st.sampled_from(["study_name", "sweep.study_name"]), names),
    st.tuples(st.sampled_from(["train.iters", "seeds", "eval.rollouts", "workers"]),
              st.integers(min_value=-3, max_value=10**6).map(str)),
    st.tuples(st.sampled_from(["train.iters", "model.mixtures", "profile", "device", "tasks", "pack"]), text),
).map(lambda fv: f"{fv[0]}={fv[1]}")


@pytest.mark.slow
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                  HealthCheck.too_slow])
@given(name=names, set_value=set_values, kind=st.sampled_from(["smoothing", "idm"]))
def test_no_name_or_value_escapes_the_working_folder(world, monkeypatch, name, set_value, kind):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    root, work = world
    incoming = root / "incoming" / uuid.uuid4().hex
    incoming.mkdir(parents=True)
    (incoming / "runs.json").write_text(json.dumps(_export_doc(name)))
    commands = [
        ("experiments", ["ablation", "--profile", "smoke", "--study-name", name, "--set", set_value, "--dry-run"]),
        ("experiments", ["sweep", "--profile", "smoke", "--study-name", name, "--set", set_value, "--dry-run"]),
        ("experiments", ["ablation", "--profile", "smoke", "--set", f"study_name={name}", "--dry-run"]),
        ("experiments", [kind, "--profile", "smoke", "--set", f"study_name={name}", "--dry-run"]),
        ("reports", ["import", str(incoming)]),
        ("experiments", ["milestones", "--study", name]),
        ("reports", ["--study", name, "--no-log-artifacts"]),
        ("reports", ["export", "--study", name]),
    ]
    event(f"name obeys the rule: {is_study_name(name)}")
    for module, argv in commands:
        before = _tree(root)
        code, err = _run(module, argv, work)
        event(f"{module} {argv[0]}: exit {code}")
        assert code in (0, 2), (argv, code, err)
        if code == 2:
            assert len(err) <= 1, (argv, err)
        after = _tree(root)
        changed = {rel for rel in {*before, *after} if before.get(rel) != after.get(rel)}
        assert all(_own_output(rel, name) for rel in changed), (argv, sorted(changed))
