"""Simulated time for the fakes: motions and waits advance it, nothing ever sleeps."""

from __future__ import annotations


class SimClock:
    """A monotonic clock in seconds that only moves when told to (``sleep`` and ``advance`` are the same)."""

    def __init__(self, start_s: float = 0.0) -> None:
        self._t = float(start_s)

    def now(self) -> float:
        """Current simulated time (s)."""
        return self._t

    def advance(self, dt_s: float) -> float:
        """Move time forward by ``dt_s`` >= 0 seconds; returns the new time."""
        if dt_s < 0:
            raise ValueError(f"SimClock cannot go backwards (dt = {dt_s} s)")
        self._t += float(dt_s)
        return self._t

    def sleep(self, dt_s: float) -> None:
        """Drop-in for ``time.sleep``: advances the simulated time at once."""
        self.advance(dt_s)
