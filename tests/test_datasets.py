"""Dataset cache: reuse, determinism, detection of corrupt/truncated/stale entries, rejections."""

from __future__ import annotations

import json
import logging
import shutil

import numpy as np
import pytest

from envs import datasets
from envs.datasets import cache_paths, entry_paths, load_demos
from envs.tasks import get_task
from envs.tasks.reacher import Reacher


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("ACRMDN_CACHE", str(tmp_path / "cache"))
    return tmp_path / "cache"


@pytest.fixture
def small():
    return get_task("reacher", n_demos=3)


@pytest.fixture(scope="module")
def good_entry(tmp_path_factory):
    """A valid cache entry (reacher, 3 demos, seed 1), generated once for the damage tests."""
    d = tmp_path_factory.mktemp("good")
    demos = load_demos(get_task("reacher", n_demos=3), seed=1, cache_dir=d)
    return demos, entry_paths(get_task("reacher", n_demos=3), 1, d)


def _warnings(caplog):
    return [r for r in caplog.records if r.levelno == logging.WARNING and r.name == "envs.datasets"]


def test_generated_once_then_read_from_the_env_var_cache(cache, small, monkeypatch):
    first = load_demos(small, seed=0)
    npz, meta_path = entry_paths(small, 0, cache)
    assert npz.exists() and meta_path.exists()
    meta = json.loads(meta_path.read_text())
    for key in ("task", "config_hash", "seed", "format_version", "count", "expert_success", "rejections",
                "generation_seconds", "arrays_sha256", "lengths"):
        assert key in meta
    assert meta["count"] == 3 and meta["expert_success"] == 1.0 and meta["task"] == "reacher"

    def boom(self, seed=0):
        raise AssertionError("regenerated although the cache is valid")

    monkeypatch.setattr(Reacher, "demos", boom)
    again = load_demos(small, seed=0)
    for name in ("q", "grip", "psi", "lengths"):
        assert np.array_equal(getattr(first, name), getattr(again, name))
    assert again.meta["config_hash"] == meta["config_hash"]


def test_a_fresh_cache_reproduces_the_same_arrays(tmp_path, small):
    a = load_demos(small, seed=4, cache_dir=tmp_path / "a")
    b = load_demos(small, seed=4, cache_dir=tmp_path / "b")
    assert np.array_equal(a.q, b.q) and np.array_equal(a.psi, b.psi)
    assert a.meta["arrays_sha256"] == b.meta["arrays_sha256"]


def _corrupt_garbage(npz, meta):
    npz.write_bytes(b"not a zip file at all")


def _truncate(npz, meta):
    data = npz.read_bytes()
    npz.write_bytes(data[: len(data) // 2])


def _tamper_arrays(npz, meta):
    with np.load(npz) as f:
        arrays = {k: f[k] for k in f.files}
    arrays["q"][0, 5, 2] += 1e-3  # a valid file whose bytes no longer match the recorded hash
    np.savez(npz, **arrays)


def _garble_metadata(npz, meta):
    meta.write_text("{ truncated")


def _old_format(npz, meta):
    m = json.loads(meta.read_text())
    m["format_version"] = 0
    meta.write_text(json.dumps(m))


def _missing_arrays(npz, meta):
    npz.unlink()


@pytest.mark.slow
@pytest.mark.parametrize("damage", [_corrupt_garbage, _truncate, _tamper_arrays, _garble_metadata,
                                    _old_format, _missing_arrays])
def test_damaged_cache_is_reported_once_and_rebuilt(cache, small, caplog, damage, good_entry):
    good, sources = good_entry
    cache.mkdir(parents=True)
    npz, meta = entry_paths(small, 1, cache)
    for src, dst in zip(sources, (npz, meta), strict=True):
        shutil.copy(src, dst)
    damage(npz, meta)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="envs.datasets"):
        rebuilt = load_demos(small, seed=1)
    warns = _warnings(caplog)
    assert len(warns) == 1 and "\n" not in warns[0].getMessage()
    assert "rebuilding" in warns[0].getMessage()
    assert np.array_equal(rebuilt.q, good.q)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="envs.datasets"):
        load_demos(small, seed=1)  # the rebuilt entry is valid again
    assert not _warnings(caplog)


