"""Running the project's command lines from tests, and the fault tests' synchronisation:
plain functions (not fixtures) so that any test module can import them.

A fault test sets ACRMDN_TEST_SIGNAL_FILE (and ACRMDN_TEST_HOLD=1) for the study it runs
(see experiments/cell_run.py): every worker appends "<run_id> <iteration>" to that file once a
checkpoint of its cell is in the store, then holds there, so the test kills or interrupts the
study at a known point, never racing the training. `stop_group`: how the fixtures that start
servers (tests/integration, tests/browser) stop them: stdlib only, as the browser lane's small
environment lacks the project's dependencies."""

from __future__ import annotations

import contextlib
import io
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from unittest import mock

REPO = Path(__file__).resolve().parents[1]
SIGNAL_FILE_ENV = "ACRMDN_TEST_SIGNAL_FILE"
HOLD_ENV = "ACRMDN_TEST_HOLD"


def cli_env(store: Path, **extra: str) -> dict[str, str]:
    """The environment of a command line run on the store in `store` (its mlflow.db)."""
    return {**os.environ, "PYTHONPATH": str(REPO), "MLFLOW_TRACKING_URI": f"sqlite:///{store / 'mlflow.db'}",
            **extra}


def run_cli(args: list[str], store: Path, timeout: int = 400, module: str = "experiments",
            **extra_env: str) -> subprocess.CompletedProcess:
    """`python -m <module> ARGS` in `store`, output captured."""
    return subprocess.run([sys.executable, "-m", module, *args], cwd=store, env=cli_env(store, **extra_env),
                          capture_output=True, text=True, timeout=timeout)


def run_in_process(module: str, argv: list[str], cwd: Path, log_level: int | None = None) -> tuple[int, str]:
    """`python -m <module> ARGV` ("experiments" or "reports") in this process, in `cwd`: its exit code and stderr,
    with the log lines at `log_level` and above among them where one is given (None: the loggers untouched).
    Cheaper than a subprocess where a property test runs hundreds of command lines."""
    code, _, err = _in_process(module, argv, cwd, log_level, "%(message)s")
    return code, err


def run_cli_in_process(args: list[str], store: Path, module: str = "experiments",
                       **extra_env: str) -> subprocess.CompletedProcess:
    """run_cli's command in this process: its exit code, stdout and stderr (with the INFO log lines, as the command
    line prints them). A study run so costs its own work only: a `python -m experiments` process first pays ~10 CPU-s
    of imports and first-use set-ups that this process has made already. For commands whose outcome a test reads
    from the store and the output; where processes, signals or exit codes are what a test checks, run_cli."""
    env = {"MLFLOW_TRACKING_URI": f"sqlite:///{store / 'mlflow.db'}", **extra_env}
    sigint = signal.getsignal(signal.SIGINT)  # the command line may install its own handler
    try:
        with mock.patch.dict(os.environ, env):
            code, out, err = _in_process(module, args, store, logging.INFO, "%(asctime)s %(name)s: %(message)s")
    finally:
        signal.signal(signal.SIGINT, sigint)
    return subprocess.CompletedProcess([module, *args], code, out, err)


def _in_process(module: str, argv: list[str], cwd: Path, log_level: int | None, log_format: str
                ) -> tuple[int, str, str]:
    if module == "experiments":
        from experiments.cli import main
    else:
        from reports.__main__ import main
    out, err, root = io.StringIO(), io.StringIO(), logging.getLogger()
    handler, level = logging.StreamHandler(err), root.level
    handler.setFormatter(logging.Formatter(log_format))
    if log_level is not None:
        root.addHandler(handler)
        root.setLevel(log_level)
    old = os.getcwd()
    os.chdir(cwd)
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
            try:
                code = main(argv)
            except SystemExit as exc:  # argparse usage errors
                code = exc.code
    finally:
        os.chdir(old)
        root.removeHandler(handler)
        root.setLevel(level)
    return code, out.getvalue(), err.getvalue()


def render_results(store: Path, out: Path, template: str) -> int:
    """`python -m reports --results` in process: `template` (text) rendered from the store into out/RESULTS.md
    and out/figures; its exit code."""
    from reports.__main__ import main

    out.mkdir(parents=True, exist_ok=True)
    (out / "template.md").write_text(template)
    return main(["--results", "--tracking-uri", f"sqlite:///{store / 'mlflow.db'}", "--template",
                 str(out / "template.md"), "--results-out", str(out / "RESULTS.md"), "--figures-dir",
                 str(out / "figures")])


def held_env(store: Path, signal_file: Path) -> dict[str, str]:
    """cli_env with the fault hook on: each cell signals its first checkpoint and holds there."""
    return cli_env(store, **{SIGNAL_FILE_ENV: str(signal_file), HOLD_ENV: "1"})


def wait_for_signals(signal_file: Path, n: int, proc: subprocess.Popen, timeout: float = 300,
                     log: Path | None = None) -> list[tuple[str, int]]:
    """Block until `n` distinct runs have signalled a checkpoint; returns their (run_id, iteration).
    Fails at once if the process exits first (it would never signal), and after `timeout` s."""
    deadline = time.monotonic() + timeout
    while True:
        lines = signal_file.read_text().split("\n") if signal_file.exists() else []
        seen: dict[str, int] = {}
        for line in lines:
            if line.count(" ") == 1:  # complete lines only
                run_id, iteration = line.split(" ")
                seen.setdefault(run_id, int(iteration))
        if len(seen) >= n:
            return list(seen.items())
        tail = log.read_text()[-3000:] if log is not None and log.exists() else ""
        if proc.poll() is not None:
            raise AssertionError(f"the study exited ({proc.returncode}) before {n} cell(s) signalled: {tail}")
        if time.monotonic() > deadline:
            raise AssertionError(f"no checkpoint signal from {n} cell(s) within {timeout} s: {tail}")
        time.sleep(0.05)  # waiting on the file, not as synchronisation: the cells hold once they signal


def kill_at_checkpoints(args: list[str], store: Path, n: int, log: Path) -> tuple[list[tuple[str, int]], int]:
    """Run `python -m experiments ARGS` in `store` with the fault hook on until `n` cells have
    signalled their first checkpoint, then SIGKILL its process group: their (run_id, iteration)
    and the command's return code."""
    with open(log, "w") as out:
        proc = subprocess.Popen([sys.executable, "-m", "experiments", *args], cwd=store,
                                env=held_env(store, log.with_suffix(".signals")), stdout=out,
                                stderr=subprocess.STDOUT, start_new_session=True)
    try:
        marks = wait_for_signals(log.with_suffix(".signals"), n, proc, log=log)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    return marks, proc.returncode


def stop_group(proc: subprocess.Popen, grace: float = 30) -> None:
    """Stop the process group of `proc` (started with start_new_session=True): SIGTERM, then
    SIGKILL if it has not exited within `grace` s. A group already gone is fine."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, sig)
        try:
            proc.wait(timeout=grace if sig == signal.SIGTERM else None)
            return
        except subprocess.TimeoutExpired:
            continue
