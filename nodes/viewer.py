"""viewer: latest-only look at the graph -- a PNG of the newest skeleton + markers and/or a status line.

Every input uses the ``latest`` queue policy: a slow viewer skips frames (counted as superseded) and
never slows the graph down. Drawing is an orthographic front view: horizontal = the first
non-vertical world axis, vertical = the capture's up axis.  With a namer in the graph the markers are
drawn from ``markers/named`` (the frames the solver solved: their slots are the body's), named.
"""

from __future__ import annotations

import os
import sys
import time
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from .base import LATEST, Node, Port

AXES = {"x": 0, "y": 1, "z": 2}


@dataclass(frozen=True)
class ViewerConfig:
    out_png: str = ""  # '' = no image
    period_s: float = 0.5
    status: bool = True  # print a status line to stderr every period
    size: int = 480  # image height and width in pixels

    def __post_init__(self):
        if self.period_s <= 0 or self.size < 64:
            raise ValueError("period_s > 0 and size >= 64 are required")
        if self.out_png and not self.out_png.endswith(".png"):
            raise ValueError(f"parameter 'out_png' must end in .png, got {self.out_png!r}")


def project(points: np.ndarray, up_axis: str) -> np.ndarray:
    """(N,3) world -> (N,2) [horizontal, vertical] for a front view."""
    up = AXES[up_axis[-1]]
    horizontal = next(a for a in range(3) if a != up)
    sign = -1.0 if up_axis.startswith("-") else 1.0
    return np.stack([points[:, horizontal], sign * points[:, up]], axis=1)


class Viewer(Node):
    Config = ViewerConfig
    SUBSCRIBES = {
        "solved": Port("body/solved", types=("SolvedFrame",), policy=LATEST, optional=True),
        "markers": Port("markers/raw", types=("MarkerFrame",), policy=LATEST, optional=True),
        "named": Port("markers/named", types=("MarkerFrame",), policy=LATEST, optional=True),
    }

    def setup(self) -> None:
        from uuomocap.solver_core.body_model import SMPL_PARENTS

        self.parents = SMPL_PARENTS
        self.timer_s = self.config.period_s
        self.solved = self.markers = None
        self.latency_ms = {"solved": float("nan"), "markers": float("nan")}
        self.frames_drawn, self._estimate_at, self._last_status, self._last_print = 0, -1e9, "", -1e9
        # frame_index -> MarkerFrame (the ones not skipped), of markers/raw and of markers/named
        self._recent, self._named = OrderedDict(), OrderedDict()

    def on_solved(self, msg, env) -> None:
        if msg.kind == "revised":
            return  # a past frame re-solved after a lock upgrade, for the recording: the view stays live
        now = time.monotonic()
        if msg.kind == "estimate":
            self._estimate_at = now
        elif now - self._estimate_at < 1.0:
            return  # estimates flow: show the newest frame, not one a fixed lag behind it
        self.solved = msg
        self.latency_ms["solved"] = (time.monotonic_ns() - env.publish_ns) / 1e6

    def on_markers(self, msg, env) -> None:
        self.markers = msg
        self._keep(self._recent, msg)
        self.latency_ms["markers"] = (time.monotonic_ns() - env.publish_ns) / 1e6

    def on_named(self, msg, env) -> None:
        self._keep(self._named, msg)

    @staticmethod
    def _keep(recent: OrderedDict, msg, size: int = 256) -> None:
        recent[msg.frame_index] = msg
        while len(recent) > size:
            recent.popitem(last=False)

    def drawn_markers(self):
        """The markers of the drawn solved frame when the viewer kept them (named ones first), else
        the newest: a body drawn over another frame's markers looks off by however far the subject
        moved between them."""
        if self.solved is not None:
            for recent in (self._named, self._recent):
                if self.solved.frame_index in recent:
                    return recent[self.solved.frame_index]
        return self.markers

    def on_timer(self) -> None:
        if self.config.status:
            line, now = self.status_line(), time.monotonic()
            if line != self._last_status or now - self._last_print >= 5.0:  # quiet while nothing arrives
                print(line, file=sys.stderr, flush=True)
                self._last_status, self._last_print = line, now
        if self.config.out_png and (self.solved is not None or self.markers is not None):
            self.draw(self.config.out_png)

    def status_line(self) -> str:
        parts = [f"[{self.name}]"]
        m, s = self.markers, self.solved
        if m is not None:
            parts.append(f"markers #{m.frame_index} {int(m.visible.sum())}/{len(m.visible)} seen, {self.latency_ms['markers']:.1f} ms")
        if self._named:  # the namer's newest frame: how many of its seen markers carry a name
            nm = next(reversed(self._named.values()))
            parts.append(f"named {sum(bool(name) and seen for name, seen in zip(nm.labels, nm.visible))}")
        if s is not None:
            parts.append(f"solved #{s.frame_index} {s.kind} residual {s.residual_m * 1000:.1f} mm, {self.latency_ms['solved']:.1f} ms")
        parts.append(f"skipped {sum(st.superseded for st in self._sub.stats.values()) if self._sub else 0}")
        return " | ".join(parts)

    def draw(self, path: str) -> None:
        import cv2

        markers = self.drawn_markers()
        up = markers.up_axis if markers is not None else "+z"
        pts = [project(np.asarray(markers.positions[markers.visible], np.float64), up)] if markers is not None else []
        pts += [project(np.asarray(self.solved.joints, np.float64), up)] if self.solved is not None else []
        allp = np.concatenate(pts) if pts else np.zeros((0, 2))
        allp = allp[np.isfinite(allp).all(axis=1)]
        n = self.config.size
        img = np.full((n, n, 3), 255, np.uint8)
        if len(allp):
            lo, hi = allp.min(axis=0), allp.max(axis=0)
            centre, scale = (lo + hi) / 2, 0.9 * n / max(float((hi - lo).max()), 0.5)
            px = lambda p: (int(n / 2 + (p[0] - centre[0]) * scale), int(n / 2 - (p[1] - centre[1]) * scale))  # noqa: E731
            if markers is not None:
                names = [name for name, seen in zip(markers.labels, markers.visible) if seen] if markers.labels else []
                for k, p in enumerate(pts[0]):
                    if np.isfinite(p).all():
                        x, y = px(p)
                        cv2.circle(img, (x, y), 3, (40, 40, 220), -1)
                        if k < len(names) and names[k]:
                            cv2.putText(img, names[k], (x + 4, y - 3), cv2.FONT_HERSHEY_SIMPLEX, 0.3, (160, 60, 20), 1)
            for child, parent in enumerate(self.parents if self.solved is not None else []):
                if parent >= 0:
                    cv2.line(img, px(pts[-1][parent]), px(pts[-1][child]), (40, 140, 40), 2)
        cv2.putText(img, self.status_line()[len(self.name) + 5:][:70], (5, n - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1)
        cv2.imwrite(path + ".tmp.png", img)
        os.replace(path + ".tmp.png", path)  # a reader never sees half a PNG
        self.frames_drawn += 1
