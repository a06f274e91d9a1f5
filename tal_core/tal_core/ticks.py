"""The sim-time tick grid every periodic node and offline replay share (no rclpy here)."""

from __future__ import annotations

from collections import deque

NS_PER_S = 1_000_000_000
TICK_TOLERANCE_NS = 100_000  # [ns] stamps are exact multiples of the physics step; absorb rounding
CLOCK_RESET_NS = 500_000_000  # [ns] a stamp this far behind the last one is a restarted clock, not reordering


def reaches_tick(stamp_ns: int, next_tick_ns: int, tolerance_ns: int = TICK_TOLERANCE_NS) -> bool:
    """True when a sample stamped ``stamp_ns`` is at (or past) the control tick ``next_tick_ns``; a sample
    up to ``tolerance_ns`` early counts (rounding; the jitter of a real robot's stamps)."""
    return stamp_ns >= next_tick_ns - tolerance_ns


def tick_after(stamp_ns: int, period_ns: int, tolerance_ns: int = TICK_TOLERANCE_NS) -> int:
    """The next control tick [ns] after the one at ``stamp_ns``, on the sim-time grid k * period_ns (a stamp
    up to ``tolerance_ns`` before a grid point belongs to it)."""
    return ((stamp_ns + tolerance_ns) // period_ns + 1) * period_ns



class StampedInbox:
    """Inputs stamped with the tick they were computed for (a heightmap, a foothold), held until the consumer's
    first tick at least ``lag_ns`` after their stamp and then handed over in stamp order. A consumer that
    used an input stamped with its own tick would depend on whether it arrived before or after the tick's
    other inputs (other topics, no order between them).

    The lag alone does not make a consumer deterministic: DDS gives no order between topics, and a large
    message (a heightmap) can arrive after the consumer's next tick even in lockstep. With ``period_ns`` (the
    producer publishes on the sim-time grid k * period_ns, as the bridge its heightmap) the consumer can ask
    ``awaited(tick)`` for the input due at a tick that has not arrived yet, and hold the tick until it does.
    An input newer than all before it that arrives after a tick that should have used it is counted in ``late``
    (its tick used an older one: the run then depends on delivery order). An input with a stamp already
    received (a producer re-sending what a late-matched consumer may have missed) is dropped, counted in
    ``repeats``. With ``period_ns``, a tick whose due input never came while a newer one did (DDS dropped it:
    published before the consumer's subscription matched) uses an older input or none; each such input is
    counted once in ``missed`` (the run then depends on when the consumer started; a lockstep bridge holds its
    first step until the map consumers' subscriptions have matched).

    At most ``keep`` inputs are held (the oldest are dropped, counted); inputs from before a restarted clock
    (stamped more than ``CLOCK_RESET_NS`` after the tick asking) are forgotten."""

    def __init__(self, lag_ns: int, keep: int = 64, period_ns: int = 0) -> None:
        if lag_ns < 0 or keep < 1 or period_ns < 0:
            raise ValueError(f"StampedInbox needs lag_ns >= 0, keep >= 1 and period_ns >= 0, got {lag_ns}, {keep} "
                             f"and {period_ns}")
        self.lag_ns = int(lag_ns)
        self.keep = int(keep)
        self.period_ns = int(period_ns)
        self.dropped = 0
        self.late = 0
        self.repeats = 0
        self.missed = 0
        self._missed_ns: int | None = None   # the last due stamp counted in missed
        self._recent: deque[int] = deque(maxlen=keep)  # stamps received, newest last (repeats)
        self._items: list[tuple[int, int, object]] = []  # (stamp, arrival, item)
        self._arrivals = 0
        self._newest_ns: int | None = None   # the newest stamp received (awaited)
        self._cutoff_ns: int | None = None   # the newest cutoff handed over (late)

    def __len__(self) -> int:
        return len(self._items)

    def add(self, stamp_ns: int, item: object) -> None:
        stamp_ns = int(stamp_ns)
        if self._newest_ns is not None and stamp_ns + CLOCK_RESET_NS < self._newest_ns:
            self.clear()  # the producer's clock restarted
        if stamp_ns in self._recent:
            self.repeats += 1
            return
        self._recent.append(stamp_ns)
        if self._cutoff_ns is not None and stamp_ns <= self._cutoff_ns and (self._newest_ns is None
                                                                          or stamp_ns > self._newest_ns):
            self.late += 1  # newer than anything before, yet a tick has passed that should have used it
        self._newest_ns = stamp_ns if self._newest_ns is None else max(self._newest_ns, stamp_ns)
        self._arrivals += 1
        self._items.append((stamp_ns, self._arrivals, item))
        if len(self._items) > self.keep:
            self._items.sort(key=lambda entry: entry[:2])
            del self._items[0]
            self.dropped += 1

    def clear(self) -> None:
        """Forget the held inputs and what arrived (a restarted clock)."""
        self._items.clear()
        self._recent.clear()
        self._newest_ns = self._cutoff_ns = self._missed_ns = None

    def due_stamp(self, tick_ns: int) -> int | None:
        """With ``period_ns``: the grid stamp of the newest input due at ``tick_ns`` (None: none due yet, or no
        period)."""
        if not self.period_ns:
            return None
        due = ((tick_ns - self.lag_ns + TICK_TOLERANCE_NS) // self.period_ns) * self.period_ns
        return due if due >= 0 else None

    def awaited(self, tick_ns: int) -> int | None:
        """The stamp of the input due at ``tick_ns`` that has not arrived (nor any newer one); None when nothing
        is awaited (no period, nothing due yet, or it is here)."""
        due = self.due_stamp(tick_ns)
        if due is None or (self._newest_ns is not None and self._newest_ns >= due - TICK_TOLERANCE_NS):
            return None
        return due

    def seen(self, stamp_ns: int) -> bool:
        """Whether an input with this stamp was received (among the last ``keep``): a re-sent one."""
        return self._received(stamp_ns)

    def _received(self, stamp_ns: int) -> bool:
        return any(abs(stamp - stamp_ns) <= TICK_TOLERANCE_NS for stamp in self._recent)

    def has_due(self, tick_ns: int) -> bool:
        """Whether ``due(tick_ns)`` would hand something over (without handing it over)."""
        cutoff = tick_ns - self.lag_ns + TICK_TOLERANCE_NS
        return any(stamp <= cutoff for stamp, _, _ in self._items)

    def due(self, tick_ns: int) -> list[tuple[int, object]]:
        """(stamp, item) of the held inputs stamped at least ``lag_ns`` before ``tick_ns``, oldest first."""
        expected = self.due_stamp(tick_ns)
        if (expected is not None and self._newest_ns is not None and self._newest_ns > expected + TICK_TOLERANCE_NS
                and expected != self._missed_ns and not self._received(expected)):
            self.missed += 1
            self._missed_ns = expected
        cutoff = tick_ns - self.lag_ns + TICK_TOLERANCE_NS
        if self._cutoff_ns is not None and tick_ns + CLOCK_RESET_NS < self._cutoff_ns:
            self._cutoff_ns = None  # the consumer's clock restarted
        self._cutoff_ns = cutoff if self._cutoff_ns is None else max(self._cutoff_ns, cutoff)
        self._items = [entry for entry in self._items if entry[0] <= tick_ns + CLOCK_RESET_NS]
        due = sorted((entry for entry in self._items if entry[0] <= cutoff), key=lambda entry: entry[:2])
        if due:
            self._items = [entry for entry in self._items if entry[0] > cutoff]
        return [(stamp, item) for stamp, _, item in due]


class HeldTicks:
    """A consumer that ticks on a message (the vfa and the vpa on the wbc's gait state) and holds each tick
    until the periodic inputs due at it (``StampedInbox.awaited``) have arrived, releasing ticks in order.
    A held tick is released anyway, counted in ``released_late``, once a tick more than ``max_defer_ns`` after
    it is offered (the producer is gone, or the run is not in lockstep)."""

    def __init__(self, inboxes: list[StampedInbox], max_defer_ns: int = 0) -> None:
        if max_defer_ns < 0:
            raise ValueError(f"HeldTicks needs max_defer_ns >= 0, got {max_defer_ns}")
        self.inboxes = inboxes
        self.max_defer_ns = int(max_defer_ns)
        self.held_ticks = 0       # ticks that waited
        self.released_late = 0    # ticks released without what they waited for
        self._held: list[tuple[int, object]] = []

    def __len__(self) -> int:
        return len(self._held)

    def waiting(self, stamp_ns: int) -> bool:
        return any(inbox.awaited(stamp_ns) is not None for inbox in self.inboxes)

    def offer(self, stamp_ns: int, item: object) -> list[tuple[int, object]]:
        """A new tick: the ticks (stamp, item) to run now, in order (maybe none, maybe older held ones)."""
        stamp_ns = int(stamp_ns)
        if self._held and stamp_ns + CLOCK_RESET_NS < self._held[-1][0]:
            released, self._held = self._held, []  # the clock restarted: run what was held, as it is
            self.released_late += len(released)
            return released + self.offer(stamp_ns, item)
        if not self._held and not self.waiting(stamp_ns):
            return [(stamp_ns, item)]
        if self.waiting(stamp_ns):
            self.held_ticks += 1
        self._held.append((stamp_ns, item))
        return self._release(stamp_ns)

    def arrived(self) -> list[tuple[int, object]]:
        """An awaited input arrived: the held ticks now complete, in order."""
        return self._release(None)

    def _release(self, newest_ns: int | None) -> list[tuple[int, object]]:
        out = []
        while self._held:
            stamp, item = self._held[0]
            if self.waiting(stamp):
                if newest_ns is None or newest_ns <= stamp + self.max_defer_ns:
                    break
                self.released_late += 1
            out.append(self._held.pop(0))
        return out


class TickAnswers:
    """A producer's last answer, for a consumer that asks again: DDS drops what a writer publishes before it has
    matched a late reader, and a lockstep consumer would wait for that answer until its driver times out, so the
    consumer (or its driver) repeats the tick and the producer answers it again. ``seen(stamp)`` for every tick
    that arrives: whether it repeats the newest one, and the answer to send again (None: nothing answered it)."""

    def __init__(self) -> None:
        self.resent = 0
        self.answered_ns: int | None = None
        self._answer: object | None = None
        self._newest_ns: int | None = None

    def seen(self, stamp_ns: int) -> tuple[bool, object | None]:
        if stamp_ns != self._newest_ns:
            self._newest_ns = stamp_ns
            return False, None
        if self._answer is None or stamp_ns != self.answered_ns:
            return True, None
        self.resent += 1
        return True, self._answer

    def answered(self, stamp_ns: int, answer: object) -> None:
        """The answer just sent to the tick ``stamp_ns``."""
        self.answered_ns, self._answer = stamp_ns, answer


class RecentByStamp:
    """The ``keep`` most recently received items of a stream, by stamp: the one of an exact stamp, the newest,
    or the newest at or before a stamp (a consumer that takes another stream's sample of its own tick and must
    not depend on whether a newer one arrived first). A stamp received again keeps its first item."""

    def __init__(self, keep: int) -> None:
        if keep < 1:
            raise ValueError(f"RecentByStamp needs keep >= 1, got {keep}")
        self.keep = int(keep)
        self._items: dict[int, object] = {}
        self._order: deque[int] = deque()
        self.newest_ns: int | None = None

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, stamp_ns: int) -> bool:
        return stamp_ns in self._items

    def add(self, stamp_ns: int, item: object) -> None:
        stamp_ns = int(stamp_ns)
        if stamp_ns in self._items:
            return
        self._items[stamp_ns] = item
        self._order.append(stamp_ns)
        if self.newest_ns is None or stamp_ns > self.newest_ns:
            self.newest_ns = stamp_ns
        while len(self._order) > self.keep:
            del self._items[self._order.popleft()]
        if self.newest_ns not in self._items:   # (the newest stamp was the oldest to arrive)
            self.newest_ns = max(self._items)

    def get(self, stamp_ns: int) -> object | None:
        return self._items.get(stamp_ns)

    def newest(self) -> tuple[int, object] | None:
        """(stamp, item) of the newest stamp held (None: none)."""
        return None if self.newest_ns is None else (self.newest_ns, self._items[self.newest_ns])

    def at_or_before(self, stamp_ns: int) -> tuple[int, object] | None:
        """(stamp, item) of the newest held at or before ``stamp_ns`` (None: none)."""
        stamp = max((s for s in self._items if s <= stamp_ns), default=None)
        return None if stamp is None else (stamp, self._items[stamp])
