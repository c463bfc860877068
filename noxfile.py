"""Sessions: tests (default), integration, ablation, sweep, report, ui, bench, lint.

Each session installs the project from this folder into its own virtualenv;
`nox -r` reuses it. Arguments after `--` go to the underlying command, e.g.
`nox -s ablation -- --profile smoke`.
"""

import nox

nox.options.sessions = ["tests"]
nox.options.reuse_existing_virtualenvs = True


def _install(session: nox.Session, extras: str = "") -> None:
    session.install("-e", f".{extras}" if extras else ".")


@nox.session
def tests(session: nox.Session) -> None:
    """The test suite (benchmarks excluded). With no arguments: coverage, failing under the floor in
    pyproject.toml. `nox -s tests -- -m "not slow"`: the fast lane (a -m here narrows the default one)."""
    _install(session, "[dev]")
    args, marks = list(session.posargs), "not bench and not integration"
    if "-m" in args[:-1]:  # pytest keeps only the last -m: combine instead of replacing ours
        i = args.index("-m")
        marks = f"({marks}) and ({args.pop(i + 1)})"
        args.pop(i)
    cov = [] if session.posargs else ["--cov", "--cov-report=term"]
    session.run("pytest", "-m", marks, *cov, *args)


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
    session.run("python", "-m", "stm.bench")


@nox.session
def ablation(session: nox.Session) -> None:
    """The main job: an ablation study (quick profile by default) tracked in MLflow."""
    _install(session)
    session.run("python", "-m", "experiments", "ablation", *session.posargs)


@nox.session
def sweep(session: nox.Session) -> None:
    """An Optuna sweep of mixture count and auto-conditioning schedule."""
    _install(session)
    session.run("python", "-m", "experiments", "sweep", *session.posargs)


@nox.session
def report(session: nox.Session) -> None:
    """Regenerate tables and figures from the tracking store."""
    _install(session)
    session.run("python", "-m", "reports", *session.posargs)


@nox.session
def ui(session: nox.Session) -> None:
    """The MLflow UI on 127.0.0.1:5000 over the study store."""
    _install(session)
    session.run("python", "-m", "experiments", "ui", *session.posargs)


@nox.session
def lint(session: nox.Session) -> None:
    session.install("ruff")
    session.run("ruff", "check", ".", *session.posargs)
