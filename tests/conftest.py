"""Isolation for every test, and the stores that several test modules share.

- The session gets its own home directory (HOME, XDG dirs, matplotlib's config): no test reads
  or writes the user's home, and nothing there (a dataset cache, an MLflow store) leaks in.
- Every test runs in its own working directory (so the default stores, mlflow.db, optuna.journal,
  queue.db and reports/out land there) with its own dataset cache (ACRMDN_CACHE) and a clean
  environment for the subprocesses it starts: no MLFLOW_*/OPTUNA_*/ACRMDN_* from the caller,
  PYTHONPATH = this checkout.
- A test's dataset cache starts as a copy of the session's pool of valid entries, and entries it
  generates (validated) go back to the pool: each demonstration set is generated about once per
  session (reacher's takes ~10 CPU-s), while no test sees another test's writes or damage.
- `smoke_store`: one smoke ablation (`python -m experiments ablation --profile smoke`) built once
  per test run through the CLI (under pytest-xdist: by the first worker that needs it, the others wait
  on a file lock), for the tests that read a real study's store.
- `results_store`: a smoke ablation (2 rollouts) and a 2-trial smoke sweep in one store, built once per
  test run likewise, for the RESULTS.md and study export tests (read only).
- The C++ step kernel (stm.cpp_ext) is built once per test run, into the session's folder that the xdist workers
  share (TORCH_EXTENSIONS_DIR; torch's file lock makes the others wait for the first build): in each worker's
  throwaway home it was built once per worker (~100 CPU-s each). A TORCH_EXTENSIONS_DIR set by the caller is kept.
- One intra-op thread per test process and per subprocess (OMP_NUM_THREADS=1), as the CLI gives each
  worker: pytest-xdist runs a process per core, and two threads each on busy cores spin at barriers
  (a smoke cell measured 68 s with 2 threads on a loaded 2-core machine, 24 s with 1).
- Hypothesis: a derandomized profile without a database when CI is set.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import sys
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import run_cli

REPO = Path(__file__).resolve().parents[1]
SCRUBBED_PREFIXES = ("MLFLOW_", "OPTUNA_", "ACRMDN_")

try:  # hypothesis: reproducible in CI (same examples every run, no example database)
    from hypothesis import settings

    settings.register_profile("ci", derandomize=True, database=None, print_blob=True)
    settings.register_profile("dev", print_blob=True)
    settings.load_profile("ci" if os.environ.get("CI") else os.environ.get("HYPOTHESIS_PROFILE", "dev"))
except ImportError:  # hypothesis is a dev extra; its tests skip themselves without it
    pass

_SESSION: dict = {}
ROOT_KEY = "acrmdn_session_root"


def pytest_configure(config: pytest.Config) -> None:
    """A throwaway home and dataset pool for the whole session, set before any test module (or
    matplotlib) is imported, so session- and module-scoped fixtures are isolated too. Under
    pytest-xdist the workers share the controller's pool (each dataset generated once per run)
    and have a home each."""
    shared = getattr(config, "workerinput", {}).get(ROOT_KEY)  # an xdist worker: the controller's root
    root = Path(shared) if shared else Path(tempfile.mkdtemp(prefix="acrmdn-tests-"))
    home, pool = root / f"home-{os.environ.get('PYTEST_XDIST_WORKER', 'main')}", root / "dataset-pool"
    for d in (home / ".cache", home / ".config" / "matplotlib", pool):
        d.mkdir(parents=True, exist_ok=True)
    _SESSION.update(root=root, home=home, pool=pool, owner=not shared)
    for key in [k for k in os.environ if k.startswith(SCRUBBED_PREFIXES)]:
        del os.environ[key]
    os.environ.update({"HOME": str(home), "XDG_CACHE_HOME": str(home / ".cache"),
                       "XDG_CONFIG_HOME": str(home / ".config"), "MPLCONFIGDIR": str(home / ".config" / "matplotlib"),
                       "ACRMDN_CACHE": str(pool), "PYTHONPATH": str(REPO), "MPLBACKEND": "Agg",
                       "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "ACRMDN_WORKERS": "1"})  # see `isolated`
    os.environ.setdefault("TORCH_EXTENSIONS_DIR", str(root / "torch-extensions"))
    if "torch" in sys.modules:  # imported before this hook (by a plugin): the variable came too late
        sys.modules["torch"].set_num_threads(1)


@pytest.hookimpl(optionalhook=True)
def pytest_configure_node(node) -> None:
    """pytest-xdist (controller): hand the session's root to each worker it starts."""
    node.workerinput[ROOT_KEY] = str(_SESSION["root"])


def pytest_unconfigure(config: pytest.Config) -> None:
    if _SESSION.get("owner"):
        shutil.rmtree(_SESSION["root"], ignore_errors=True)


def _entries(cache: Path) -> dict[str, tuple[Path, Path]]:
    """Complete cache entries (npz + json) by stem."""
    return {j.stem: (j.with_suffix(".npz"), j) for j in cache.glob("*.json") if j.with_suffix(".npz").exists()}


