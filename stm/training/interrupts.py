"""Ctrl-C during training: held until the training step in progress is whole, so that an interrupted
training checkpoints a consistent state where it stands (stm.training.loop) instead of
losing the iterations since its last periodic checkpoint. A busy study worker is stopped the same
way (experiments/runtime/processes.py interrupts its main thread as a SIGINT would). A store call is held
whole too (experiments/runtime/tracking.py)."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator


@contextlib.contextmanager
def whole_step() -> Iterator[None]:
    """A SIGINT that arrives inside the block is delivered when the block ends (to the handler that was
    there before: KeyboardInterrupt by default); one that arrives outside is not touched. Off the main
    thread, where Python delivers no signal, a no-op."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if held:
        if callable(previous):
            previous(signal.SIGINT, None)
        elif previous == signal.SIG_DFL:  # the default would end the process: end the training instead
            raise KeyboardInterrupt
