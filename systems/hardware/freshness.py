"""Freshness of a message stream across the arm boundary (pure; both sides use it).

A receiver accepts a message only when its sender time stamp is newer than the last accepted one
(a duplicate or an older, out-of-order message is ignored and counted). It trips, latched, when
no new message arrived for `limit_s` by its own clock (the stream stopped or stalled), or when
the sender's clock advanced by more than `limit_s` between two consecutive messages (a clock jump
or a gap the sampling assumption A6 does not cover). A tripped receiver is the cue to brake.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any


@dataclass(frozen=True)
class Freshness:
    limit_s: float
    last_sent_s: float | None = None  # sender time of the last accepted message (None: none yet)
    last_arrival_s: float = 0.0  # receiver time it arrived
    payload: Any = None  # the last accepted message's content
    tripped: str | None = None  # why the stream is no longer trusted (latched)
    ignored: int = 0  # out-of-order messages (older than the last accepted one)
    last_seen_s: float | None = None  # sender time of the newest message looked at (accepted or not)
    grace_until_s: float = -1.0  # receiver time before which no timing check trips (the loop's start)
    events: tuple[dict, ...] = ()

    def __deepcopy__(self, memo: dict) -> Freshness:
        return self  # immutable: Drake copies the state at every step's unrestricted update

    @property
    def armed(self) -> bool:
        return self.last_sent_s is not None

    def trip(self, now_s: float, kind: str, detail: str) -> Freshness:
        if self.tripped is not None:
            return self
        return replace(self, tripped=kind, events=self.events + (dict(t=now_s, kind=kind, detail=detail),))

    def step(self, now_s: float, sent_s: float | None = None, payload: Any = None, *, name: str) -> Freshness:
        """One receiver tick at now_s with the newest message received (sent_s None: nothing yet)."""
        if self.tripped is not None:
            return self
        if now_s < self.grace_until_s:  # starting: take the newest message, check nothing yet
            if sent_s is None or (self.armed and sent_s <= self.last_sent_s):
                return self
            return replace(self, last_sent_s=sent_s, last_seen_s=sent_s, last_arrival_s=now_s, payload=payload)
        out = self
        if sent_s is not None and sent_s != self.last_seen_s:
            out = replace(out, last_seen_s=sent_s)
            if self.armed and sent_s <= self.last_sent_s:
                out = replace(out, ignored=out.ignored + 1)
            elif self.armed and sent_s - self.last_sent_s > self.limit_s:
                jump = (sent_s - self.last_sent_s) * 1e3
                return out.trip(now_s, f"{name}_clock_jump", f"sender clock advanced {jump:.1f} ms in one message")
            else:
                out = replace(out, last_sent_s=sent_s, last_arrival_s=now_s, payload=payload)
        if out.armed and now_s - out.last_arrival_s > self.limit_s:
            silent = (now_s - out.last_arrival_s) * 1e3
            return out.trip(now_s, f"{name}_lost", f"no new {name} message for {silent:.1f} ms")
        return out
