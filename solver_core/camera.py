"""A pinhole camera in the OpenCV convention (x right, y down, z forward) for synthetic video.

Used to render ground truth to ``video.mp4`` and to express the simulated video prior in
the camera frame.  The solver never sees this camera: its pose is the unknown the paper's
yaw hypotheses search over.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PinholeCamera:
    """R_wc (3, 3): world-from-camera rotation (its columns are the camera axes in world).
    position (3,): camera centre in world metres.  fx, fy, cx, cy: pixels.  width, height: pixels.
    """

    R_wc: np.ndarray
    position: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def world_to_camera(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) world -> (..., 3) camera frame."""
        return (np.asarray(points) - self.position) @ self.R_wc

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(..., 3) world -> pixel coordinates (..., 2) and depth (..., ) (camera z)."""
        pc = self.world_to_camera(points)
        z = pc[..., 2]
        zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
        uv = np.stack([self.fx * pc[..., 0] / zs + self.cx, self.fy * pc[..., 1] / zs + self.cy], -1)
        return uv, z

    def scaled(self, width: int, height: int) -> "PinholeCamera":
        """The same camera at another resolution (same field of view)."""
        sx, sy = width / self.width, height / self.height
        return PinholeCamera(self.R_wc, self.position, self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5,
                             (self.cy + 0.5) * sy - 0.5, int(width), int(height))


def look_at(position: np.ndarray, target: np.ndarray, up: np.ndarray, roll_rad: float = 0.0) -> np.ndarray:
    """World-from-camera rotation (3, 3) for an OpenCV camera at ``position`` looking at ``target``.

    The camera's x axis is horizontal (perpendicular to ``up``) before ``roll_rad`` turns it
    about the optical axis.
    """
    z = np.asarray(target, dtype=np.float64) - np.asarray(position, dtype=np.float64)
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    n = np.linalg.norm(x)
    if n < 1e-6:
        raise ValueError("camera looks straight along the up axis; look_at is undefined")
    x /= n
    y = np.cross(z, x)
    c, s = math.cos(roll_rad), math.sin(roll_rad)
    x, y = c * x + s * y, -s * x + c * y
    return np.stack([x, y, z], axis=1)


def place_camera(
    pelvis_path: np.ndarray,
    up_axis: str,
    azimuth_rad: float,
    width: int = 640,
    height: int = 480,
    vfov_deg: float = 50.0,
    camera_height_m: float = 1.3,
    roll_rad: float = 0.0,
    body_height_m: float = 1.8,
) -> PinholeCamera:
    """A static camera that keeps a moving person in view, roughly horizontal and upright.

    pelvis_path: (F, 3) world pelvis positions.  azimuth_rad: the camera's viewing direction
    as a turn about the up axis from the level camera the solver assumes (OpenCV axes
    mapped to world x, -up, forward; forward = world +Y for a Z-up world, +Z for a Y-up
    world, see ``prior_preparation.camera_to_world_rotation``).  So the azimuth IS the yaw
    offset between the video prior and the world.  The distance is the smallest that keeps
    the whole path plus the body inside the frame with a margin.
    """
    from .motions import heading_rotation, up_index

    ui = up_index(up_axis)
    up = np.zeros(3)
    up[ui] = 1.0
    fwd0 = np.array([0.0, 1.0, 0.0]) if up_axis == "+z" else np.array([0.0, 0.0, 1.0])
    fwd = heading_rotation(np.array(azimuth_rad), up_axis) @ fwd0
    path = np.asarray(pelvis_path, dtype=np.float64)
    centre = 0.5 * (path.min(0) + path.max(0))
    centre[ui] = 0.0
    horiz = path - centre
    horiz[:, ui] = 0.0
    radius = float(np.linalg.norm(horiz, axis=1).max()) if len(horiz) else 0.0
    tan_v = math.tan(math.radians(vfov_deg) / 2)
    tan_h = tan_v * width / height
    # Nearest approach (distance - radius) must still show the whole body (plus 20 %), and
    # the far sides of the path must fit horizontally with half a metre to spare.
    dist = max(radius + 0.6 * body_height_m / tan_v, (radius + 0.7) / tan_h, 2.5)
    target = centre + up * (0.5 * body_height_m)
    position = centre - fwd * dist + up * camera_height_m
    R = look_at(position, target, up, roll_rad)
    f = 0.5 * height / tan_v
    return PinholeCamera(R, position, f, f, (width - 1) / 2.0, (height - 1) / 2.0, int(width), int(height))
