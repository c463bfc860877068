"""Throwaway PostgreSQL cluster and MLflow tracking server for the integration tests
(`nox -s integration`; marker `integration`, excluded from `nox -s tests`).

PostgreSQL comes from the Debian packages: installed with apt-get when missing (CI runs as
root on a fresh machine). The cluster lives in a temp dir, listens on 127.0.0.1 on a free
port, trusts local connections, and runs as the `postgres` user when we are root (the
server refuses to run as root). Everything started here is stopped at the end of the session.
"""

from __future__ import annotations

import glob
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from cli_helpers import stop_group

PG_USER = "postgres"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def pg_bin() -> Path:
    """The newest installed PostgreSQL's bin dir, installing the Debian packages if needed."""
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"), key=lambda p: int(Path(p).parts[-3]))
    if not found:
        if os.geteuid() != 0:
            pytest.fail("PostgreSQL is not installed (apt-get install postgresql) and we are not root to install it")
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        subprocess.run(["apt-get", "update", "-q"], check=True, env=env, stdout=subprocess.DEVNULL)
        subprocess.run(["apt-get", "install", "-y", "-q", "--no-install-recommends", "postgresql"], check=True,
                       env=env, stdout=subprocess.DEVNULL)
        found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"), key=lambda p: int(Path(p).parts[-3]))
    return Path(found[-1]).parent


def _as_pg(cmd: list[str]) -> list[str]:
    return ["runuser", "-u", PG_USER, "--", *cmd] if os.geteuid() == 0 else cmd


@dataclass
class Postgres:
    bin: Path
    data: Path
    port: int

    def url(self, db: str) -> str:
        return f"postgresql://{PG_USER}@127.0.0.1:{self.port}/{db}"

    def psql(self, sql: str, db: str = "postgres") -> str:
        return subprocess.run([str(self.bin / "psql"), "-h", "127.0.0.1", "-p", str(self.port), "-U", PG_USER,
                               "-d", db, "-At", "-c", sql], check=True, capture_output=True, text=True).stdout


@pytest.fixture(scope="session")
def postgres() -> Iterator[Postgres]:
    bindir = pg_bin()
    root = Path(tempfile.mkdtemp(prefix="acrmdn-pg-"))
    data, port = root / "data", free_port()
    if os.geteuid() == 0:
        shutil.chown(root, PG_USER)
    subprocess.run(_as_pg([str(bindir / "initdb"), "-D", str(data), "-U", PG_USER, "-A", "trust", "--no-sync",
                           "-E", "UTF8"]), check=True, capture_output=True)
    opts = f"-p {port} -k {root} -c listen_addresses=127.0.0.1 -c fsync=off -c max_connections=200"
    subprocess.run(_as_pg([str(bindir / "pg_ctl"), "-D", str(data), "-o", opts, "-l", str(root / "server.log"),
                           "-w", "-t", "60", "start"]), check=True, capture_output=True)
    pg = Postgres(bindir, data, port)
    try:
        for db in ("mlflow", "optuna"):
            pg.psql(f"CREATE DATABASE {db}")
        yield pg
    finally:
        subprocess.run(_as_pg([str(bindir / "pg_ctl"), "-D", str(data), "-m", "immediate", "-w", "stop"]),
                       capture_output=True)
        shutil.rmtree(root, ignore_errors=True)


@dataclass
class MlflowServer:
    url: str
    proc: subprocess.Popen


@pytest.fixture(scope="session")
def mlflow_server(postgres: Postgres) -> Iterator[MlflowServer]:
    artifacts = Path(tempfile.mkdtemp(prefix="acrmdn-mlartifacts-"))
    port = free_port()
    log = open(artifacts.parent / f"{artifacts.name}.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "mlflow", "server", "--backend-store-uri", postgres.url("mlflow"),
                             "--artifacts-destination", str(artifacts), "--host", "127.0.0.1", "--port", str(port),
                             "--workers", "2"], stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 180
        while True:
            try:
                if urllib.request.urlopen(f"{url}/health", timeout=5).status == 200:
                    break
            except OSError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                log.flush()
                pytest.fail("mlflow server did not start:\n" + Path(log.name).read_text()[-3000:])
            time.sleep(0.5)
        yield MlflowServer(url, proc)
    finally:
        stop_group(proc)
        log.close()
        shutil.rmtree(artifacts, ignore_errors=True)
        Path(log.name).unlink(missing_ok=True)
