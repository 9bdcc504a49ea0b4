"""The boundary's receiving side: LCM's own Python binding with a queue per subscription.

pydrake's DrakeLcm keeps one message per subscription between two pumps (the first; the rest
are dropped: tests/test_hardware.py) and gives Python no handle on the subscription's queue.
A 1 kHz loop that pumps once per step then loses the second of two statuses that reach one step,
and every status of a burst but the first (an arm catching up after a stall): measured beside
one experiment_a run, a DrakeLcm listener lost 444 of ~10 000 statuses, this one none. LCM's
`lcm` package (lcm-proj; the same protocol and Drake's lcmtypes' bytes) reads the socket on its
own C thread into a queue of QUEUE_CAPACITY per subscription; the loop hands every queued
message over at its step (HandleSubscriptions drains the queue). No Python thread: one that
handled messages beside the loop crashed the process (a segfault inside the binding, 2 of 16 runs).
Publishing stays with DrakeLcm and the LcmPublisherSystems.
"""

from __future__ import annotations

from collections.abc import Callable

QUEUE_CAPACITY = 1000  # messages per subscription between two steps: a second of a 1 kHz stream


class QueuedLcm:
    """DrakeLcm's receiving half (Subscribe, HandleSubscriptions) on LCM's Python binding."""

    def __init__(self, url: str) -> None:
        import lcm

        self._lcm = lcm.LCM(url)

    def Subscribe(self, channel: str, handler: Callable[[bytes], None]) -> None:  # noqa: N802 -- DrakeLcm's name: LatestMessage takes either
        subscription = self._lcm.subscribe(channel, lambda _channel, data: handler(data))
        subscription.set_queue_capacity(QUEUE_CAPACITY)

    def HandleSubscriptions(self, timeout_ms: int) -> int:  # noqa: N802
        """Hand over every queued message (waiting up to timeout_ms for the first); how many."""
        handled = self._lcm.handle_timeout(timeout_ms)
        while handled and self._lcm.handle_timeout(0):
            handled += 1
        return handled
