"""The life cycle every emulated device shares: open its link, serve it from one thread, close it on stop."""

from __future__ import annotations

import threading
from typing import TypeVar

D = TypeVar("D", bound="ThreadedDevice")


class ThreadedDevice:
    """Subclasses implement ``_open()`` (bind the bus/socket), ``_run()`` (loop until ``self._stop`` is set) and
    ``_close()`` (release it). ``start()``/``stop()`` or ``with device:``; ``stop`` waits at most 2 s."""

    thread_name = "device"

    def __init__(self) -> None:
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _open(self) -> None:
        raise NotImplementedError

    def _run(self) -> None:
        raise NotImplementedError

    def _close(self) -> None:
        raise NotImplementedError

    def start(self: D) -> D:
        self._open()
        self._thread = threading.Thread(target=self._run, name=self.thread_name, daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._close()

    def __enter__(self: D) -> D:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
