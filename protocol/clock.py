"""This host's clock onto a capture system's clock, learnt from the capture stream itself.

A live marker stream is stamped by the capture system's own clock (Motive: seconds since it
started; QTM: microseconds since its start), a camera on this host by this host's monotonic
clock, and the two share no epoch.  Every marker frame that arrives says "capture time ``c`` was at
most here and now ``h``": ``c - h`` is the capture clock's offset from ours less that frame's
transport latency.  The largest ``c - h`` over a recent window is therefore the offset less the
*smallest* latency seen (the frames that came straight through), which is what maps a camera
frame's arrival time into the marker clock.  The window (not the whole take) follows clock drift
and a capture system restarted mid-take; a capture stamp going back clears it at once.  The
mapping is offered only once the frames seen span ``settle_s`` of capture time *and* of arrival
time: the first frames of a stream often wait in a queue while a node starts up and then come in a
burst (measured here: with no settling the first camera frame was mapped 1.2 s off, the next ones
12 and 7 ms, then under 1 ms; settling on capture time alone, a burst of a second of frames left the
first one 291 ms off).
"""

from __future__ import annotations

from collections import deque

NS = 1_000_000_000


class ClockBridge:
    """Sliding-window estimate of ``capture clock - local monotonic clock`` (ns).

    ``observe(capture_stamp_ns, local_arrival_ns)`` for each marker frame as it arrives;
    ``to_capture(local_ns)`` maps a local monotonic time (a camera frame's read time) onto the
    capture clock.  ``window_s``: how long an observation counts (drift and restarts);
    ``settle_s``: capture time the observations must span before the mapping is used."""

    def __init__(self, window_s: float = 10.0, settle_s: float = 1.0):
        if not window_s > 0 or not 0 <= settle_s < window_s:
            raise ValueError("window_s > 0 and 0 <= settle_s < window_s are required")
        self.window_ns, self.settle_ns = int(window_s * NS), int(settle_s * NS)
        self._first_capture: int | None = None
        self._first_local = self._last_local = 0
        self._max: deque[tuple[int, int]] = deque()  # (local arrival, capture - local), offsets decreasing
        self._last_capture: int | None = None
        self.observations = 0
        self.resets = 0

    @property
    def ready(self) -> bool:
        return bool(self._max) and min(self._last_capture - self._first_capture, self._last_local - self._first_local) >= self.settle_ns

    def observe(self, capture_stamp_ns: int, local_arrival_ns: int) -> None:
        capture, local = int(capture_stamp_ns), int(local_arrival_ns)
        if self._last_capture is not None and capture < self._last_capture:
            self._max.clear()  # the capture clock went back (capture software restarted): old offsets are void
            self._first_capture = None
            self.resets += 1
        if self._first_capture is None:
            self._first_capture, self._first_local = capture, local
        self._last_local = local
        self._last_capture = capture
        offset = capture - local
        while self._max and self._max[-1][1] <= offset:  # a later, larger offset outlives the smaller ones
            self._max.pop()
        self._max.append((local, offset))
        while self._max[0][0] < local - self.window_ns:
            self._max.popleft()
        self.observations += 1

    @property
    def first_capture_ns(self) -> int | None:
        """The first capture stamp seen (since the capture clock last went back)."""
        return self._first_capture

    @property
    def offset_ns(self) -> int:
        """capture clock - local clock (ns), from the least-delayed frame of the window."""
        if not self._max:
            raise RuntimeError("no capture frame observed yet")
        return self._max[0][1]

    def to_capture(self, local_ns: int) -> int:
        return int(local_ns) + self.offset_ns

    def frame_times(self, video_stamp_ns: int, live: bool, now_ns: int) -> tuple[int, int]:
        """(local monotonic ns, capture-clock ns) of a video frame.  A live camera's frame is where
        it arrived (``now_ns``); a file beside a live stream plays as a camera started with the
        marker stream (rehearsals, tests): its frame at ``video_stamp_ns`` (from 0) belongs to the
        first marker frame's capture time plus that much, and is due here then."""
        if live:
            return int(now_ns), self.to_capture(now_ns)
        capture = self._first_capture + int(video_stamp_ns)
        return capture - self.offset_ns, capture
