"""`python -m experiments.sweeps.dashboard` (`nox -s dashboard`): optuna-dashboard over the sweep
storage, printing its link and the studies in it first.

The storage is the one `python -m experiments sweep` writes: by default the journal file next
to the MLflow store (mlflow.db, or the working directory for a tracking server); `--storage`
takes an RDB URL (postgresql://..., sqlite:///...) or `journal:PATH`. Exit 2 with one line
when there is nothing to open (no journal file yet) or the storage does not answer.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from experiments.runtime.optuna_storage import JOURNAL_NAME, JOURNAL_PREFIX, open_storage, storage_spec
from experiments.runtime.tracking import tracking_uri


def default_storage() -> str:
    return storage_spec(None, tracking_uri())  # the sweeps' default: the journal next to the MLflow store


def open_existing(spec: str):
    """The Optuna storage named by spec; a journal file must exist already (the dashboard
    only reads sweeps: an empty new file would show nothing and hide a wrong folder)."""
    if spec.startswith(JOURNAL_PREFIX):
        path = Path(spec.removeprefix(JOURNAL_PREFIX))
        if not path.is_file():
            raise FileNotFoundError(f"no sweep storage at {path}; run `nox -s sweep` first or pass --storage URL")
    return open_storage(spec)


def study_lines(storage) -> list[str]:
    import optuna

    summaries = optuna.get_all_study_summaries(storage, include_best_trial=False)
    return [f"{s.study_name}: {s.n_trials} trial(s)" for s in summaries] or ["no studies yet"]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.sweeps.dashboard", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--storage", default=None,
                   help=f"Optuna storage URL or journal:PATH (default: {JOURNAL_NAME} next to mlflow.db)")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8080)
    args = p.parse_args(argv)
    spec = args.storage or default_storage()
    try:
        storage = open_existing(spec)
        studies = study_lines(storage)
    except Exception as exc:  # a missing file, a bad URL, a server that does not answer
        print(f"error: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}", file=sys.stderr)
        return 2
    print(f"optuna-dashboard over {spec}")
    for line in studies:
        print(f"  {line}")
    print(f"  http://{args.host}:{args.port}/dashboard  (Ctrl-C stops it)", flush=True)
    from optuna_dashboard import run_server

    try:
        run_server(storage, host=args.host, port=args.port)
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
