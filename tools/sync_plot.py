"""A PNG to check a video's clock offset by eye (``uuomocap solve --clock-offset auto --sync-plot``).

Top: how fast the body articulates, seen by the markers and by the video prior, the prior's moved
by the offset the solve used - when the offset is right, their bumps line up.  Bottom: the motion
correlation at every offset searched, with the offset found, the one recorded in the session, the
other correlation peaks, and the registered body's marker fit at the offsets the refinement scored
(lower is better: a V at the offset found says the fit confirms it).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

WIDTH, PANEL_H, MARGIN_L, MARGIN_R = 1000, 230, 70, 70
BLUE, ORANGE, GREEN, RED, GREY, PURPLE, BLACK = (200, 90, 20), (0, 140, 255), (40, 160, 40), (40, 40, 220), (160, 160, 160), (160, 40, 140), (30, 30, 30)
FONT = cv2.FONT_HERSHEY_SIMPLEX


def _nice_ticks(lo: float, hi: float, n: int = 8) -> np.ndarray:
    step = (hi - lo) / max(n, 1)
    mag = 10 ** np.floor(np.log10(step)) if step > 0 else 1.0
    step = min((m * mag for m in (1, 2, 5, 10) if m * mag >= step), default=mag)
    return np.arange(np.ceil(lo / step) * step, hi + 1e-9, step)


class _Axes:
    """Data -> pixel mapping of one panel (y up), with its frame and x ticks."""

    def __init__(self, img, top: int, x_range, y_range, x_label: str):
        self.img, self.top = img, top
        self.x0, self.x1 = MARGIN_L, WIDTH - MARGIN_R
        self.y0, self.y1 = top + PANEL_H - 30, top + 22  # bottom, top in pixels
        self.xr, self.yr = x_range, y_range
        cv2.rectangle(img, (self.x0, self.y1), (self.x1, self.y0), BLACK, 1)
        for t in _nice_ticks(*x_range):
            x = self.px(t, y_range[0])[0]
            cv2.line(img, (x, self.y0), (x, self.y0 + 4), BLACK, 1)
            cv2.putText(img, f"{t:g}", (x - 12, self.y0 + 17), FONT, 0.4, BLACK, 1, cv2.LINE_AA)
        cv2.putText(img, x_label, (self.x1 - 8 * len(x_label), self.y0 + 28), FONT, 0.4, BLACK, 1, cv2.LINE_AA)

    def px(self, x: float, y: float, y_range=None) -> tuple[int, int]:
        lo, hi = y_range or self.yr
        u = (x - self.xr[0]) / max(self.xr[1] - self.xr[0], 1e-12)
        v = (y - lo) / max(hi - lo, 1e-12)
        return int(round(self.x0 + u * (self.x1 - self.x0))), int(round(self.y0 - v * (self.y0 - self.y1)))

    def line(self, x: np.ndarray, y: np.ndarray, colour, thickness: int = 1, y_range=None) -> None:
        ok = np.isfinite(x) & np.isfinite(y)
        for run in np.split(np.flatnonzero(ok), np.flatnonzero(np.diff(np.flatnonzero(ok)) > 1) + 1):  # NaN gaps break the line
            if len(run) > 1:
                pts = np.array([self.px(a, b, y_range) for a, b in zip(x[run], y[run])], np.int32)
                cv2.polylines(self.img, [pts], False, colour, thickness, cv2.LINE_AA)

    def vline(self, x: float, colour, label: str = "", row: int = 0, thickness: int = 1) -> None:
        if not self.xr[0] <= x <= self.xr[1]:
            return
        px = self.px(x, self.yr[0])[0]
        cv2.line(self.img, (px, self.y1), (px, self.y0), colour, thickness)
        if label:
            cv2.putText(self.img, label, (px + 3, self.y1 + 14 + 14 * row), FONT, 0.4, colour, 1, cv2.LINE_AA)


def _zscore(x: np.ndarray) -> np.ndarray:
    ok = np.isfinite(x)
    return (x - x[ok].mean()) / (x[ok].std() or 1.0) if ok.any() else x


def _wrap(text: str, width: int = 130) -> list[str]:
    lines, line = [], ""
    for word in text.split():
        if len(line) + len(word) + 1 > width:
            lines.append(line)
            line = word
        else:
            line = f"{line} {word}".strip()
    return lines + [line]


def write_sync_plot(path: str | Path, curve, estimate, used_s: float, recorded_s: float) -> Path:
    """Draw ``curve`` (``clock_sync.CorrelationCurve``) and ``estimate`` (``ClockOffsetEstimate``)
    into a PNG at ``path``; ``used_s``: the offset the solve used, ``recorded_s``: the session's."""
    title = _wrap(f"clock offset: auto {estimate.summary()}; used {used_s:+.3f} s")
    head = 14 + 16 * len(title)
    img = np.full((head + 2 * PANEL_H + 10, WIDTH, 3), 255, np.uint8)
    for i, line in enumerate(title):
        cv2.putText(img, line, (8, 18 + 16 * i), FONT, 0.42, BLACK, 1, cv2.LINE_AA)

    m_t, m = curve.marker_t, _zscore(curve.marker_signal)
    p_t, p = curve.prior_t + used_s, _zscore(curve.prior_signal)  # the prior's signal on the marker clock
    x_range = (min(m_t[0], p_t[0]), max(m_t[-1], p_t[-1]))
    both = np.concatenate([m[np.isfinite(m)], p[np.isfinite(p)]])
    top = _Axes(img, head, x_range, (float(both.min()), float(both.max())), "marker clock (s)")
    top.line(m_t, m, BLUE, 2)
    top.line(p_t, p, ORANGE, 1)
    # z-scores hide how much each stream moves at all: a near-still take's bumps are noise
    sd_m, sd_p = np.nanstd(curve.marker_signal), np.nanstd(curve.prior_signal)
    cv2.putText(img, f"markers (sd {sd_m:.2f} m/s)", (MARGIN_L + 6, top.y1 + 14), FONT, 0.45, BLUE, 1, cv2.LINE_AA)
    cv2.putText(img, f"video prior, moved by {used_s:+.3f} s (sd {sd_p:.2f} m/s)", (MARGIN_L + 200, top.y1 + 14), FONT, 0.45, ORANGE, 1,
                cv2.LINE_AA)
    cv2.putText(img, "articulation speed (z-score)", (MARGIN_L, top.y1 - 6), FONT, 0.42, BLACK, 1, cv2.LINE_AA)

    o, r = curve.offsets_s, curve.correlation
    finite = r[np.isfinite(r)]
    lo, hi = (float(finite.min()), float(finite.max())) if len(finite) else (-1.0, 1.0)
    bottom = _Axes(img, head + PANEL_H, (float(o[0]), float(o[-1])), (min(lo, 0.0), max(hi, 0.1)), "offset: marker time - video time (s)")
    bottom.line(o, r, BLACK, 1)
    for value in sorted({round(bottom.yr[0], 2), 0.0, round(bottom.yr[1], 2)}):
        y = bottom.px(o[0], value)[1]
        cv2.putText(img, f"{value:.2f}", (MARGIN_L - 40, y + 4), FONT, 0.4, BLACK, 1, cv2.LINE_AA)
    cv2.putText(img, "motion correlation", (MARGIN_L, bottom.y1 - 6), FONT, 0.42, BLACK, 1, cv2.LINE_AA)
    for c in estimate.candidates_s:  # the correlation peaks the fit judged and did not pick
        if estimate.correlation_offset_s is None or abs(c - estimate.correlation_offset_s) > 1e-6:
            bottom.vline(c, GREY, "other peak", row=2)
    bottom.vline(recorded_s, RED, f"recorded {recorded_s:+.3f}", row=1)
    bottom.vline(estimate.offset_s, GREEN, f"found {estimate.offset_s:+.3f}", thickness=2)
    if estimate.fit_points:  # the fit's scale on the right
        fo, fr = np.array(estimate.fit_points).T
        f_range = (0.0, float(fr.max()) * 1.05)  # from zero: a flat fit must look flat
        for a, b in zip(fo, fr):
            cv2.circle(img, bottom.px(a, b, f_range), 3, PURPLE, -1, cv2.LINE_AA)
        for value in (f_range[1] / 2, f_range[1]):
            y = bottom.px(o[0], value, f_range)[1]
            cv2.putText(img, f"{value:.0f}", (bottom.x1 + 4, y + 4), FONT, 0.4, PURPLE, 1, cv2.LINE_AA)
        cv2.putText(img, "body fit RMS mm (dots)", (bottom.x1 - 190, bottom.y1 - 6), FONT, 0.42, PURPLE, 1, cv2.LINE_AA)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), img):
        raise OSError(f"could not write {path}")
    return path
