"""Worker processes of a study or sweep: spawned (fresh interpreters: no forked torch, pybullet
or SQLite state), and stopped with their main process.

- Threads: one per training process unless the user asks otherwise (`--threads N` or
  $OMP_NUM_THREADS): training_threads() for torch in each worker, and OMP/MKL/OpenBLAS variables
  the spawned interpreters inherit, set where the user left them unset. The models are small, so
  intra-op threads mostly spin at barriers; parallelism comes from the worker processes.

- Parent death: on Linux the kernel kills each worker the moment its main process dies (kill -9,
  OOM killer; PR_SET_PDEATHSIG), however loaded the machine; elsewhere, and as a fallback, each
  worker watches its main process and exits within a second or so of its death instead of
  training on alone. Its run stays RUNNING with its
  last checkpoint artifact, so a re-run resumes it (and claims it at once: experiments/runtime/claims.py
  sees that its holder is gone).
- Stop (Ctrl-C in the main process): `stop` is set; a busy worker is interrupted (a training
  cell finishes its step and checkpoints there: stm/training/interrupts.py; the cell is marked KILLED,
  resumable), an idle one starts nothing more. No worker exits on its own: one that died would break the
  pool, and a broken pool terminates the others mid-checkpoint; the main process waits for them all, and
  its pool's shutdown ends them. Ctrl-C in a terminal reaches the workers too: a worker acts on the
  first interrupt only, so the second (the main process's) cannot cut its checkpoint short. A worker
  still busy GRACE seconds after the stop exits anyway.
- Busy processes: a pool's workers share `budget` slots (IdleSlots; the study's --workers, at least the pool's size)
  and each holds one while it runs a job; a cell evaluating meanwhile borrows the idle ones for its physics
  (experiments/runtime/spread.py), so that no more than `budget` processes are busy at once.
"""

from __future__ import annotations

import _thread
import contextlib
import ctypes
import multiprocessing as mp
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor

from experiments.config_errors import ConfigError
from experiments.runtime.spread import IdleSlots, lend, lent_slots

# seconds an interrupted worker gets to checkpoint its cells and mark its runs before it exits anyway: a
# pick-and-place pack stores a checkpoint of several MB per seed, on a store other workers write to as well
GRACE = 120.0
POLL = 0.5
_busy = threading.Event()
_stopping = threading.Event()  # this worker has been interrupted once and is on its way out
WORKERS_ENV = "ACRMDN_WORKERS"
PR_SET_PDEATHSIG, PR_GET_PDEATHSIG = 1, 2  # linux/prctl.h
THREADS_ENV = "OMP_NUM_THREADS"
NATIVE_THREADS_ENV = (THREADS_ENV, "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")  # read by the libraries as they load


def default_workers() -> int:
    """$ACRMDN_WORKERS (a shared machine's share, or 1 in the test suite: in-process, no spawned
    interpreters), else one per core this process may use."""
    raw = os.environ.get(WORKERS_ENV, "").strip()
    if raw:
        if not raw.isdigit() or int(raw) < 1:
            raise ConfigError(f"{WORKERS_ENV}={raw!r}: expected a whole number of worker processes >= 1")
        return int(raw)
    return usable_cores()


def usable_cores() -> int:
    """The cores this process may run on (its affinity where the platform tells it)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def training_threads() -> int:
    """Torch threads per training process: $OMP_NUM_THREADS (its first level) where set, else 1: the models are
    small, so a second thread mostly waits at barriers, and two 1-thread processes train several times faster."""
    first = os.environ.get(THREADS_ENV, "").split(",")[0].strip()
    return int(first) if first.isdigit() and int(first) > 0 else 1


def add_threads_option(parser) -> None:
    parser.add_argument("--threads", type=int, default=None, help="torch threads per training process "
                        f"(default: ${THREADS_ENV}, else 1; more cores train with more --workers)")


def add_device_option(parser, what: str = "train") -> None:
    parser.add_argument("--device", default=None, metavar="DEVICE",
                        help=f"where models {what}: auto (cuda if torch sees a GPU, else cpu), cpu (default), cuda or "
                             "cuda:N; rollouts' physics stays on the CPU")


def checked_device(device: str | None) -> str | None:
    """--device resolved here, before anything is written: ConfigError (one line) for a bad or missing device."""
    if device is None:
        return None
    from stm.device import DeviceError, resolve_device

    try:
        resolve_device(device)
    except DeviceError as e:
        raise ConfigError(f"--device: {e}") from None
    return device


def set_training_threads(threads: int | None) -> None:
    """The user's `--threads N` (None: keep $OMP_NUM_THREADS or the default), for this process and its workers."""
    if threads is not None:
        if threads < 1:
            raise ConfigError(f"--threads {threads}: expected a whole number of threads >= 1")
        os.environ[THREADS_ENV] = str(threads)


