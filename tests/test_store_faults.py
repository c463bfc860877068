"""Faults of the store mid-study (experiments/runtime/store_faults.py): a full disk, a store file that becomes
read-only and one that disappears each stop the study with one `error:` line and a summary, exit code 3, no
traceback, the unfinished cell resumable; a store file that is read-only from the start fails the start-up check
(it did not: SQLite's BEGIN IMMEDIATE succeeds on a read-only file). Also: Ctrl-C before any cell started marks the
parent KILLED, and a cell whose checkpoint belongs to another config says how to discard it.

The faults are injected (tests/store_fault_injection.py) into a `--workers 1` study once its first checkpoint is in
the store."""

from __future__ import annotations

import errno
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest
from cli_helpers import cli_env, kill_at_checkpoints, run_cli, run_cli_in_process
from mlflow.tracking import MlflowClient

TESTS = Path(__file__).resolve().parent
# the Python step kernel: these tests need no C++ extension built first (minutes, on a busy machine)
STUDY = ["ablation", "--profile", "smoke", "--workers", "1", "--variants", "lstm", "--study-name", "f",
         "--set", "train.iters=20", "--set", "eval.figures=0", "--set", "eval.rollouts=2", "--set", "train.val_every=0",
         "--set", "train.step_kernel=python"]


def _uri(folder: Path) -> str:
    return f"sqlite:///{folder / 'mlflow.db'}"


def _runs(folder: Path, role: str) -> list:
    client = MlflowClient(_uri(folder))
    exp = client.get_experiment_by_name("ablation")
    return client.search_runs([exp.experiment_id], f"tags.role = '{role}'") if exp else []


# ------------------------------------------------------------------------------------------- recognising a fault
def test_sqlite_faults_are_recognised_through_mlflow(tmp_path):
    """The errors as they reach a study: sqlite3's, wrapped by SQLAlchemy, wrapped by MLflow."""
    from mlflow.entities import RunTag
    from sqlalchemy import event
    from sqlalchemy.engine import Engine

    from experiments.runtime.store_faults import fault_reason, is_lasting
    from experiments.runtime.tracking import Client, get_or_create_experiment

    client = Client(_uri(tmp_path))
    run_id = client.create_run(get_or_create_experiment(client, "ablation")).info.run_id
    pragma = []

    def limit(dbapi_connection, *_):  # every connection of the store, while the test sets a pragma
        for sql in pragma:
            dbapi_connection.execute(sql)

    event.listen(Engine, "checkout", limit)
    try:
        pragma[:] = ["PRAGMA query_only = 1"]
        with pytest.raises(Exception) as read_only:
            client.set_tag(run_id, "k", "v")
        pages = sqlite3.connect(tmp_path / "mlflow.db").execute("PRAGMA page_count").fetchone()[0]
        pragma[:] = ["PRAGMA query_only = 0", f"PRAGMA max_page_count = {pages}"]  # (a pooled connection keeps it)
        with pytest.raises(Exception) as full:  # more than the free pages hold: SQLITE_FULL
            for i in range(50):
                client.log_batch(run_id, tags=[RunTag(f"t{i}.{j}", "x" * 4000) for j in range(100)])
    finally:
        event.remove(Engine, "checkout", limit)
    assert fault_reason(read_only.value) == "the store file is read-only" and is_lasting(read_only.value)
    assert fault_reason(full.value) == "the disk is full" and is_lasting(full.value)
    assert fault_reason(OSError(errno.ENOSPC, "No space left on device", "x/y")) == "the disk is full (x/y)"
    assert fault_reason(ValueError("a bug")) is None and fault_reason(OSError(errno.ENOENT, "gone")) is None


def test_a_store_file_replaced_or_moved_is_noticed(tmp_path):
    from experiments.runtime.store_faults import StoreFault
    from experiments.runtime.tracking import Client

    client = Client(_uri(tmp_path))
    client.check_store()
    (tmp_path / "mlflow.db").rename(tmp_path / "aside.db")
    with pytest.raises(StoreFault, match="was deleted or moved"):
        client.check_store()
    with pytest.raises(StoreFault, match="was deleted or moved"):
        Client(_uri(tmp_path), create=False)  # a worker never creates an empty store in its place
    assert not (tmp_path / "mlflow.db").exists()
    shutil.copy(tmp_path / "aside.db", tmp_path / "mlflow.db")
    with pytest.raises(StoreFault, match="replaced by another file"):
        client.check_store()


