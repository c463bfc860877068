"""The command written into RESULTS.md ({{ command }}) that regenerates it: `nox -s report -- --results ...` with the
studies pinned by name and the store named portably (relative to the working directory, or by
$MLFLOW_TRACKING_URI), never by a path of this machine."""

from __future__ import annotations

import os
import shlex
from pathlib import Path

from reports.data.store import DEFAULT_TRACKING_URI, Study

DEFAULT_TEMPLATE = Path("reports/RESULTS.template.md")
DEFAULT_RESULTS = Path("reports/RESULTS.md")
DEFAULT_FIGURES = Path("reports/figures")


def portable_uri(uri: str | None, cwd: Path | None = None) -> str | None:
    """The store as the regeneration command names it: a SQLite file relative to the working directory, None for
    the default store, '$MLFLOW_TRACKING_URI' for anything else (a server URL may hold a password)."""
    if uri is None:
        return None
    if not uri.startswith("sqlite:///"):
        return "$MLFLOW_TRACKING_URI"
    path = Path(uri.removeprefix("sqlite:///"))
    if path.is_absolute():
        path = Path(os.path.relpath(path, cwd or Path.cwd()))
    rel = f"sqlite:///{path.as_posix()}"
    return None if rel == DEFAULT_TRACKING_URI else rel


def _portable_path(value: Path) -> str:
    return Path(os.path.relpath(value)).as_posix() if Path(value).is_absolute() else Path(value).as_posix()


def regeneration_command(ablation: Study | None, sweeps_used: list[Study], template: Path, results_out: Path,
                         figures_dir: Path, tracking_uri: str | None, exports: Path | None = None) -> str:
    """`nox -s report -- --results ...` with the studies pinned by name (non-default paths and the store, in
    portable_uri's form, or the exports folder, kept)."""
    args = ["nox", "-s", "report", "--", "--results"]
    uri = None if exports else portable_uri(tracking_uri)
    if uri:
        args += ["--tracking-uri", uri]
    if exports:
        args += ["--exports", _portable_path(exports)]
    if ablation is not None:
        args += ["--ablation", ablation.name]
    for s in sweeps_used:
        args += ["--sweep", s.name]
    for flag, value, default in (("--template", template, DEFAULT_TEMPLATE), ("--results-out", results_out,
                                 DEFAULT_RESULTS), ("--figures-dir", figures_dir, DEFAULT_FIGURES)):
        if Path(value) != default:
            args += [flag, _portable_path(value)]
    # the variable is meant to be expanded by the reader's shell: unquote it
    return shlex.join(args).replace("'$MLFLOW_TRACKING_URI'", '"$MLFLOW_TRACKING_URI"')
