"""One torch thread per training process unless the user asks otherwise: `--threads N` or $OMP_NUM_THREADS
(experiments/runtime/processes.py); spawned workers inherit one-thread OMP/MKL/OpenBLAS variables where the user
set none."""

from __future__ import annotations

import os

import pytest

from experiments.runtime.processes import NATIVE_THREADS_ENV, set_training_threads, training_threads, worker_pool


@pytest.mark.parametrize("value,threads", [(None, 1), ("3", 3), ("4,2", 4), ("", 1), ("many", 1), ("0", 1)])
def test_training_threads_default_to_one_and_follow_the_users_variable(monkeypatch, value, threads):
    if value is None:
        monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    else:
        monkeypatch.setenv("OMP_NUM_THREADS", value)
    assert training_threads() == threads


def test_the_threads_flag_wins_over_the_variable(monkeypatch, capsys):
    from experiments.cli import main

    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    set_training_threads(None)
    assert training_threads() == 1
    set_training_threads(2)
    assert training_threads() == 2 and os.environ["OMP_NUM_THREADS"] == "2"
    assert main(["ablation", "--profile", "smoke", "--threads", "0"]) == 2
    assert capsys.readouterr().err.strip() == "error: --threads 0: expected a whole number of threads >= 1"


def _child_settings() -> tuple[dict[str, str | None], int]:
    import torch

    from experiments.runtime.processes import training_threads

    torch.set_num_threads(training_threads())  # what experiments.cell_run.setup_process does with it
    return {k: os.environ.get(k) for k in NATIVE_THREADS_ENV}, torch.get_num_threads()


@pytest.mark.slow
def test_spawned_workers_get_one_thread_and_keep_a_users_setting(monkeypatch):
    for name in NATIVE_THREADS_ENV:  # unset here; restored (or removed) after the test
        monkeypatch.setenv(name, "1")
        monkeypatch.delenv(name)
    monkeypatch.setenv("MKL_NUM_THREADS", "3")  # the user's: kept
    with worker_pool(1) as pool:
        env, torch_threads = pool.submit(_child_settings).result(timeout=300)
    assert env == {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "3", "OPENBLAS_NUM_THREADS": "1"}
    assert torch_threads == 1
