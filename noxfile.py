"""Sessions: tests (default), integration, bench, lint, browser; the user's sessions ablation,
sweep, report, ui, dashboard, smoothing, idm; and app, the environment those share.

The user's sessions run in ONE environment, `.nox/app`, built by the `app` session (each of
them `requires` it, so nox runs it first): the project installed from this folder, editable.
`app` installs again only when pyproject.toml changed since the last install (a hash kept
in the environment), so after the first session the next ones start in seconds. tests,
integration and bench keep their own environments (their extras differ); lint and browser
have small ones. Arguments after `--` go to the underlying command, e.g.
`nox -s ablation -- --profile smoke`.
"""

import hashlib
import os
import shutil
from pathlib import Path

import nox

nox.options.sessions = ["tests"]
nox.options.reuse_venv = "yes"

APP = "app"
STAMP = "acrmdn-install.sha256"  # in the environment: what the project was last installed from
REQUIRE_CPP = "ACRMDN_REQUIRE_CPP"  # stm.cpp_ext.REQUIRE; `ACRMDN_REQUIRE_CPP=0 nox -s tests` lets the C++ tests skip


def _install(session: nox.Session, extras: str = "") -> None:
    """`pip install -e .[extras]` unless this environment already holds an install made from
    the same pyproject.toml and extras (the code itself is editable: no reinstall needed)."""
    spec = f".{extras}" if extras else "."
    digest = hashlib.sha256(Path("pyproject.toml").read_bytes() + spec.encode()).hexdigest()
    stamp = Path(session.virtualenv.location) / STAMP
    if stamp.is_file() and stamp.read_text() == digest:
        session.log(f"{spec} already installed from this pyproject.toml")
        return
    session.install("-e", spec)
    stamp.write_text(digest)


def _app_env(session: nox.Session) -> dict[str, str]:
    """Environment variables that put the `app` session's virtualenv first (nox keeps every
    session's virtualenv beside its shared cache_dir)."""
    venv = (session.cache_dir.parent / APP).absolute()  # absolute: commands may run in another folder
    return {"VIRTUAL_ENV": str(venv), "PATH": f"{venv / 'bin'}{os.pathsep}{os.environ.get('PATH', '')}"}


def _run_app(session: nox.Session, *args: str) -> None:
    env = _app_env(session)  # nox finds the command on its own PATH: name the app's python in full
    session.run(str(Path(env["VIRTUAL_ENV"]) / "bin" / "python"), *args, *session.posargs, env=env, external=True)


@nox.session(default=False)
def app(session: nox.Session) -> None:
    """The environment the user's sessions share (.nox/app): the project and its dependencies."""
    _install(session)


@nox.session
def tests(session: nox.Session) -> None:
    """The test suite (benchmarks, integration and browser checks excluded). `nox -s tests -- --cov`:
    with coverage, failing under the floor in pyproject.toml (CI runs it so; the tracing costs ~30 %
    more CPU). `nox -s tests -- -m "not slow"`: the fast lane (a -m here narrows the default one).
    All run on pytest-xdist (`-n auto --dist loadfile`) unless the arguments choose (`-n 0`: one process). The C++
    step kernel must build here (ACRMDN_REQUIRE_CPP=1 unless the environment sets it)."""
    _install(session, "[dev]")
    args, marks = list(session.posargs), "not bench and not integration and not browser"
    if "-m" in args[:-1]:  # pytest keeps only the last -m: combine instead of replacing ours
        i = args.index("-m")
        marks = f"({marks}) and ({args.pop(i + 1)})"
        args.pop(i)
    cov = []
    if "--cov" in args:  # moved before an option, so that it never takes a test path as its source
        args.remove("--cov")
        cov = ["--cov"] + ([] if any(a.startswith("--cov-report") for a in args) else ["--cov-report=term"])
    # pytest-xdist, one worker a core; a module's tests share a worker (its module fixtures are built once)
    xdist = [] if any(a.startswith(("-n", "--numprocesses", "--dist")) for a in args) else \
        ["-n", "auto", "--dist", "loadfile"]
    scratch, env = _memory_tmpdir()
    # the C++ step kernel must build (stm.cpp_ext): a broken toolchain fails its tests instead of skipping them
    env[REQUIRE_CPP] = os.environ.get(REQUIRE_CPP, "1")
    if scratch:
        session.log(f"test folders in memory: TMPDIR={scratch}")
        args = ["-o", "tmp_path_retention_count=1", *args]  # the last run's folders only, in RAM
    session.run("pytest", *cov, "-m", marks, *xdist, *args, env=env)