def _child_thread_env() -> None:
    """What spawned workers inherit: training_threads() for each native library whose variable is unset."""
    for name in NATIVE_THREADS_ENV:
        os.environ.setdefault(name, str(training_threads()))


def _on_sigint(signum, frame) -> None:
    if _stopping.is_set():
        return  # interrupted already: the cell is checkpointing, and a second interrupt would cut that short
    _stopping.set()
    if _busy.is_set():
        raise KeyboardInterrupt  # the running cell or trial records the interruption
    # idle: stay, and start nothing more (_call); the pool's shutdown ends this process. Exiting here would break
    # the pool, and a broken pool terminates every other worker, however far its checkpoint has got


def _watch(parent: int, stop) -> None:
    stopped = False
    while True:
        if os.getppid() != parent:  # reparented: the main process is gone
            os._exit(1)
        if stop.is_set() and not stopped:
            stopped = True
            if _busy.is_set() and not _stopping.is_set():
                _thread.interrupt_main()  # runs _on_sigint in the main thread (which marks the worker stopping)
            else:
                _stopping.set()
            deadline = time.monotonic() + GRACE
            while _busy.is_set() and time.monotonic() < deadline:  # _call returns once the cell has recorded it
                time.sleep(POLL)
            if _busy.is_set():  # stuck past the grace period: leave anyway
                os._exit(130)
        time.sleep(POLL)


def die_with_parent() -> int:
    """Ask the kernel to SIGKILL this process when its parent dies (Linux; a no-op elsewhere): a polling
    thread may wake seconds late on a loaded machine. The signal it will get, or 0 where unsupported."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL) != 0:
            return 0
        got = ctypes.c_int(0)
        libc.prctl(PR_GET_PDEATHSIG, ctypes.byref(got))
        return got.value
    except (OSError, AttributeError):  # no libc prctl (not Linux)
        return 0


def _init(parent: int, stop, slots: IdleSlots | None = None) -> None:
    die_with_parent()
    if os.getppid() != parent:  # the main process died before the kernel was told
        os._exit(1)
    signal.signal(signal.SIGINT, _on_sigint)
    lend(slots)
    threading.Thread(target=_watch, args=(parent, stop), name="parent-watch", daemon=True).start()


def _call(fn: Callable, *args):
    """fn(*args) in a worker; once the worker has been interrupted, nothing more starts. An interruption reaches
    the main process as the future's KeyboardInterrupt (fn has recorded it), the worker staying alive: the pool
    stays whole, so the other workers finish their checkpoints (see the module docstring)."""
    if _stopping.is_set():
        raise KeyboardInterrupt
    slots = lent_slots()
    with slots.held(_stopping.is_set) if slots is not None else contextlib.nullcontext():  # this worker's slot
        _busy.set()
        try:
            return fn(*args)
        finally:
            _busy.clear()


class WorkerPool:
    """ProcessPoolExecutor whose workers stop with the main process and keep at most `budget` (default: workers)
    processes busy (see the module docstring)."""

    def __init__(self, workers: int, budget: int | None = None):
        _child_thread_env()
        ctx = mp.get_context("spawn")
        self.stop = ctx.Event()
        self.slots = IdleSlots(max(workers, budget or workers), ctx)
        self.executor = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init,
                                            initargs=(os.getpid(), self.stop, self.slots))

    def submit(self, fn: Callable, *args) -> Future:
        return self.executor.submit(_call, fn, *args)


@contextlib.contextmanager
def worker_pool(workers: int, budget: int | None = None) -> Iterator[WorkerPool]:
    pool = WorkerPool(workers, budget)
    try:
        yield pool
    except BaseException:  # Ctrl-C or an error in the main process: stop the workers now
        pool.stop.set()
        pool.executor.shutdown(wait=True, cancel_futures=True)
        raise
    pool.executor.shutdown(wait=True)
