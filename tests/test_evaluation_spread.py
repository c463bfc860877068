"""experiments.runtime.spread: a cell's physics spread over the study's idle worker slots gives every per-episode
result bit for bit as played alone; the slots keep a study to its budget of busy processes; an interrupt stops the
helpers without a hang or an orphan."""

from __future__ import annotations

import os
import threading
import time

import numpy as np
import pytest

from envs.tasks import get_task
from envs.tasks.pickplace import pad_rows
from experiments.runtime import spread
from experiments.runtime.processes import worker_pool
from experiments.runtime.spread import IdleSlots, lent, lent_slots, physics_spread
from stm.rollout import Rollouts, evaluate


def _expert_rollouts(task, episodes: list, nudge: int | None = None) -> Rollouts:
    """The IK expert's paths as rollouts (with a gripper: its commands); episode `nudge` turned off its path after
    the first third, so that outcomes differ."""
    H = max(ep.horizon for ep in episodes)
    qs, grips = [], []
    for i, ep in enumerate(episodes):
        q, grip = task.expert_episode(ep)
        q = pad_rows(pad_rows(np.asarray(q, float), ep.horizon + 1), H + 1)
        if i == nudge:
            q[H // 3:, 0] += 0.05
        qs.append(q)
        grips.append(np.zeros(H + 1) if grip is None else pad_rows(np.asarray(grip, float), H + 1))
    return Rollouts(q=np.stack(qs), grip=np.stack(grips), seconds=0.0,
                    horizons=np.array([ep.horizon for ep in episodes]))


def _equal(a: list[dict], b: list[dict]) -> None:
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        assert sorted(x) == sorted(y)
        np.testing.assert_equal(x, y)  # every value bit for bit (NaN equal to NaN)


@pytest.fixture
def one_idle_slot(monkeypatch):
    """This process a worker holding its slot of a budget of two, the other idle; any trajectory worth spreading."""
    monkeypatch.setattr(spread, "MIN_SHARE_ROWS", 1)
    slots = IdleSlots(2)
    with slots.held(), lent(slots):
        yield slots


def test_spread_physics_gives_every_result_bit_for_bit(one_idle_slot, monkeypatch):
    """Pick-and-place (a fresh block scene per episode) played by a helper alone, then reacher (an arm-only scene
    reused within a process) shared between this process and the same helper: the results of stm.rollout.evaluate,
    and the borrowed slot given back."""
    pick = get_task("pick-place")
    pick_eps = pick.episodes(2, 10_000)
    pick_rollouts = _expert_rollouts(pick, pick_eps, nudge=1)
    reach = get_task("reacher")
    reach_eps = reach.episodes(4, 10_000)
    reach_rollouts = _expert_rollouts(reach, reach_eps)
    alone = evaluate(pick, pick_rollouts, pick_eps), evaluate(reach, reach_rollouts, reach_eps)
    assert {r["success"] for r in alone[0]} == {0.0, 1.0}  # the nudged episode fails

    take_share = spread.take_share
    with physics_spread() as spreading:
        monkeypatch.setattr(spread, "take_share", lambda *args: {})  # this process plays none: the helper all
        _equal(spreading.evaluate(pick, pick_rollouts, pick_eps), alone[0])
        assert spreading.helped == len(pick_eps)
        monkeypatch.setattr(spread, "take_share", take_share)
        _equal(spreading.evaluate(reach, reach_rollouts, reach_eps), alone[1])
        assert one_idle_slot.free() == 1


def test_without_lent_slots_the_physics_stays_in_this_process(monkeypatch):
    monkeypatch.setattr(spread, "MIN_SHARE_ROWS", 1)
    reach = get_task("reacher")
    episodes = reach.episodes(2, 10_000)
    rollouts = _expert_rollouts(reach, episodes)
    with lent(None), physics_spread() as spreading:
        _equal(spreading.evaluate(reach, rollouts, episodes), evaluate(reach, rollouts, episodes))
        assert spreading.helped == 0 and spreading._pool is None


def test_an_interrupt_stops_the_helpers_without_a_hang_or_an_orphan(one_idle_slot, monkeypatch):
    pick = get_task("pick-place")
    episodes = pick.episodes(3, 10_000)
    q = np.stack([np.repeat(ep.q0[None], ep.horizon + 1, axis=0) for ep in episodes])  # the arm held still
    rollouts = Rollouts(q=q, grip=np.zeros(q.shape[:2]), seconds=0.0, horizons=np.full(len(episodes), q.shape[1] - 1))
    helpers = []

    def interrupted(task, rollouts, episodes, counter, stop):
        while counter.value == 0:  # until the helper plays its first episode
            time.sleep(0.05)
        helpers.extend(spreading._pool._processes.values())
        raise KeyboardInterrupt  # (a Ctrl-C, or the worker pool's stop) in this process, mid-evaluation

    monkeypatch.setattr(spread, "take_share", interrupted)
    with pytest.raises(KeyboardInterrupt), physics_spread() as spreading:
        spreading.evaluate(pick, rollouts, episodes)
    assert len(helpers) == 1 and not helpers[0].is_alive()  # it ended its episode and was joined
    assert spreading._pool is None and one_idle_slot.free() == 1


def test_idle_slots_keep_the_budget_of_busy_processes():
    """A worker's job holds a slot; an evaluation borrows only the idle ones; a worker whose slot is lent out waits
    for it; nothing is ever more than the budget."""
    slots = IdleSlots(3)
    started, release = threading.Event(), threading.Event()

    def job() -> None:
        with slots.held():
            started.set()
            release.wait(30)

    with slots.held():  # one worker busy
        assert slots.borrow(5) == 2 and slots.free() == 0  # an evaluation takes the two idle slots
        second = threading.Thread(target=job)
        second.start()
        assert not started.wait(0.5)  # the second worker waits: its slot is lent out
        slots.give_back(1)
        assert started.wait(30) and slots.free() == 0
        release.set()
        second.join(30)
        slots.give_back(1)
        assert slots.free() == 2
    assert slots.free() == 3
    assert slots.borrow(3) == 3
    with pytest.raises(KeyboardInterrupt), slots.held(stopping=lambda: True):  # an interrupted worker stops waiting
        pass
    slots.give_back(3)
    assert slots.free() == 3


def _budget_seen_by_a_job() -> tuple[int, int, int]:
    slots = lent_slots()
    return os.getpid(), slots.total, slots.free()


def test_a_pool_worker_holds_its_slot_of_the_study_budget():
    """worker_pool(1, budget=3): the worker's job runs holding one slot, two idle ones for its evaluation."""
    with worker_pool(1, budget=3) as pool:
        pid, total, free = pool.submit(_budget_seen_by_a_job).result(timeout=300)
    assert pid != os.getpid() and (total, free) == (3, 2)
    assert pool.slots.free() == 3