@pytest.mark.slow
def test_cache_from_another_config_is_not_used(cache, small, caplog, monkeypatch):
    """An entry written under other defaults (same file name, other config hash) is rebuilt."""
    import envs.datasets

    monkeypatch.setattr(envs.datasets, "_variant", lambda task, chash: "")  # both count as the default config
    load_demos(small, seed=0)
    other = get_task("reacher", n_demos=4)
    with caplog.at_level(logging.WARNING, logger="envs.datasets"):
        d = load_demos(other, seed=0)
    assert len(d) == 4 and d.meta["count"] == 4
    warns = _warnings(caplog)
    assert len(warns) == 1 and "another task config" in warns[0].getMessage()


def test_failed_samples_are_resampled_and_counted(cache, small, monkeypatch):
    real = Reacher.final_distance
    calls = {"n": 0}

    def flaky(self, q, goal):  # the first two physics replays "fail"
        calls["n"] += 1
        return 1.0 if calls["n"] <= 2 else real(self, q, goal)

    monkeypatch.setattr(Reacher, "final_distance", flaky)
    d = load_demos(small, seed=2)
    assert len(d) == 3 and d.meta["rejections"]["physics"] == 2 and d.meta["expert_success"] == 1.0
    saved = json.loads(entry_paths(small, 2, cache)[1].read_text())
    assert saved["rejections"]["physics"] == 2


def test_changing_goal_task_shares_the_reacher_dataset(cache, small):
    base = load_demos(small, seed=0)
    twin = load_demos(get_task("reacher-changing-goal", n_demos=3), seed=0)
    assert np.array_equal(base.q, twin.q)
    assert not cache_paths("reacher-changing-goal", 0, cache)[0].exists()


def test_default_cache_dir(monkeypatch, tmp_path):
    monkeypatch.setenv("ACRMDN_CACHE", str(tmp_path))
    assert datasets.default_cache_dir() == tmp_path
    monkeypatch.delenv("ACRMDN_CACHE")
    assert datasets.default_cache_dir().name == "acrmdn"


@pytest.mark.slow
def test_non_default_task_config_has_its_own_entry(tmp_path):
    """A task built with other options gets its own cache entry: the default one is not overwritten."""
    from envs.tasks.reacher import Reacher

    default = load_demos(Reacher(n_demos=3), seed=0, cache_dir=tmp_path)
    more = load_demos(Reacher(n_demos=4), seed=0, cache_dir=tmp_path)
    assert len(default) == 3 and len(more) == 4
    entries = sorted(p.name for p in tmp_path.glob("reacher_seed0*.npz"))
    assert len(entries) == 2, entries
    assert len(load_demos(Reacher(n_demos=3), seed=0, cache_dir=tmp_path)) == 3  # still cached, not rebuilt


def test_atomic_write_replaces_whole_files_and_a_failed_write_leaves_the_old_one(tmp_path):
    from envs.fileio import atomic_open, atomic_write_bytes, atomic_write_text

    target = tmp_path / "sub" / "f.bin"
    atomic_write_bytes(target, b"old")
    with pytest.raises(RuntimeError, match="killed"):
        with atomic_open(target, "wb") as f:
            f.write(b"half of the new")
            raise RuntimeError("killed mid-write")
    assert target.read_bytes() == b"old"
    assert sorted(p.name for p in target.parent.iterdir()) == ["f.bin"]  # no temporary file left
    atomic_write_text(target, "new")
    assert target.read_text() == "new"
    with pytest.raises(ValueError, match="mode"):
        with atomic_open(target, "ab"):
            pass
