"""Concurrency and process faults on one machine, each by real processes on a real
SQLite store: a working directory we may not write to, studies racing on a fresh store's
schema, two identical studies at once, the main process killed with SIGKILL while its workers
train, a Ctrl-C that reaches a worker twice while it checkpoints, a missing store folder or a corrupt
database, and pybullet's banner on one-line errors."""

from __future__ import annotations

import multiprocessing as mp
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mlflow.tracking import MlflowClient

REPO = Path(__file__).resolve().parents[1]
FAST = ["--set", "eval.figures=0", "--set", "eval.rollouts=2", "--set", "train.val_every=0"]


def _env(store: Path, **extra: str) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(REPO), "MLFLOW_TRACKING_URI": f"sqlite:///{store / 'mlflow.db'}",
            **extra}


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "experiments", *args]


def _without_permission_override() -> list[str]:
    """A command prefix under which root obeys file permission bits, as any other user does."""
    if os.geteuid() != 0:
        return []
    if shutil.which("setpriv") is None:
        pytest.skip("running as root without setpriv: permission bits cannot be enforced")
    return ["setpriv", "--bounding-set", "-dac_override,-dac_read_search"]


@pytest.mark.slow
def test_unwritable_working_directory_fails_at_once_with_one_line(tmp_path):
    work = tmp_path / "ro"
    work.mkdir()
    work.chmod(0o555)
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    try:  # before: MLflow retried creating ./mlflow.db for minutes (the timeout below fired)
        proc = subprocess.run([*_without_permission_override(), *_cli("ablation", "--profile", "smoke")], cwd=work,
                              env={**env, "PYTHONPATH": str(REPO)}, capture_output=True, text=True, timeout=120)
    finally:
        work.chmod(0o755)
    assert proc.returncode == 3, proc.stderr[-2000:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr[-2000:]
    assert lines[0].startswith("error: MLflow store") and "not writable" in lines[0]
    assert "start it" not in lines[0]  # waiting would not help: no hint to wait
    assert not list(work.iterdir())


def _open_store(uri: str, barrier, results) -> None:
    from experiments.runtime.tracking import Client, get_or_create_experiment

    barrier.wait()  # every process creates the fresh store at the same moment
    try:
        results.put(get_or_create_experiment(Client(uri), "ablation"))
    except Exception as exc:
        results.put(f"{type(exc).__name__}: {exc}"[:300])


@pytest.mark.slow
def test_processes_creating_a_fresh_store_at_once_do_not_race_on_its_schema(tmp_path):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    ctx = mp.get_context("spawn")
    n = 4
    barrier, results = ctx.Barrier(n), ctx.Queue()
    procs = [ctx.Process(target=_open_store, args=(uri, barrier, results)) for _ in range(n)]
    for p in procs:
        p.start()
    ids = [results.get(timeout=300) for _ in procs]  # before: alembic errors in all but one
    for p in procs:
        p.join()
    assert len(set(ids)) == 1, ids
    exp = MlflowClient(uri).get_experiment(ids[0])
    assert exp.tags["mlflow.experimentKind"] == "custom_model_development"


def test_missing_folder_and_corrupt_database_fail_at_once_without_a_hint_to_wait(tmp_path):
    from experiments.runtime.store_check import StoreUnusable, wait_for_stores

    with pytest.raises(StoreUnusable) as missing:
        wait_for_stores(f"sqlite:///{tmp_path / 'nope' / 'mlflow.db'}", attempts=5, delay=30)  # no retry: no wait
    assert "does not exist" in str(missing.value) and "start it" not in str(missing.value)
    (tmp_path / "mlflow.db").write_bytes(b"this is not a database" * 100)
    with pytest.raises(StoreUnusable) as corrupt:
        wait_for_stores(f"sqlite:///{tmp_path / 'mlflow.db'}", attempts=5, delay=30)
    assert "not a usable SQLite database" in str(corrupt.value) and "start it" not in str(corrupt.value)


@pytest.mark.slow
def test_one_line_errors_stay_one_line_despite_pybullets_banner(tmp_path):
    proc = subprocess.run(_cli("ablation", "--profile", "smoke", "--tasks", "nope"), cwd=tmp_path,
                          env=_env(tmp_path), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [proc.stderr.strip()]  # before: "pybullet build time: ..." first
    assert proc.stderr.startswith("error: tasks:")


def test_redacted_urls_hide_passwords():
    from experiments.runtime.store_check import redact

    assert redact("postgresql://acrmdn:s3cret@db:5432/optuna") == "postgresql://acrmdn:***@db:5432/optuna"
    assert redact("http://127.0.0.1:5000") == "http://127.0.0.1:5000"


@pytest.mark.slow
def test_a_claim_is_taken_once_and_freed_when_its_holder_is_gone(tmp_path):
    from experiments.runtime.claims import is_live, latest_claim, try_claim
    from experiments.runtime.tracking import Client, get_or_create_experiment

    client = Client(f"sqlite:///{tmp_path / 'mlflow.db'}")
    run_id = client.create_run(get_or_create_experiment(client, "ablation")).info.run_id
    host = socket.gethostname()
    assert try_claim(client, run_id, grace=60, me=f"{host}:{os.getpid()}:a") == 1
    assert try_claim(client, run_id, grace=60, me=f"{host}:{os.getpid()}:b") == 0  # live: ours, fresh beat
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    client.log_param(run_id, "claim.2", f"{host}:{dead.pid}:c")  # a holder that died (kill -9) on this host
    client.set_tag(run_id, "claim.beat", f"2:{time.time():.0f}")
    assert not is_live(client.get_run(run_id), grace=60)  # a re-run takes over at once, not after the grace
    assert try_claim(client, run_id, grace=60, me=f"{host}:{os.getpid()}:d") == 3
    assert latest_claim(client.get_run(run_id)) == (3, f"{host}:{os.getpid()}:d")


def _cells(client: MlflowClient):
    exp = client.get_experiment_by_name("ablation")
    return client.search_runs([exp.experiment_id], "tags.role = 'cell'") if exp else []


@pytest.mark.slow
def test_two_identical_studies_at_once_train_each_cell_once_and_report_the_same_table(tmp_path):
    args = _cli("ablation", "--profile", "smoke", "--workers", "1", "--study-name", "twin",
                "--set", "train.iters=300", "--set", "train.checkpoint_every=50", *FAST)
    procs = [subprocess.Popen(args, cwd=tmp_path, env=_env(tmp_path), stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, start_new_session=True) for _ in range(2)]
    try:
        outs = [p.communicate(timeout=600) for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
    for p, (_, err) in zip(procs, outs, strict=True):
        assert p.returncode == 0, err[-3000:]
        assert "Traceback" not in err, err[-3000:]
    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    runs = _cells(client)
    assert len(runs) == 2 and {r.info.status for r in runs} == {"FINISHED"}
    for run in runs:  # trained by one process: one claim, each step logged once (before: twice)
        assert [k for k in run.data.params if k.startswith("claim.")] == ["claim.1"]
        steps = [m.step for m in client.get_metric_history(run.info.run_id, "train/loss")]
        assert len(steps) == len(set(steps)) and max(steps) == 300
    tables = [out[out.index("success rate"):out.index("runs:")] for out, _ in outs]
    assert tables[0] == tables[1]
    assert sum("cell(s) run" in out for out, _ in outs) == 2
    parents = client.search_runs([client.get_experiment_by_name("ablation").experiment_id], "tags.role = 'parent'")
    assert len(parents) == 1 and parents[0].info.status == "FINISHED"
    from experiments.ablation import success_markdown
    from experiments.runtime.tracking import Client

    table = success_markdown(Client(f"sqlite:///{tmp_path / 'mlflow.db'}"), parents[0].info.experiment_id,
                          parents[0].info.run_id)
    assert "variant" in table and table in parents[0].data.tags["mlflow.note.content"]  # the run's description


def _children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid and fields[0] != "Z":
            out.append(int(stat.parent.name))
    return out


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")
def test_workers_stop_when_the_main_process_is_killed(tmp_path):
    # cells far too long to finish during the test: a worker that trained on alone would still be alive
    args = _cli("ablation", "--profile", "smoke", "--workers", "2", "--study-name", "orphans",
                "--set", "train.iters=200000", "--set", "train.checkpoint_every=50", *FAST)
    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    proc = subprocess.Popen(args, cwd=tmp_path, env=_env(tmp_path), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    workers: list[int] = []
    try:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.5)
            try:
                runs = _cells(client)
            except Exception:  # store not created yet
                continue
            if len(runs) == 2 and all(int(r.data.tags.get("checkpoint_iteration", 0)) >= 50 for r in runs):
                workers = _children(proc.pid)  # the cells' processes (and multiprocessing's resource tracker)
                os.kill(proc.pid, signal.SIGKILL)  # the main process only, as the OOM killer would
                break
        assert workers, "the cells never checkpointed"
        proc.wait()
        deadline = time.monotonic() + 90  # a generous bound; before the fix they trained on for hours
        while time.monotonic() < deadline and any(_alive(p) for p in workers):
            time.sleep(0.5)
        assert not [p for p in workers if _alive(p)], "worker processes outlived their study"
    finally:
        if proc.poll() is None:
            proc.kill()
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    steps = {r.info.run_id: max(m.step for m in client.get_metric_history(r.info.run_id, "train/loss"))
             for r in _cells(client)}
    time.sleep(2)
    assert steps == {r.info.run_id: max(m.step for m in client.get_metric_history(r.info.run_id, "train/loss"))
                     for r in _cells(client)}  # nothing writes to the store any more


def _death_signal() -> int:
    import ctypes

    from experiments.runtime.processes import PR_GET_PDEATHSIG

    got = ctypes.c_int(0)
    ctypes.CDLL(None).prctl(PR_GET_PDEATHSIG, ctypes.byref(got))
    return got.value


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_the_kernel_kills_a_worker_when_its_main_process_dies():
    """Not left to the watch thread's poll, which a busy or starved worker may run seconds late."""
    from experiments.runtime.processes import worker_pool

    with worker_pool(1) as pool:
        assert pool.submit(_death_signal).result(timeout=120) == signal.SIGKILL


_INTERRUPTED_WORKER = '''
import sys
import time
from pathlib import Path

from experiments.runtime.processes import worker_pool


def cell(out):
    Path(out, "started").write_text("")
    try:
        while True:
            time.sleep(0.05)
    except KeyboardInterrupt:  # what a cell does on Ctrl-C: checkpoint where it stands, which takes a while
        time.sleep(3)
        Path(out, "saved").write_text("")
        raise


if __name__ == "__main__":
    with worker_pool(1) as pool:
        pool.submit(cell, sys.argv[1]).result()
'''


@pytest.mark.slow
def test_ctrl_c_in_a_terminal_lets_a_worker_finish_its_checkpoint(tmp_path):
    # Ctrl-C reaches the main process and the worker at once; the main process then stops the worker a second
    # time. Before: that second interrupt cut the worker's checkpoint short
    script = tmp_path / "study.py"
    script.write_text(_INTERRUPTED_WORKER)
    proc = subprocess.Popen([sys.executable, str(script), str(tmp_path)], env=_env(tmp_path),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 120
        while not (tmp_path / "started").exists():
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()[-2000:]
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGINT)  # the whole group, as a terminal does
        proc.wait(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert (tmp_path / "saved").exists(), proc.stderr.read()[-2000:]
