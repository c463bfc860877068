"""experiments.runtime.schedule: a unit starts only once its dataset is built, at most `workers` at once, the
costliest ready unit first; datasets are built in the background, a failure reaches the caller."""

from __future__ import annotations

import threading
from concurrent.futures import Future

import pytest

from experiments.cells import build_cells
from experiments.pack import pack_units
from experiments.runtime import schedule
from experiments.study_config import load_profile


def _units(*tasks: str):
    cells = build_cells(load_profile("quick", tasks=list(tasks), variants=["lstm", "ac-lstm"], seeds=2))
    return pack_units([(c, str(i)) for i, c in enumerate(cells)], 0)


def test_unit_cost_weighs_steps_auto_conditioned_iterations_and_packed_seeds():
    by_variant = {u[0][0].variant: u for u in _units("pick-place")}
    tf, ac = by_variant["lstm"], by_variant["ac-lstm"]
    train = ac[0][0].train
    assert train.v > 0 and tf[0][0].train.v == 0 and train.tf_warmup < train.iters
    assert schedule.unit_cost(tf, 100.0) == pytest.approx(100.0 * train.iters * 1.5)
    want = 100.0 * (train.tf_warmup + schedule.AC_ITERATION_WEIGHT * (train.iters - train.tf_warmup)) * 1.5
    assert schedule.unit_cost(ac, 100.0) == pytest.approx(want)
    assert schedule.unit_cost(ac[:1], 100.0) == pytest.approx(want / 1.5)
    assert schedule.unit_cost(tf, 200.0) == pytest.approx(2 * schedule.unit_cost(tf, 100.0))


def _done_future(value=None) -> Future:
    fut = Future()
    fut.set_result(value)
    return fut


def test_with_every_dataset_built_the_costliest_unit_goes_first_and_workers_bound_the_flight(monkeypatch):
    units = _units("reacher", "pick-place", "circle")
    steps = {"reacher": 60.0, "pick-place": 168.0, "circle": 50.0}
    monkeypatch.setattr(schedule, "_build_in_background",  # all cached: every dataset known at the first wait
                        lambda datasets: {_done_future(steps[key[0]]): key for key, _ in datasets})
    started, running, peak = [], [], [0]

    def submit(unit):
        started.append((unit[0][0].task, unit[0][0].variant))
        running.append(unit)
        peak[0] = max(peak[0], len(running))
        return Future()  # finished one at a time by finish_oldest, below

    def on_done(unit, fut):
        running.remove(unit)

    real_wait = schedule.wait

    def finish_oldest(fs, return_when):  # when nothing is done yet, the oldest running unit finishes
        if not any(f.done() for f in fs):
            fs[0].set_result(None)
        return real_wait(fs, return_when=return_when)

    monkeypatch.setattr(schedule, "wait", finish_oldest)
    schedule.run_scheduled(units, 2, submit, on_done)
    assert peak[0] == 2 and not running
    # quick: pick-place 2,000 iterations (1,500 teacher-forced), reacher 900 (a.c. from the start), circle 800
    assert started == [("pick-place", "ac-lstm"), ("pick-place", "lstm"), ("reacher", "ac-lstm"),
                       ("circle", "ac-lstm"), ("reacher", "lstm"), ("circle", "lstm")]


def test_no_unit_starts_before_its_dataset_is_built(monkeypatch):
    units = _units("reacher", "pick-place", "circle")
    gates = [threading.Event() for _ in range(3)]  # the k-th dataset built waits for gates[k]
    built: list[str] = []

    def gated_build(cell):
        assert gates[len(built)].wait(30)
        built.append(cell.task)
        return 50.0

    monkeypatch.setattr(schedule, "build_dataset", gated_build)
    gates[0].set()
    started = []

    def submit(unit):
        assert unit[0][0].task in built
        started.append(unit[0][0].task)
        gates[{1: 1, 3: 2}.get(len(started), 0)].set()  # the next dataset arrives after the 1st and 3rd starts
        return _done_future()

    schedule.run_scheduled(units, 2, submit, lambda unit, fut: None)
    assert sorted(started) == sorted(u[0][0].task for u in units) and started[:2] == [built[0]] * 2


def test_a_dataset_builder_crash_reaches_the_caller(monkeypatch):
    def broken(cell):
        raise MemoryError("out of memory in the dataset builder")

    monkeypatch.setattr(schedule, "build_dataset", broken)
    with pytest.raises(MemoryError, match="dataset builder"):
        schedule.run_scheduled(_units("circle"), 2, lambda unit: pytest.fail("nothing may start"), lambda *a: None)
