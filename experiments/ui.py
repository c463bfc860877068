"""`python -m experiments ui`: the MLflow UI over the study store, with the runs-page links
printed first (MLflow 3 opens an experiment on its GenAI overview, not on the runs)."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time

from experiments.runtime.tracking import STUDY_KINDS, runs_page_url, sqlite_path, tracking_uri

log = logging.getLogger(__name__)


def experiment_links(uri: str, host: str, port: int) -> list[str]:
    """Links to the runs page of every study-kind experiment already in the store (read only:
    a missing sqlite file is not created here)."""
    db = sqlite_path(uri)
    if db is not None and not db.exists():
        return []
    from experiments.runtime.tracking import Client

    client = Client(uri)
    links = []
    for kind in STUDY_KINDS:
        exp = client.get_experiment_by_name(kind)
        if exp is not None:
            links.append(f"{kind}: {runs_page_url(exp.experiment_id, host, port)}")
    return links


def serve(host: str = "127.0.0.1", port: int = 5000) -> int:
    uri = tracking_uri()
    if not uri.startswith(("sqlite:", "postgresql", "mysql", "mssql", "file:")):
        print(f"MLFLOW_TRACKING_URI={uri} is a tracking server already; open it in a browser.")
        return 0
    links = experiment_links(uri, host, port)
    print(f"MLflow UI over {uri}")
    for line in links or [f"no studies yet; after `nox -s ablation` see {runs_page_url('<id>', host, port)}"]:
        print(f"  {line}", flush=True)
    cmd = [sys.executable, "-m", "mlflow", "ui", "--backend-store-uri", uri, "--host", host, "--port", str(port)]
    db = sqlite_path(uri)
    if db is not None:  # new experiments created through the UI keep artifacts beside the db
        cmd += ["--artifacts-destination", str(db.parent / "mlartifacts")]
    # browsing needs no MLflow job execution (GenAI jobs): without it the server starts no huey consumer
    # processes, each of which imports all of mlflow (a user's explicit setting wins)
    env = {"MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false", **os.environ}
    # the server starts helper processes (uvicorn workers): run it in its own process group and stop
    # the whole group on Ctrl-C or SIGTERM, leaving nothing behind
    proc = subprocess.Popen(cmd, start_new_session=True, env=env)

    def stop(*_):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        return proc.wait()
    except KeyboardInterrupt:
        return 0
    finally:
        signal.signal(signal.SIGTERM, previous)
        _stop_group(proc)


def _stop_group(proc: subprocess.Popen, grace: float = 10.0) -> None:
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        deadline = time.monotonic() + grace
        while time.monotonic() < deadline:
            try:
                os.killpg(proc.pid, 0)  # anything left in the group?
            except ProcessLookupError:
                proc.poll()
                return
            proc.poll()
            time.sleep(0.2)
