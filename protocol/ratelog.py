"""Rate-limited warnings about bad input from peers (one helper for mapper, planner and robot agent).

A flood of malformed messages must be visible in the log without writing one line per message. Each
message names a *reason* (a short fixed name such as ``decode_errors``, never a peer-chosen string). A
reason's message is logged in full when that reason was not logged in the last ``period_s`` (its first
occurrence, and again once per period while it keeps happening); the others are counted, and one summary
line, ``period_s`` after the first of them, says how many of each reason were held back::

    bad = RateLimitedLog(log, period_s=10.0)
    bad.warning("goals_garbage", "ignoring undecodable goal payload (%d bytes): %s", len(data), e)
    ...
    bad.flush()   # from a periodic loop: emits the summary once the period is over

Thread-safe (Zenoh callbacks). The clock is injectable for tests. At most ``max_reasons`` reasons are
remembered (least recently seen forgotten), so even careless use with varying reasons stays bounded.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable

DEFAULT_PERIOD_S = 10.0
"""Default: at most one summary line per this many seconds."""
MAX_LINE_CHARS = 400
"""A logged line is cut to this many characters (peer-chosen text such as a 4000-character query)."""


def clean(text: str, max_chars: int = MAX_LINE_CHARS) -> str:
    """``text`` on one line (control characters escaped, so a peer cannot forge log lines), cut to ``max_chars``."""
    out = "".join(c if c.isprintable() else repr(c)[1:-1] for c in text[: max_chars + 1])
    return out if len(out) <= max_chars else out[: max_chars - 3] + "..."


class RateLimitedLog:
    """First occurrence per reason logged at once, then at most one summary line per ``period_s`` with counts."""

    def __init__(
        self,
        logger: logging.Logger,
        period_s: float = DEFAULT_PERIOD_S,
        *,
        level: int = logging.WARNING,
        max_reasons: int = 256,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if period_s <= 0 or max_reasons < 1:
            raise ValueError("period_s must be > 0 and max_reasons >= 1")
        self._log, self.period_s, self.level, self.max_reasons = logger, period_s, level, max_reasons
        self._clock = clock
        self._lock = threading.Lock()
        self._seen: collections.OrderedDict[str, float] = collections.OrderedDict()  # reason -> last logged
        self._held: dict[str, int] = {}
        self._held_since = 0.0  # when the oldest held-back message was counted
        self.logged = 0
        """Lines written so far (first occurrences and summaries)."""

    def warning(self, reason: str, msg: str, *args: object) -> bool:
        """Count one bad input of ``reason``; log ``msg % args`` unless ``reason`` was logged less than
        ``period_s`` ago (then it is held back for the summary). True when logged."""
        with self._lock:
            now = self._clock()
            last = self._seen.get(reason)
            first = last is None or now - last >= self.period_s
            if first:
                self._seen[reason] = now
            self._seen.move_to_end(reason)
            while len(self._seen) > self.max_reasons:
                forgotten, _ = self._seen.popitem(last=False)
                self._held.pop(forgotten, None)
            if not first:
                if not self._held:
                    self._held_since = now
                self._held[reason] = self._held.get(reason, 0) + 1
        if first:
            self._emit(msg, *args)
        self.flush()
        return first

    def flush(self, force: bool = False) -> bool:
        """Log the summary of held-back messages once ``period_s`` has passed since the first of them was
        counted (or at once with ``force``). True when a line was written. Call it from a periodic loop."""
        with self._lock:
            now = self._clock()
            if not self._held or (not force and now - self._held_since < self.period_s):
                return False
            held, self._held = self._held, {}
            since = now - self._held_since
        parts = ", ".join(f"{reason} x{n}" for reason, n in sorted(held.items()))
        self._emit("%d more bad inputs in the last %.0f s (not logged one by one): %s",
                   sum(held.values()), since, parts)
        return True

    def held(self) -> dict[str, int]:
        """Messages counted but not yet reported, per reason."""
        with self._lock:
            return dict(self._held)

    def _emit(self, msg: str, *args: object) -> None:
        self.logged += 1
        try:
            text = msg % args if args else msg
        except (TypeError, ValueError) as e:  # a wrong format must not lose the warning
            text = f"{msg} {args!r} ({e})"
        self._log.log(self.level, "%s", clean(text))
