"""SIGINT and SIGTERM end a stream cleanly: the first stops the source, a second one interrupts at once."""
from __future__ import annotations

import logging
from typing import Callable

log = logging.getLogger(__name__)


def install_stop_handlers(source, stopped: list[str]) -> Callable[[], None]:
    """SIGINT/SIGTERM: the first stops the source (the stream ends cleanly with what it has), a second one
    raises KeyboardInterrupt. Only in the main thread; returns a function that restores the old handlers."""
    import signal
    import threading
    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    old = {}

    def handler(signum, _frame) -> None:
        name = signal.Signals(signum).name
        if stopped:
            raise KeyboardInterrupt
        stopped.append(name)
        log.info("%s: stopping the stream; what was captured is processed and written.", name)
        source.stop()

    for sig in (signal.SIGINT, signal.SIGTERM):
        old[sig] = signal.signal(sig, handler)

    def restore() -> None:
        for sig, h in old.items():
            signal.signal(sig, h)
    return restore
