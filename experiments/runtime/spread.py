"""Idle worker capacity lent to a cell's evaluation physics.

A study or sweep with `--workers W` keeps at most W processes busy: its workers share W slots (IdleSlots), and a
worker holds one while it runs a job (experiments/runtime/processes.py). Near the end of a study, or with fewer
jobs than W, slots sit idle while one cell evaluates alone. That cell borrows them for its physics: a task's
episodes are played by the cell's process and by as many helper processes as it borrowed, each taking the next
episode from a shared counter, and the slots go back when the task's physics is done (a worker that wants its slot
back meanwhile waits for that). Without slots lent to this process (`--workers 1`, the test suite's in-process
runs) the physics runs here alone, as stm.rollout.evaluate.

Every episode is played as stm.rollout.evaluate plays it, and episodes are independent (each builds its own block
scene, or replays in an arm-only scene that carries nothing from one episode to the next), so a spread evaluation
gives every per-episode result bit for bit (tests/test_evaluation_spread.py).

Helpers are spawned once per evaluated model, when a task first borrows, and reused by its next tasks. They ignore
SIGINT and die with the cell's process (PR_SET_PDEATHSIG, else at its next episode): an interrupted cell sets the
stop flag, each helper ends the episode it is playing, and the cell's process waits for them before it goes on.
"""

from __future__ import annotations

import contextlib
import dataclasses
import multiprocessing as mp
import os
import signal
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from typing import Any

# trajectory rows each process plays at least (~4 CPU-s of pick-and-place physics): a helper first pays ~3-4 CPU-s
# of imports (torch, pybullet), so a smoke evaluation or a reacher task stays in one process
MIN_SHARE_ROWS = 1500
WAIT_POLL = 0.1  # seconds between looks for a slot given back

_lent: IdleSlots | None = None  # this process's study slots (lend)


class IdleSlots:
    """A budget of W busy processes shared by a study's processes (a counter in shared memory): a worker holds one
    slot while it runs a job (`held`), an evaluating cell borrows the idle ones (`borrow`) and gives them back."""

    def __init__(self, total: int, ctx=None):
        if total < 1:
            raise ValueError(f"a budget of busy processes needs at least 1 slot, got {total}")
        self.total = total
        self._free = (ctx or mp.get_context("spawn")).Value("i", total)

    def free(self) -> int:
        return self._free.value

    def borrow(self, most: int) -> int:
        """Up to `most` idle slots, at once (none when none is idle); how many were taken."""
        with self._free.get_lock():
            n = max(0, min(most, self._free.value))
            self._free.value -= n
        return n

    def give_back(self, n: int) -> None:
        with self._free.get_lock():
            self._free.value += n

    @contextlib.contextmanager
    def held(self, stopping: Callable[[], bool] = lambda: False) -> Iterator[None]:
        """One slot for the duration (a worker's job), waiting while borrowed ones are out; KeyboardInterrupt
        when `stopping()` turns true meanwhile."""
        while not self.borrow(1):
            if stopping():
                raise KeyboardInterrupt
            time.sleep(WAIT_POLL)
        try:
            yield
        finally:
            self.give_back(1)


def lent_slots() -> IdleSlots | None:
    return _lent


def lend(slots: IdleSlots | None) -> None:
    """Make `slots` the ones this process's evaluations borrow from (None: evaluate alone)."""
    global _lent
    _lent = slots


@contextlib.contextmanager
def lent(slots: IdleSlots | None) -> Iterator[None]:
    """lend(slots) for the duration, then what was lent before."""
    before = _lent
    lend(slots)
    try:
        yield
    finally:
        lend(before)


@contextlib.contextmanager
def physics_spread() -> Iterator[Spread]:
    """One evaluated model's physics, spread over the slots lent to this process; its helpers end with it."""
    spread = Spread(_lent)
    try:
        yield spread
    finally:
        spread.close()


class Spread:
    """Plays tasks' episodes (evaluate) here and in helpers on borrowed slots; `helped` counts the episodes the
    helpers played."""

    def __init__(self, slots: IdleSlots | None):
        self.slots = slots
        self.helped = 0
        self._pool: ProcessPoolExecutor | None = None
        self._next = self._stop = None

    def evaluate(self, task, rollouts, episodes: list) -> list[dict[str, Any]]:
        """stm.rollout.evaluate(task, rollouts, episodes), its episodes spread over the idle slots."""
        from stm.rollout import evaluate

        rows = int(sum(int(h) + 1 for h in rollouts.horizons))
        want = min(len(episodes), rows // MIN_SHARE_ROWS) - 1
        helpers = self.slots.borrow(want) if self.slots is not None and want > 0 else 0
        if not helpers:
            return evaluate(task, rollouts, episodes)
        try:
            return self._spread(task, dataclasses.replace(rollouts, components=None), episodes, helpers)
        finally:
            self.slots.give_back(helpers)

    def _spread(self, task, rollouts, episodes: list, helpers: int) -> list[dict[str, Any]]:
        if self._pool is None:
            ctx = mp.get_context("spawn")
            self._next, self._stop = ctx.Value("i", 0), ctx.Event()
            self._pool = ProcessPoolExecutor(self.slots.total, mp_context=ctx, initializer=_init_helper,
                                             initargs=(os.getpid(), self._next, self._stop))
        self._next.value = 0  # the last task's helpers have all returned
        futures = [self._pool.submit(_helper_share, task, rollouts, episodes) for _ in range(helpers)]
        try:
            results = take_share(task, rollouts, episodes, self._next, self._stop)  # this process plays too
            for fut in futures:
                theirs = fut.result()
                self.helped += len(theirs)
                results.update(theirs)
        except BaseException:
            self._stop.set()  # (an interrupt, or a failed episode) each helper ends the episode it is playing
            self.close()
            raise
        return [results[i] for i in range(len(episodes))]

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


def take_share(task, rollouts, episodes: list, counter, stop, parent: int | None = None) -> dict[int, dict[str, Any]]:
    """Play the next unplayed episode until none is left (or `stop` is set): {episode index: its results}, each as
    stm.rollout.evaluate plays it. parent: exit when it is no longer this process's parent."""
    from stm.rollout import evaluate

    out: dict[int, dict[str, Any]] = {}
    while not stop.is_set():
        if parent is not None and os.getppid() != parent:
            os._exit(1)
        with counter.get_lock():
            i = counter.value
            counter.value = i + 1
        if i >= len(episodes):
            break
        one = dataclasses.replace(rollouts, q=rollouts.q[i: i + 1], grip=rollouts.grip[i: i + 1],
                                  horizons=rollouts.horizons[i: i + 1])
        out[i] = evaluate(task, one, [episodes[i]])[0]
    return out


_helper: tuple[int, Any, Any] | None = None  # a helper's (parent, counter, stop)


def _init_helper(parent: int, counter, stop) -> None:
    from experiments.runtime.processes import die_with_parent, training_threads

    global _helper
    die_with_parent()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the cell's process handles a Ctrl-C and stops its helpers
    if os.getppid() != parent:
        os._exit(1)
    import torch

    torch.set_num_threads(training_threads())  # as the cell's process (a stacking restart's IK uses torch)
    _helper = (parent, counter, stop)


def _helper_share(task, rollouts, episodes: list) -> dict[int, dict[str, Any]]:
    parent, counter, stop = _helper
    return take_share(task, rollouts, episodes, counter, stop, parent)
