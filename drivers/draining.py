"""A writer thread behind a producer that must never wait for the disk (the control loop): the
producer appends to a deque, the thread calls :meth:`DrainingWriter._drain` every period and once
more at the stop. A writer that fails (a full disk) keeps its error in ``error`` and ends; the
producer carries on and the owner reports the error at close. The CAN capture
(:mod:`drivers.capture`) and the MCAP recording (:mod:`hil_runtime.formats.mcap_record`) share it.
"""

from __future__ import annotations

import abc
import logging
import threading

log = logging.getLogger(__name__)


class DrainingWriter(abc.ABC):
    """The drain thread's lifecycle around one hook, :meth:`_drain` (write what is queued)."""

    def __init__(self, drain_period_s: float, thread_name: str, what: str) -> None:
        self.drain_period_s = drain_period_s
        self.error: BaseException | None = None  # what stopped the writer thread, if anything did
        self._what = what  # named in the log line when the writer fails
        self._thread_name = thread_name
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @abc.abstractmethod
    def _drain(self) -> None:
        """Write everything queued so far (the writer thread, or the caller of :meth:`_stop_draining`)."""

    def _start_draining(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name=self._thread_name, daemon=True)
            self._thread.start()

    def _run(self) -> None:
        try:
            while not self._stop.wait(self.drain_period_s):
                self._drain()
        except BaseException as exc:  # noqa: BLE001 - a full disk must not stop the loop: reported at close
            self.error = exc
            log.error("%s stopped: %r", self._what, exc)

    def _stop_draining(self, write_rest: bool = True) -> bool:
        """Stop the thread and (``write_rest``, the writer healthy) write what is still queued.
        False when the thread was never started."""
        self._stop.set()
        if self._thread is None:
            return False
        self._thread.join()
        if write_rest and self.error is None:
            self._drain()
        return True


__all__ = ["DrainingWriter"]
