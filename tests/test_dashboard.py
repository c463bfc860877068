"""`python -m experiments.sweeps.dashboard`: optuna-dashboard over the sweep storage (the journal
file next to mlflow.db by default, an RDB URL when given), read over HTTP on a free port."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import optuna
import pytest

from experiments.runtime.optuna_storage import JOURNAL_NAME, open_storage

REPO = Path(__file__).resolve().parents[1]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _make_study(spec: str, name: str, trials: int) -> None:
    study = optuna.create_study(study_name=name, storage=open_storage(spec), direction="minimize")
    study.optimize(lambda t: (t.suggest_int("m", 1, 20) - 5) ** 2, n_trials=trials)


def _env(store: Path) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(REPO), "MLFLOW_TRACKING_URI": f"sqlite:///{store / 'mlflow.db'}"}


def _serve(args: list[str], store: Path) -> tuple[list[dict], str]:
    """Start the dashboard, wait for its study list over HTTP, stop it; (studies, its printout)."""
    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "experiments.sweeps.dashboard", "--port", str(port), *args],
                            cwd=store, env=_env(store), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/studies", timeout=5) as r:
                    studies = json.load(r)["study_summaries"]
                break
            except OSError as exc:  # not listening yet
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise AssertionError(f"dashboard did not answer: {exc}\n{proc.stdout.read()}") from exc
                time.sleep(0.3)
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        out = proc.communicate(timeout=30)[0]
    return studies, out


@pytest.mark.slow
def test_dashboard_lists_the_sweeps_in_the_default_journal(tmp_path):
    _make_study(f"journal:{tmp_path / JOURNAL_NAME}", "reacher-ac-lstm-mdn", trials=3)
    _make_study(f"journal:{tmp_path / JOURNAL_NAME}", "pick-place-lstm-mdn", trials=2)
    studies, out = _serve([], tmp_path)
    assert sorted(s["study_name"] for s in studies) == ["pick-place-lstm-mdn", "reacher-ac-lstm-mdn"]
    assert f"journal:{tmp_path / JOURNAL_NAME}" in out
    assert "reacher-ac-lstm-mdn: 3 trial(s)" in out and "/dashboard" in out


@pytest.mark.slow
def test_dashboard_over_an_rdb_url(tmp_path):
    url = f"sqlite:///{tmp_path / 'optuna.db'}"
    _make_study(url, "sweep-on-rdb", trials=2)
    studies, out = _serve(["--storage", url], tmp_path)
    assert [s["study_name"] for s in studies] == ["sweep-on-rdb"]
    assert url in out


@pytest.mark.slow
@pytest.mark.parametrize("args, says", [([], "no sweep storage at"), (["--storage", "nosuch://x"], "error: ")])
def test_nothing_to_open_is_one_line_and_exit_2(tmp_path, args, says):
    proc = subprocess.run([sys.executable, "-m", "experiments.sweeps.dashboard", *args], cwd=tmp_path,
                          env=_env(tmp_path), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and says in lines[0], proc.stderr
    assert not (tmp_path / JOURNAL_NAME).exists()  # nothing created by looking
