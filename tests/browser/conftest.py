"""Fixtures of the browser check (`nox -s browser`; marker `browser`): smoke studies and their
report built with the app environment's Python (ACRMDN_APP_PYTHON, else this one), the MLflow
UI and optuna-dashboard serving them on free ports of 127.0.0.1, and headless Chromium driven
by Selenium through chromedriver. Chromium and chromedriver come from the Debian packages
(`chromium`, `chromium-driver`), installed with apt-get when missing, as PostgreSQL is for the
integration tests. selenium is imported inside the fixtures: the test suite's own environment
collects this folder without it (the tests there skip)."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest
from cli_helpers import stop_group

REPO = Path(__file__).resolve().parents[2]
APP_PYTHON = os.environ.get("ACRMDN_APP_PYTHON") or sys.executable
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--no-first-run", "--window-size=1280,800")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def chromium() -> tuple[str, str]:
    """Paths of chromium and chromedriver, installing the Debian packages if needed."""
    found = shutil.which("chromium"), shutil.which("chromedriver")
    if all(found):
        return found
    if os.geteuid() != 0:
        pytest.fail("Chromium is not installed (apt-get install chromium chromium-driver) and we are not root")
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    subprocess.run(["apt-get", "update", "-q"], check=True, env=env, stdout=subprocess.DEVNULL)
    subprocess.run(["apt-get", "install", "-y", "-q", "--no-install-recommends", "chromium", "chromium-driver"],
                   check=True, env=env, stdout=subprocess.DEVNULL)
    return shutil.which("chromium"), shutil.which("chromedriver")


def _env() -> dict[str, str]:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    env.pop("MLFLOW_TRACKING_URI", None)  # the studies write ./mlflow.db in their folder
    return env


def _app(args: list[str], cwd: Path) -> None:
    proc = subprocess.run([APP_PYTHON, *args], cwd=cwd, env=_env(), capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, f"{args}: exit {proc.returncode}\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}"


@pytest.fixture(scope="session")
def store(tmp_path_factory) -> Path:
    """A folder with a smoke ablation, a smoke sweep and their report."""
    root = tmp_path_factory.mktemp("browser-store")
    _app(["-m", "experiments", "ablation", "--profile", "smoke", "--workers", "1"], root)
    _app(["-m", "experiments", "sweep", "--profile", "smoke", "--workers", "1"], root)
    _app(["-m", "reports"], root)
    return root


def _serve(args: list[str], cwd: Path, ready: str) -> Iterator[str]:
    """Start a server of the app environment on a free port; yield its base URL once `ready`
    answers 200; stop its whole process group afterwards."""
    port = free_port()
    log = open(cwd / f"server-{port}.log", "w")
    proc = subprocess.Popen([APP_PYTHON, *args, "--port", str(port)], cwd=cwd, env=_env(), stdout=log,
                            stderr=subprocess.STDOUT, start_new_session=True)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 240
        while True:
            try:
                if urllib.request.urlopen(url + ready, timeout=5).status == 200:
                    break
            except OSError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                log.flush()
                pytest.fail(f"{args} did not start:\n" + Path(log.name).read_text()[-3000:])
            time.sleep(0.5)
        yield url
    finally:
        stop_group(proc)
        log.close()


@pytest.fixture(scope="session")
def mlflow_ui(store: Path) -> Iterator[str]:
    yield from _serve(["-m", "experiments", "ui"], store, "/health")


@pytest.fixture(scope="session")
def dashboard(store: Path) -> Iterator[str]:
    yield from _serve(["-m", "experiments.sweeps.dashboard"], store, "/api/studies")


@pytest.fixture(scope="session")
def driver():
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    binary, chromedriver = chromium()
    options = webdriver.ChromeOptions()
    options.binary_location = binary
    for flag in CHROMIUM_FLAGS:
        options.add_argument(flag)
    d = webdriver.Chrome(service=Service(chromedriver), options=options)
    try:
        yield d
    finally:
        d.quit()


@pytest.fixture(scope="session")
def screenshots() -> Path | None:
    """Where to save the pictures (ACRMDN_SCREENSHOTS, e.g. docs/screenshots), else nowhere."""
    folder = os.environ.get("ACRMDN_SCREENSHOTS")
    if not folder:
        return None
    path = Path(folder) if Path(folder).is_absolute() else REPO / folder
    path.mkdir(parents=True, exist_ok=True)
    return path
