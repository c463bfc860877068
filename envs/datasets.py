"""Demonstration datasets, generated once by a task's IK expert and cached on disk.

A cache entry is two files in the cache directory:
    <task>_seed<seed>.npz   the arrays of envs.tasks.Demos (q, grip, psi, lengths)
    <task>_seed<seed>.json  metadata: task, config and config hash, seed, format version,
                            counts, expert success, rejections, generation seconds, and the
                            SHA-256 of the array bytes
A task built with non-default options (e.g. Reacher(n_demos=90)) has its own entry,
<task>_seed<seed>_<config hash prefix>, beside the default one.
The JSON is written last (atomically), so a half-written entry never validates. An entry
that is corrupt, truncated, of another format version or from another task config is
reported in one warning line and rebuilt; it is never used.

Tasks evaluated with another task's model (reacher-changing-goal, stack, ...) share the
dataset of their `model_task`.
"""

from __future__ import annotations

import fcntl
import hashlib
import io
import json
import logging
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from envs.fileio import atomic_write_bytes, atomic_write_text
from envs.tasks.base import Demos, Task

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
ARRAYS = ("q", "grip", "psi", "lengths")


def default_cache_dir() -> Path:
    """ACRMDN_CACHE, else ~/.cache/acrmdn."""
    env = os.environ.get("ACRMDN_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "acrmdn"


def config_hash(config: dict[str, Any]) -> str:
    """Stable hash of a task config (JSON with sorted keys)."""
    return hashlib.sha256(json.dumps(config, sort_keys=True, default=str).encode()).hexdigest()


def arrays_hash(arrays: dict[str, np.ndarray]) -> str:
    """SHA-256 over the arrays' names, dtypes, shapes and bytes, in ARRAYS order."""
    h = hashlib.sha256()
    for name in ARRAYS:
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def cache_paths(task_name: str, seed: int, cache_dir: Path, variant: str = "") -> tuple[Path, Path]:
    """The entry's files; `variant` (a config hash prefix) names a non-default task config's own entry."""
    stem = f"{task_name}_seed{seed}" + (f"_{variant}" if variant else "")
    return cache_dir / f"{stem}.npz", cache_dir / f"{stem}.json"


def entry_paths(task: Task, seed: int, cache_dir: Path | None = None) -> tuple[Path, Path]:
    """Where load_demos(task, seed, cache_dir) keeps its entry (the model task's, for evaluation-only tasks)."""
    task = _dataset_task(task)
    cache_dir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    return cache_paths(task.name, seed, cache_dir, _variant(task, config_hash(task.config())))


def _dataset_task(task: Task) -> Task:
    """The task whose demonstrations `task` uses: itself, or its model_task for evaluation-only tasks."""
    if task.model_task and task.model_task != task.name:
        from envs.tasks.registry import task_class

        return _model_task_of(task, task_class(task.model_task))
    return task


def _variant(task: Task, chash: str) -> str:
    """"" for the task's default config, else a hash prefix: a task built with other options
    (e.g. more demos) gets its own cache entry instead of overwriting the default one."""
    try:
        default = type(task)().config()
    except TypeError:  # a task without a no-argument constructor
        return chash[:10]
    return "" if config_hash(default) == chash else chash[:10]


class _Invalid(Exception):
    """Why a cache entry cannot be used."""


def _read(npz_path: Path, meta_path: Path, task_name: str, seed: int, chash: str) -> Demos:
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, ValueError) as exc:
        raise _Invalid(f"unreadable metadata ({type(exc).__name__})") from None
    if not isinstance(meta, dict):
        raise _Invalid("metadata is not a JSON object")
    if meta.get("format_version") != FORMAT_VERSION:
        raise _Invalid(f"format version {meta.get('format_version')!r} != {FORMAT_VERSION}")
    if meta.get("task") != task_name or meta.get("seed") != seed:
        raise _Invalid(f"for task {meta.get('task')!r} seed {meta.get('seed')!r}")
    if meta.get("config_hash") != chash:
        raise _Invalid("from another task config")
    try:
        with np.load(npz_path, allow_pickle=False) as f:
            arrays = {name: f[name] for name in ARRAYS}
    except Exception as exc:  # zipfile/numpy raise many kinds for truncated or garbled files
        raise _Invalid(f"unreadable arrays ({type(exc).__name__})") from None
    if arrays_hash(arrays) != meta.get("arrays_sha256"):
        raise _Invalid("array bytes do not match their recorded hash")
    return Demos(**arrays, meta=meta)


def _generate(task: Task, seed: int, chash: str) -> tuple[Demos, dict[str, np.ndarray], dict[str, Any]]:
    t0 = time.perf_counter()
    demos = task.demos(seed)
    seconds = time.perf_counter() - t0
    arrays = {"q": demos.q.astype(np.float64), "grip": demos.grip.astype(np.float64),
              "psi": demos.psi.astype(np.float64), "lengths": demos.lengths.astype(np.int64)}
    meta = {
        "format_version": FORMAT_VERSION,
        "task": task.name,
        "seed": seed,
        "config": task.config(),
        "config_hash": chash,
        "count": len(demos),
        "lengths": {"min": int(arrays["lengths"].min()), "max": int(arrays["lengths"].max()),
                    "mean": float(arrays["lengths"].mean())},
        "state_dim": task.layout.dim,
        "state_names": task.layout.names,
        "expert_success": float(demos.meta.get("expert_success", float("nan"))),
        "rejections": demos.meta.get("rejections", {}),
        "generation_seconds": seconds,
        "created_unix": time.time(),
        "arrays_sha256": arrays_hash(arrays),
    }
    return Demos(**arrays, meta=meta), arrays, meta


def load_demos(task: Task, seed: int = 0, cache_dir: Path | None = None) -> Demos:
    """The task's demonstrations for `seed`: from the cache when valid, else generated
    (deterministically per seed), cached and returned. `Demos.meta` holds the metadata."""
    task = _dataset_task(task)
    npz_path, meta_path = entry_paths(task, seed, cache_dir)
    npz_path.parent.mkdir(parents=True, exist_ok=True)
    chash = config_hash(task.config())
    # one generator per entry at a time; other processes wait and then read its result
    with open(npz_path.with_name(f".{npz_path.stem}.lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if meta_path.exists() or npz_path.exists():
            try:
                return _read(npz_path, meta_path, task.name, seed, chash)
            except _Invalid as why:
                log.warning("dataset cache %s is invalid (%s); rebuilding it", npz_path, why)
        demos, arrays, meta = _generate(task, seed, chash)
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        meta_path.unlink(missing_ok=True)  # the entry is invalid until both files are written
        atomic_write_bytes(npz_path, buf.getvalue())
        atomic_write_text(meta_path, json.dumps(meta, indent=1, default=str))
        log.info("generated %d %s demos in %.1f s -> %s", len(demos), task.name, meta["generation_seconds"], npz_path)
        return demos


def _model_task_of(task: Task, cls: type[Task]) -> Task:
    """The training task (class `cls`) behind an evaluation-only task, with the same settings
    where it is a subclass of it (e.g. reacher-changing-goal -> reacher)."""
    if isinstance(task, cls):
        twin = cls.__new__(cls)
        twin.__dict__.update(task.__dict__)
        return twin
    return cls()
