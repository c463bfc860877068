"""A stop reaches every worker of a pool, and none cuts another's checkpoint short: an idle worker that exited on
Ctrl-C used to break the pool, and a broken pool terminates the busy workers however far their checkpoint had got."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest

from experiments.runtime.processes import worker_pool


def slow_to_stop(marks: str) -> str:
    """A busy worker's cell: says it is running, and on Ctrl-C takes a while to record it (a checkpoint of several
    MB into a store other workers write to), then says it has."""
    Path(marks, "running").touch()
    try:
        while True:
            time.sleep(0.05)
    except KeyboardInterrupt:
        time.sleep(1.5)
        Path(marks, "recorded").touch()
        raise


def test_ctrl_c_leaves_a_busy_worker_its_checkpoint_while_another_idles(tmp_path):
    with pytest.raises(KeyboardInterrupt):
        with worker_pool(2) as pool:
            future = pool.submit(slow_to_stop, str(tmp_path))
            assert pool.submit(os.getpid).result(timeout=60) > 0  # a second worker, idle from now on
            deadline = time.monotonic() + 60
            while not (tmp_path / "running").exists():
                assert time.monotonic() < deadline, "the worker never started"
                time.sleep(0.05)
            workers = list(pool.executor._processes)
            assert len(workers) == 2  # one busy, one idle
            for pid in workers:  # what Ctrl-C in a terminal does to them (this process is spared)
                os.kill(pid, signal.SIGINT)
            future.result(timeout=60)  # the cell's interruption, recorded, reaches the main process
    assert (tmp_path / "recorded").exists()