def _memory_tmpdir(min_free: int = 4 << 30) -> tuple[str | None, dict[str, str]]:
    """TMPDIR in /dev/shm when it is a writable tmpfs with room (else the default): the tests' throwaway
    SQLite stores commit thousands of times, and on a disk each commit waits on fsync (the suite took
    11 min 36 s with it, 14 min 20 s without, on the same loaded 2-core machine)."""
    shm = Path("/dev/shm")
    try:
        if not (os.access(shm, os.W_OK) and shutil.disk_usage(shm).free >= min_free):
            return None, {}
        folder = shm / f"acrmdn-tests-{os.getuid()}"
        folder.mkdir(exist_ok=True)
    except OSError:
        return None, {}
    return str(folder), {"TMPDIR": str(folder)}


@nox.session
def integration(session: nox.Session) -> None:
    """Scale-out on PostgreSQL: installs it (Debian packages) if missing, starts a throwaway
    cluster and an MLflow server on 127.0.0.1, runs sweep workers and kills one (tests/integration)."""
    _install(session, "[dev,integration]")
    session.run("pytest", "-m", "integration", "tests/integration", *session.posargs)


@nox.session
def bench(session: nox.Session) -> None:
    """Benchmarks: pytest-benchmark suites, then the STM bench."""
    _install(session, "[dev]")
    session.run("pytest", "-m", "bench", "--benchmark-only", "--benchmark-columns=min,mean,median,ops,rounds",
                *session.posargs)
    session.run("python", "-m", "stm.speed.bench")


@nox.session(venv_backend="none", requires=[APP])
def ablation(session: nox.Session) -> None:
    """The main job: an ablation study (quick profile by default) tracked in MLflow."""
    _run_app(session, "-m", "experiments", "ablation")


@nox.session(venv_backend="none", requires=[APP])
def sweep(session: nox.Session) -> None:
    """An Optuna sweep of mixture count and auto-conditioning schedule."""
    _run_app(session, "-m", "experiments", "sweep")


@nox.session(venv_backend="none", requires=[APP])
def smoothing(session: nox.Session) -> None:
    """The trajectory smoothing study."""
    _run_app(session, "-m", "experiments", "smoothing")


@nox.session(venv_backend="none", requires=[APP])
def idm(session: nox.Session) -> None:
    """The inverse dynamics model study."""
    _run_app(session, "-m", "experiments", "idm")


@nox.session(venv_backend="none", requires=[APP])
def report(session: nox.Session) -> None:
    """Regenerate tables and figures from the tracking store (`-- --results`: RESULTS.md; `-- export` / `-- import`:
    the study exports of reports/studies, see reports/data/export.py)."""
    _run_app(session, "-m", "reports")


@nox.session(venv_backend="none", requires=[APP])
def ui(session: nox.Session) -> None:
    """The MLflow UI on 127.0.0.1:5000 over the study store."""
    _run_app(session, "-m", "experiments", "ui")


@nox.session(venv_backend="none", requires=[APP])
def dashboard(session: nox.Session) -> None:
    """optuna-dashboard on 127.0.0.1:8080 over the sweep storage (journal file, or `-- --storage URL`)."""
    _run_app(session, "-m", "experiments.sweeps.dashboard")


@nox.session(requires=[APP])
def browser(session: nox.Session) -> None:
    """Headless Chromium (Debian packages, installed when missing) over the MLflow UI, the
    dashboard and a report built from smoke studies run in the app environment;
    ACRMDN_SCREENSHOTS=docs/screenshots also saves the pictures in the README."""
    session.install("selenium>=4.20", "pytest>=8", "pytest-timeout>=2")
    app_python = Path(_app_env(session)["VIRTUAL_ENV"]) / "bin" / "python"
    # --confcutdir: the suite's conftest files import the project, which this small venv lacks
    session.run("pytest", "-p", "no:cacheprovider", "--confcutdir", "tests/browser", "-m", "browser", "tests/browser",
                *session.posargs,
                env={"ACRMDN_APP_PYTHON": str(app_python)})


@nox.session
def lint(session: nox.Session) -> None:
    """ruff over the repository."""
    session.install("ruff>=0.5")
    session.run("ruff", "check", ".", *session.posargs)