def _valid(npz: Path, meta_path: Path) -> bool:
    """The entry's arrays match their recorded hash and its config its recorded config hash."""
    from envs.datasets import ARRAYS, arrays_hash, config_hash

    try:
        meta = json.loads(meta_path.read_text())
        with np.load(npz, allow_pickle=False) as f:
            arrays = {name: f[name] for name in ARRAYS}
        return arrays_hash(arrays) == meta["arrays_sha256"] and config_hash(meta["config"]) == meta["config_hash"]
    except Exception:  # any damage (a test may corrupt its copy on purpose): not for the pool
        return False


def _forget_mlflow_stores() -> None:
    """MLflow caches one store per URI string in this process; a relative URI (sqlite:///mlflow.db) would
    otherwise keep reaching the first test's working directory from every later in-process test. No public
    API clears it: the cache of its store registry (absent in another MLflow version: nothing to clear)."""
    from mlflow.tracking._tracking_service import utils

    get_store = getattr(type(utils._tracking_store_registry), "_get_store_with_resolved_uri", None)
    if hasattr(get_store, "cache_clear"):
        get_store.cache_clear()


@pytest.fixture(autouse=True)
def isolated(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch):
    """Own working directory, dataset cache and store; clean environment for subprocesses.
    Beside the test's tmp_path, not in it: a test may check that nothing was written there."""
    pool = _SESSION["pool"]
    root = tmp_path_factory.mktemp("isolated")
    cache, work = root / "acrmdn-cache", root / "work"
    cache.mkdir()
    work.mkdir()
    for npz, meta in _entries(pool).values():
        shutil.copy2(npz, cache)
        shutil.copy2(meta, cache)
    for key in [k for k in os.environ if k.startswith(SCRUBBED_PREFIXES)]:
        monkeypatch.delenv(key)
    monkeypatch.setenv("ACRMDN_CACHE", str(cache))
    # studies and sweeps run in-process unless a test asks for --workers: a spawned worker pays ~3-4 CPU-s
    # of imports (torch, mlflow, pybullet; more under coverage), and the xdist workers already use the cores
    monkeypatch.setenv("ACRMDN_WORKERS", "1")
    monkeypatch.setenv("PYTHONPATH", str(REPO))
    monkeypatch.chdir(work)  # the default stores (sqlite:///mlflow.db, optuna.journal) are the test's own
    _forget_mlflow_stores()
    yield work
    _forget_mlflow_stores()
    known = _entries(pool)
    for stem, (npz, meta) in _entries(cache).items():
        if stem not in known and _valid(npz, meta):
            for path in (npz, meta):  # the json last: a half-copied entry is incomplete
                tmp = pool / f".{path.name}.{os.getpid()}.tmp"  # xdist workers may return the same entry at once
                shutil.copy2(path, tmp)
                os.replace(tmp, pool / path.name)


@pytest.fixture
def sigint_raises() -> Iterator[None]:
    """SIGINT raises KeyboardInterrupt in this process, as in a terminal: a test run started in the background
    (`cmd &`, as CI runners may) inherits SIGINT ignored, and an in-process Ctrl-C test would see nothing."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def _built_once(name: str, build) -> tuple[Path, str]:
    """A folder `build(folder) -> text` fills, built once per test run: under pytest-xdist the first
    worker that needs it builds it in the session's shared root while the others wait on a file lock
    (a failed build is retried by the next worker that needs it). Returns the folder and the text."""
    from filelock import FileLock

    root = _SESSION["root"]
    folder, done = root / name, root / f"{name}.built"
    with FileLock(str(root / f"{name}.lock")):
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            text = build(folder)
            done.write_text(text)
    return folder, done.read_text()


def _cli_output(store: Path, *args: str, timeout: int = 900) -> str:
    """`python -m experiments ARGS` on the store in `store` (cli_helpers.run_cli), which must succeed: its output."""
    proc = run_cli(list(args), store, timeout=timeout)
    assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
    return proc.stdout


@dataclass(frozen=True)
class SmokeStore:
    """A finished smoke ablation: its folder (mlflow.db inside), tracking URI and CLI output."""

    path: Path
    uri: str
    stdout: str


@pytest.fixture(scope="session")
def smoke_store() -> SmokeStore:
    """`python -m experiments ablation --profile smoke --workers 2`, built once per test run (shared by
    the xdist workers). Shared: tests may add to it (a re-run, a report logged to the parent run),
    never remove."""
    path, stdout = _built_once("smoke-store", lambda store: _cli_output(store, "ablation", "--profile", "smoke",
                                                                        "--workers", "2"))
    return SmokeStore(path, f"sqlite:///{path / 'mlflow.db'}", stdout)


@pytest.fixture(scope="session")
def results_store() -> Path:
    """A folder whose mlflow.db holds a smoke ablation and a smoke sweep of reacher (built through the CLI, once per
    test run; in a process of its own: a sweep run in the test's process leaves state behind that changes the
    figures the report tests compare with a report rendered in another process); read only."""

    def build(store: Path) -> str:
        return _cli_output(store, "ablation", "--profile", "smoke", "--workers", "1", "--set", "eval.rollouts=2") + \
            _cli_output(store, "sweep", "--profile", "smoke", "--workers", "1", "--trials", "2", "--set",
                        "train.val_every=2", timeout=600)

    return _built_once("results-store", build)[0]
