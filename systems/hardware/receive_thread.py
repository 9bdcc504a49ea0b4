"""The boundary's receiving side: LCM's own Python binding, handled by a thread of its own.

pydrake's DrakeLcm keeps one message per subscription between two pumps (the first; the rest
are dropped: tests/test_hardware.py), gives Python no handle on the subscription's queue, and
holds the GIL while a pump waits. A 1 kHz loop that pumps once per step then loses the second of
two statuses that reach one step, and every status of a burst but the first (an arm catching up
after a stall): measured beside one experiment_a run, a DrakeLcm listener lost 444 of ~10 000
statuses where this one lost none. LCM's `lcm` package (lcm-proj, the same protocol) sets the
queue (QUEUE_CAPACITY) and releases the GIL while it waits, so the thread costs the loop nothing
until a message arrives; started from a SCHED_FIFO thread it inherits that policy. Messages are
the same Drake lcmtypes' bytes; publishing stays with DrakeLcm and the LcmPublisherSystems.
"""

from __future__ import annotations

import threading

QUEUE_CAPACITY = 1000  # messages per subscription between two handlings: a second of a 1 kHz stream
WAIT_MS = 20  # one handling waits at most this long: how soon stop() is honoured
# The loop's process sets this switch interval (the interpreter's default, 5 ms, would let the
# loop hold the GIL from the thread's handler for five steps).
SWITCH_INTERVAL_S = 1e-4


class ReceiveThread:
    """DrakeLcm's receiving half (Subscribe, HandleSubscriptions) on LCM's Python binding. Subscribe,
    then start(); stop() at the end. Before start() the owner may handle messages itself."""

    def __init__(self, url: str) -> None:
        import lcm

        self._lcm = lcm.LCM(url)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def Subscribe(self, channel: str, handler) -> None:  # noqa: N802 -- DrakeLcm's name: LatestMessage takes either
        subscription = self._lcm.subscribe(channel, lambda _channel, data: handler(data))
        subscription.set_queue_capacity(QUEUE_CAPACITY)

    def HandleSubscriptions(self, timeout_ms: int) -> None:  # noqa: N802
        if self._thread is None:
            self._lcm.handle_timeout(timeout_ms)
        else:  # the thread handles them: just wait
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
            self._lcm.handle_timeout(WAIT_MS)  # the GIL released while it waits