# ---------------------------------------------------------------------------------------------- mid-study faults
def _injected(store: Path, fault: str) -> subprocess.CompletedProcess:
    """The study in `store` with `fault` injected after its first checkpoint."""
    env = cli_env(store, ACRMDN_TEST_STORE_FAULT=fault, PYTHONPATH=f"{TESTS}{os.pathsep}{os.environ['PYTHONPATH']}")
    code = "import store_fault_injection; from experiments.cli import main; raise SystemExit(main())"
    return subprocess.run([sys.executable, "-c", code, *STUDY], cwd=store, env=env, capture_output=True, text=True,
                          timeout=600)


@pytest.mark.slow
@pytest.mark.parametrize("fault,reason", [("disk-full", "the disk is full"),
                                          ("read-only", "the store file is read-only"),
                                          ("gone", "was deleted or moved while the study ran")])
def test_a_store_fault_mid_study_is_one_line_exit_3_and_a_rerun_resumes(tmp_path, fault, reason):
    proc = _injected(tmp_path, fault)
    assert proc.returncode == 3, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert errors == [proc.stderr.strip().splitlines()[-1]], proc.stderr[-3000:]  # one, and the last line
    assert errors[0].startswith("error: the MLflow store failed: ") and reason in errors[0], errors
    log = Path(errors[0].rsplit("(traceback in ", 1)[1].rstrip(")"))
    assert "Traceback" in log.read_text()
    log.unlink()
    assert "study 'f' stopped by a store fault" in proc.stdout and "unfinished: reacher/lstm/seed0" in proc.stdout
    if fault == "gone":  # put back (it was moved): the study goes on from there
        (tmp_path / "mlflow.db.moved").replace(tmp_path / "mlflow.db")
    (cell,) = _runs(tmp_path, "cell")
    (parent,) = _runs(tmp_path, "parent")
    assert cell.info.status == parent.info.status == "RUNNING"  # nothing more was written: resumable as after a kill
    assert cell.data.tags["checkpoint_iteration"] == "5"

    again = run_cli_in_process(STUDY, tmp_path)  # the resume needs no process of its own
    assert again.returncode == 0, again.stderr[-3000:]
    (cell,) = _runs(tmp_path, "cell")
    assert cell.info.status == "FINISHED" and cell.data.tags["resumed_from_iteration"] == "5"
    assert _runs(tmp_path, "parent")[0].info.status == "FINISHED"


def _read_only(path: Path) -> bool:
    """Take the write permission from the file; as root (which writes anyway) make it immutable instead."""
    path.chmod(0o444)
    if os.geteuid() != 0:
        return True
    return shutil.which("chattr") is not None and subprocess.run(["chattr", "+i", str(path)]).returncode == 0


@pytest.mark.slow
def test_a_read_only_store_fails_the_start_up_check(tmp_path):
    from experiments.runtime.tracking import Client

    Client(_uri(tmp_path))
    db = tmp_path / "mlflow.db"
    before = db.read_bytes()
    if not _read_only(db):
        pytest.skip("running as root without chattr: no file is read-only to this process")
    try:
        proc = run_cli(STUDY, tmp_path, timeout=120)
    finally:
        if os.geteuid() == 0:
            subprocess.run(["chattr", "-i", str(db)])
        db.chmod(0o644)
    assert proc.returncode == 3 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    assert proc.stderr.strip().splitlines() == [f"error: MLflow store {db}: the file is read-only; make it writable "
                                                "(chmod u+w) or set MLFLOW_TRACKING_URI; nothing was written"]
    assert db.read_bytes() == before


