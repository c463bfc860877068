"""Helpers of the tests that run `python -m experiments` in a subprocess over a temporary store."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def env(store: Path) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(REPO), "MLFLOW_TRACKING_URI": f"sqlite:///{store / 'mlflow.db'}"}


def cli(args: list[str], store: Path, timeout: int = 400) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "experiments", *args], cwd=store, env=env(store),
                          capture_output=True, text=True, timeout=timeout)


def cell_runs(client) -> list:
    return client.search_runs([client.get_experiment_by_name("ablation").experiment_id], "tags.role = 'cell'")


def kill_when(args: list[str], store: Path, client, ready: Callable[[list], bool], seconds: float = 300,
              sig: int = signal.SIGKILL) -> list | None:
    """Start the command in its own process group and send it `sig` once `ready(cell runs)`;
    the runs it was killed at, or None when it finished (or the time ran out) first."""
    proc = subprocess.Popen([sys.executable, "-m", "experiments", *args], cwd=store, env=env(store),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    killed, deadline = None, time.monotonic() + seconds
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.3)
            try:
                runs = cell_runs(client)
            except Exception:  # store not created yet
                continue
            if ready(runs):
                os.killpg(proc.pid, sig)
                killed = runs
                break
    finally:
        if proc.poll() is None and killed is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    return killed
