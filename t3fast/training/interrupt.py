"""Ctrl-C during training: the first stops the run cleanly after the current step, the second aborts."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from typing import Any

from tqdm import tqdm


class StopRequest:
    """``requested`` turns True on the first Ctrl-C while :meth:`installed` is active."""

    def __init__(self, announce: bool = True) -> None:
        self.requested = False
        self.announce = announce  # only rank 0 prints

    @contextlib.contextmanager
    def installed(self) -> Iterator[None]:
        """First Ctrl-C: set ``requested``. Second: KeyboardInterrupt at once."""
        if threading.current_thread() is not threading.main_thread():  # signal handlers live there only
            yield
            return

        def handler(signum: int, frame: Any) -> None:
            if self.requested:
                raise KeyboardInterrupt
            self.requested = True
            if self.announce:
                tqdm.write("interrupted: saving last.pt after this step (Ctrl-C again to abort)")

        previous = signal.signal(signal.SIGINT, handler)
        try:
            yield
        finally:
            # None means a handler not installed from Python; the default is the closest we can restore
            signal.signal(signal.SIGINT, previous if previous is not None else signal.SIG_DFL)


def ignore_sigint(worker_id: int) -> None:
    """DataLoader workers leave Ctrl-C to the main process, which stops cleanly and shuts them down."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