# --------------------------------------------------------------------------------------------------------- Ctrl-C
@pytest.mark.slow
def test_ctrl_c_before_any_cell_started_marks_the_parent_killed(tmp_path):
    """A study of many cells interrupted while it creates their runs: the parent and the runs made so far KILLED."""
    args = [sys.executable, "-m", "experiments", *STUDY, "--seeds", "20000"]  # 20,000 cells: more than MAX_CELLS
    refused = subprocess.run(args, cwd=tmp_path, env=cli_env(tmp_path), capture_output=True, text=True, timeout=120)
    assert refused.returncode == 2 and "add --yes" in refused.stderr and not (tmp_path / "mlflow.db").exists()
    proc = subprocess.Popen([*args, "--yes"], cwd=tmp_path, env=cli_env(tmp_path), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 300  # a bound against a hang: building 20,000 cells takes a while on a busy CI
        while not _cell_runs_begun(tmp_path):  # the parent comes first
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()[-3000:]
            time.sleep(0.2)
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130 and "Traceback" not in err, err[-3000:]
    (parent,) = _runs(tmp_path, "parent")
    cells = _runs(tmp_path, "cell")
    assert parent.info.status == "KILLED", err[-3000:]
    assert 0 < len(cells) < 20000 and {c.info.status for c in cells} == {"KILLED"}
    assert not any(c.data.metrics for c in cells)  # none had started training


def test_a_ctrl_c_inside_a_store_call_comes_once_the_call_is_whole(tmp_path):
    """The Ctrl-C lands while the store writes: the write completes, then KeyboardInterrupt (a write cut short
    inside SQLAlchemy could keep SQLite's lock, and the Ctrl-C's own writes, the runs marked KILLED, waited)."""
    from experiments.runtime.tracking import Client

    client = Client(_uri(tmp_path))
    experiment_id = client.create_experiment("x")
    real = client._client.create_run

    def interrupted_create_run(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)  # handled by Python between two bytecodes: here, mid-call
        return real(*args, **kwargs)

    client._client.create_run = interrupted_create_run
    with pytest.raises(KeyboardInterrupt):
        client.create_run(experiment_id, tags={"role": "cell"})
    (run,) = MlflowClient(_uri(tmp_path)).search_runs([experiment_id])
    assert run.data.tags["role"] == "cell"  # the whole write is in the store
    client.set_terminated(run.info.run_id, "KILLED")
    assert client.get_run(run.info.run_id).info.status == "KILLED"


def _cell_runs_begun(folder: Path) -> bool:
    """Whether the store holds a cell run yet: read straight from SQLite, so that the interrupt comes while few
    runs exist (each is marked KILLED on the way out; an MLflow search per poll let hundreds be created first)."""
    if not (folder / "mlflow.db").exists():
        return False
    db = sqlite3.connect(f"file:{folder / 'mlflow.db'}?mode=ro", uri=True, timeout=5)
    try:
        return db.execute("SELECT 1 FROM tags WHERE key = 'role' AND value = 'cell' LIMIT 1").fetchone() is not None
    except sqlite3.OperationalError:  # the schema is still being created
        return False
    finally:
        db.close()


# ------------------------------------------------------------------------------------- a checkpoint of another cell
@pytest.mark.slow
def test_a_checkpoint_of_another_config_fails_its_cell_with_the_command_that_discards_it(tmp_path):
    """A cell's checkpoint swapped for another cell's: the cell fails before training, its reason (on the run and the
    console) names the command that discards the run; once that command has run, the study trains the cell anew."""
    donor = run_cli_in_process([*STUDY, "--study-name", "donor", "--set", "model.hidden_size=8"], tmp_path)  # smaller
    assert donor.returncode == 0, donor.stderr[-3000:]
    (donor_cell,) = [r for r in _runs(tmp_path, "cell") if r.data.tags["study_name"] == "donor"]
    kill_at_checkpoints(STUDY, tmp_path, 1, tmp_path / "killed.log")  # f's cell: RUNNING, its checkpoint at 5
    (cell,) = [r for r in _runs(tmp_path, "cell") if r.data.tags["study_name"] == "f"]
    client = MlflowClient(_uri(tmp_path))
    local = client.download_artifacts(donor_cell.info.run_id, "checkpoint/model.pt", str(tmp_path / "dl"))
    client.log_artifact(cell.info.run_id, local, "checkpoint")  # the donor's checkpoint in place of f's

    failed = run_cli(STUDY, tmp_path)
    assert failed.returncode == 1 and "Traceback" not in failed.stderr, failed.stderr[-3000:]
    command = f"`mlflow runs delete --run-id {cell.info.run_id}`"  # (MLFLOW_TRACKING_URI is set: no prefix)
    line = next(line for line in failed.stdout.splitlines() if "CheckpointMismatch" in line)
    assert cell.info.run_id in line and command in line, line
    assert "another model config (differing in hidden_size)" in line, line
    assert command in failed.stderr  # the cell's own error line, on the console as it happens
    run = client.get_run(cell.info.run_id)
    assert run.info.status == "FAILED" and command in run.data.tags["error"]

    deleted = subprocess.run([sys.executable, "-m", "mlflow", "runs", "delete", "--run-id", cell.info.run_id],
                             cwd=tmp_path, env=cli_env(tmp_path), capture_output=True, text=True, timeout=120)
    assert deleted.returncode == 0, deleted.stderr[-2000:]
    again = run_cli_in_process(STUDY, tmp_path)
    assert again.returncode == 0, again.stderr[-3000:]
    (new,) = [r for r in _runs(tmp_path, "cell") if r.data.tags["study_name"] == "f"]
    assert new.info.run_id != cell.info.run_id and new.info.status == "FINISHED"
    assert "resumed_from_iteration" not in new.data.tags


def test_the_discard_command_names_the_store_as_the_user_does(monkeypatch):
    from experiments.cell_run import discard_command

    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    assert discard_command("abc") == "`MLFLOW_TRACKING_URI=sqlite:///mlflow.db mlflow runs delete --run-id abc`"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://tracking:5000")
    assert discard_command("abc") == "`mlflow runs delete --run-id abc`"
