"""Commands of one study started at once settle on one parent run and one run per cell
(experiments/runtime/tracking.py get_or_create_parent_run, experiments/ablation.py prepare_runs).
MLflow stamps a run's start_time on the client before its insert commits, so a run that started
earlier can become visible later: each race below injects such a late commit while the command
waits out its settle window, on a real SQLite store. The PostgreSQL soak test met the last one
(a command deleting a run another command had created and was about to train) by chance."""

from __future__ import annotations

import time
from pathlib import Path

import pytest


@pytest.fixture
def store(tmp_path: Path):
    from experiments.runtime.tracking import Client, get_or_create_experiment

    client = Client(f"sqlite:///{tmp_path / 'mlflow.db'}")
    return client, get_or_create_experiment(client, "ablation")


def _late_commit(monkeypatch, module, create):
    """While the command under test waits out its settle window, another command's run that
    started 100 ms before the waited-for run commits; returns the ids it created."""
    real, made = module.wait_for_earlier_runs, []

    def wait(start_ms: int, window: float) -> None:
        if not made:
            made.append(create(start_ms - 100))
        real(start_ms, window)

    monkeypatch.setattr(module, "wait_for_earlier_runs", wait)
    return made


def _cells(n: int):
    from experiments.cells import build_cells
    from experiments.study_config import load_profile

    return build_cells(load_profile("smoke", seeds=n))[:n]


def test_a_parent_run_committed_late_but_started_earlier_wins_and_ours_is_deleted(store, monkeypatch):
    from experiments.runtime import tracking

    client, exp = store
    made = _late_commit(monkeypatch, tracking, lambda ms: client.create_run(
        exp, run_name="s", start_time=ms, tags={"study_name": "s", "role": "parent"}).info.run_id)
    parent = tracking.get_or_create_parent_run(client, exp, "s", {"kind": "ablation"})
    assert parent == made[0]
    parents = client.search_runs([exp], "tags.study_name = 's' and tags.role = 'parent'")
    assert [r.info.run_id for r in parents] == [parent] and parents[0].info.status == "RUNNING"
    assert parents[0].data.tags["kind"] == "ablation"
    # a second command of the study finds it and settles on it at once (its window has passed)
    began = time.monotonic()
    assert tracking.get_or_create_parent_run(client, exp, "s", {"kind": "ablation"}) == parent
    assert time.monotonic() - began < tracking.settle_window(client.uri)


def test_a_cell_run_committed_late_but_started_earlier_wins_and_ours_is_deleted(store, monkeypatch):
    from experiments import ablation
    from experiments.runtime.tracking import PARENT_TAG

    client, exp = store
    parent = client.create_run(exp).info.run_id
    cell = _cells(1)[0]
    made = _late_commit(monkeypatch, ablation, lambda ms: client.create_run(
        exp, start_time=ms, tags={PARENT_TAG: parent, "config_hash": cell.config_hash}).info.run_id)
    todo, skipped = ablation.prepare_runs(client, exp, parent, [cell])
    assert todo == [(cell, made[0])] and skipped == []
    runs = client.search_runs([exp], f"tags.config_hash = '{cell.config_hash}'")
    assert [r.info.run_id for r in runs] == [made[0]]


def test_a_command_never_deletes_a_cell_run_it_did_not_create(store):
    """Two runs of a cell (two commands created them at once): a third command settles on the
    earlier and leaves the later alone, though it is RUNNING and unclaimed -- its creator is
    about to withdraw it or to train it, and a run deleted under its trainer fails it."""
    from experiments.ablation import prepare_runs
    from experiments.runtime.tracking import PARENT_TAG

    client, exp = store
    parent = client.create_run(exp).info.run_id
    cells = _cells(2)
    earlier, later = (client.create_run(exp, start_time=int(time.time() * 1000) + dt,
                                        tags={PARENT_TAG: parent, "config_hash": cells[0].config_hash}).info.run_id
                      for dt in (0, 50))
    done = client.create_run(exp, tags={PARENT_TAG: parent, "config_hash": cells[1].config_hash}).info.run_id
    client.set_terminated(done, "FINISHED")
    todo, skipped = prepare_runs(client, exp, parent, cells)
    assert todo == [(cells[0], earlier)] and skipped == [cells[1].key]
    assert client.get_run(later).info.lifecycle_stage == "active"


def test_params_another_command_logs_at_the_same_moment_are_no_error(store, monkeypatch):
    """Workers of one study log the parent's params at once: the one whose insert meets the other's rows reads
    the run again and records only what differs (as a `changed.` tag), as the PostgreSQL soak met."""
    from mlflow.entities import Param

    from experiments.runtime.tracking import log_params

    client, exp = store
    run_id = client.create_run(exp).info.run_id
    real, raced = client._client.log_batch, []

    def log_batch(rid, params=(), **kw):
        if not raced:  # the other command's insert (its own commit) lands between our read and our write
            raced.append(real(rid, params=[Param(p.key, "other" if p.key == "git_commit" else p.value)
                                           for p in params]))
        return real(rid, params=params, **kw)

    monkeypatch.setattr(client._client, "log_batch", log_batch)
    log_params(client, run_id, {"profile": "smoke", "git_commit": "abc"})
    run = client.get_run(run_id)
    assert run.data.params == {"profile": "smoke", "git_commit": "other"}
    assert run.data.tags["changed.git_commit"] == "abc"
