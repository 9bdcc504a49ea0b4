"""A DrakeLcm polled by a thread of its own, so every message reaches its handler as it arrives.

pydrake's DrakeLcm keeps one message per subscription between two pumps (the first; the rest are
dropped, tests/test_hardware.py) and gives Python no handle on the subscription's queue capacity.
A 1 kHz loop that pumps once per step therefore loses the second of two statuses (or commands)
that reach it within one step: two free-running 1 kHz clocks do that every few steps, and each
lost status ends the estimator's segment (docs/hardware.md, Time). This thread polls every
POLL_S and sleeps between polls: a pump that waits (HandleSubscriptions(timeout > 0)) holds the
GIL while it waits, and starved the loop (measured: 10x fewer loop iterations). Polling costs
~9 % of a core; started from a SCHED_FIFO thread it inherits that policy.
"""

from __future__ import annotations

import threading
import time

POLL_S = 1e-4  # two messages closer than this (plus the sleep's slack) still lose one
# The loop's process sets this switch interval (the interpreter's default, 5 ms, would let the
# loop hold the GIL from the thread's handler for five steps).
SWITCH_INTERVAL_S = 1e-4


class ReceiveThread:
    """Subscribe on `.lcm` (e.g. LatestMessage(thread.lcm, ...)), then start(); stop() at the end.
    Before start() the owner may pump `.lcm` itself (pump); never both at once."""

    def __init__(self, url: str) -> None:
        from pydrake.lcm import DrakeLcm

        self.lcm = DrakeLcm(url)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def pump(self, timeout_ms: int) -> None:
        if self._thread is None:
            self.lcm.HandleSubscriptions(timeout_ms)
        else:  # the thread pumps: just wait
            self._stop.wait(timeout_ms * 1e-3)

    def start(self) -> None:
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="lcm-receive", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        if self._thread is not None:
            self._stop.set()
            self._thread.join(timeout=1.0)
            self._thread = None

    def _run(self) -> None:
        while not self._stop.is_set():
            self.lcm.HandleSubscriptions(0)
            time.sleep(POLL_S)  # the GIL released
