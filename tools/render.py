"""Render a posed body to images / ``video.mp4`` with a small vectorised z-buffer rasterizer.

Purpose: synthetic sessions need a video that a real person detector and pose estimator
(BlazePose) can run on, so the figure is shaded (Lambert + ambient, smooth normals),
dressed in clothing-like colours by skinning region (skin head/forearms/hands, shirt
torso/upper arms, trousers legs, dark shoes, hair), stands on a lit floor with a soft
contact shadow, in front of a neutral wall.

Rasterizer: faces are grouped by the size of their pixel bounding box; each group tests
all pixels of its (padded) boxes at once with edge functions, interpolates depth
perspective-correctly, and the nearest fragment per pixel wins (one lexsort).  No Python
loop runs per face or per pixel, so a low-resolution body renders in a few milliseconds.
OpenCV only encodes the frames (mp4v; H.264 is not available in opencv-python wheels).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from uuomocap.solver_core.camera import PinholeCamera
from uuomocap.solver_core.motions import up_index

# Albedo (RGB, 0..1) of the clothing regions.
SKIN = (0.87, 0.66, 0.54)
SHIRT = (0.18, 0.36, 0.70)
TROUSERS = (0.20, 0.21, 0.27)
SHOES = (0.10, 0.09, 0.09)
HAIR = (0.16, 0.11, 0.07)
FLOOR = (0.62, 0.60, 0.55)
FLOOR_ALT = (0.56, 0.545, 0.50)
WALL_TOP = (0.80, 0.82, 0.84)
WALL_BOTTOM = (0.70, 0.71, 0.72)

# Dominant joint -> region (SMPL joint order).
_JOINT_REGION = {
    0: TROUSERS, 1: TROUSERS, 2: TROUSERS, 4: TROUSERS, 5: TROUSERS,
    7: SHOES, 8: SHOES, 10: SHOES, 11: SHOES,
    3: SHIRT, 6: SHIRT, 9: SHIRT, 13: SHIRT, 14: SHIRT, 16: SHIRT, 17: SHIRT,
    12: SKIN, 15: SKIN, 18: SKIN, 19: SKIN, 20: SKIN, 21: SKIN, 22: SKIN, 23: SKIN,
}


def vertex_albedo(model) -> np.ndarray:
    """(N, 3) clothing colours from each vertex's dominant joint; hair on the skull's top/back."""
    from uuomocap.solver_core.parts import vertex_dominant_joint

    dom = np.asarray(vertex_dominant_joint(model))
    col = np.array([_JOINT_REGION.get(int(j), SHIRT) for j in range(24)], dtype=np.float32)[dom]
    v = model.v_template.numpy()
    head = model.J_regressor.numpy()[15] @ v
    rel = v - head
    # Canonical axes: +Y up, +Z front.  Hair covers the top and back of the head, not the face.
    hair = (dom == 15) & (rel[:, 1] > 0.045 - 0.5 * np.clip(-rel[:, 2], 0, None)) & ~((rel[:, 2] > 0.045) & (rel[:, 1] < 0.11))
    col[hair] = HAIR
    return col


def vertex_normals_np(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N, 3), (F, 3) -> (N, 3) area-weighted unit vertex normals."""
    tri = vertices[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    vn = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(vn, faces[:, k], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)


@dataclass
class Fragments:
    """Visible surface per covered pixel (sparse): pixel (P,) flat index y*W+x, face (P,),
    bary (P, 3) perspective-correct barycentrics, depth (P,) camera z."""

    pixel: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    depth: np.ndarray
    width: int
    height: int

    def face_image(self) -> np.ndarray:
        """(H, W) face id per pixel, -1 for background."""
        img = np.full(self.height * self.width, -1, dtype=np.int64)
        img[self.pixel] = self.face
        return img.reshape(self.height, self.width)


def rasterize(uv: np.ndarray, depth: np.ndarray, faces: np.ndarray, width: int, height: int,
              near: float = 0.05) -> Fragments:
    """Z-buffer rasterization of a triangle mesh.

    uv: (N, 2) pixel coordinates (pixel centres at integers), depth: (N,) camera z, faces (F, 3).
    Triangles with a vertex behind ``near`` are dropped (the body is always in front).
    """
    uv = np.asarray(uv, dtype=np.float32)
    tri = uv[faces]                                       # (F, 3, 2)
    tz = np.asarray(depth, dtype=np.float32)[faces]       # (F, 3)
    x0, y0 = tri[:, 0, 0], tri[:, 0, 1]
    x1, y1 = tri[:, 1, 0], tri[:, 1, 1]
    x2, y2 = tri[:, 2, 0], tri[:, 2, 1]
    area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
    xmin = np.ceil(tri[..., 0].min(1)).astype(np.int64).clip(0, width)
    xmax = np.floor(tri[..., 0].max(1)).astype(np.int64).clip(-1, width - 1)
    ymin = np.ceil(tri[..., 1].min(1)).astype(np.int64).clip(0, height)
    ymax = np.floor(tri[..., 1].max(1)).astype(np.int64).clip(-1, height - 1)
    ok = (tz.min(1) > near) & (np.abs(area) > 1e-6) & (xmax >= xmin) & (ymax >= ymin)
    size = np.maximum(xmax - xmin + 1, ymax - ymin + 1)
    pix_l, z_l, f_l, b_l = [], [], [], []
    bucket = 1
    while True:
        sel = np.nonzero(ok & (size <= bucket) & (size > bucket // 2))[0]
        if sel.size:
            d = np.arange(bucket)
            shape = (sel.size, bucket, bucket)
            px = np.broadcast_to(xmin[sel, None, None] + d[None, None, :], shape).reshape(sel.size, -1)
            py = np.broadcast_to(ymin[sel, None, None] + d[None, :, None], shape).reshape(sel.size, -1)
            valid = (px <= xmax[sel, None]) & (py <= ymax[sel, None])
            fx, fy = px.astype(np.float32), py.astype(np.float32)
            a = area[sel, None]
            w0 = ((x1[sel, None] - fx) * (y2[sel, None] - fy) - (x2[sel, None] - fx) * (y1[sel, None] - fy)) / a
            w1 = ((x2[sel, None] - fx) * (y0[sel, None] - fy) - (x0[sel, None] - fx) * (y2[sel, None] - fy)) / a
            w2 = 1.0 - w0 - w1
            inside = valid & (w0 >= -1e-6) & (w1 >= -1e-6) & (w2 >= -1e-6)
            fi, pi = np.nonzero(inside)
            if fi.size:
                f = sel[fi]
                W = np.stack([w0[fi, pi], w1[fi, pi], w2[fi, pi]], -1)
                invz = W / tz[f]                              # perspective-correct
                z = 1.0 / invz.sum(1)
                pix_l.append(py[fi, pi] * width + px[fi, pi])
                z_l.append(z)
                f_l.append(f)
                b_l.append(invz * z[:, None])
        if bucket >= max(width, height) * 2 or not (ok & (size > bucket)).any():
            break
        bucket *= 2
    if not pix_l:
        e = np.zeros(0, dtype=np.int64)
        return Fragments(e, e, np.zeros((0, 3), np.float32), np.zeros(0, np.float32), width, height)
    pix, z, f, b = (np.concatenate(x) for x in (pix_l, z_l, f_l, b_l))
    order = np.lexsort((z, pix))
    ps = pix[order]
    first = np.ones(ps.size, dtype=bool)
    first[1:] = ps[1:] != ps[:-1]
    win = order[first]
    return Fragments(pix[win], f[win], b[win], z[win], width, height)


class BodyRenderer:
    """Renders one body model from one static camera; the background is computed once."""

    def __init__(self, model, camera: PinholeCamera, up_axis: str = "+z"):
        self.model = model
        self.camera = camera
        self.up_axis = up_axis
        self.faces = model.faces.numpy().astype(np.int64)
        self.albedo = vertex_albedo(model)
        ui = up_index(up_axis)
        self.ui = ui
        up = np.zeros(3)
        up[ui] = 1.0
        self.up = up
        # Key light from above, behind the camera and to its left; a dimmer fill from the right.
        cam_back = -camera.R_wc[:, 2]
        cam_left = -camera.R_wc[:, 0]
        key = 1.2 * up + 0.8 * cam_back + 0.5 * cam_left
        self.key = key / np.linalg.norm(key)
        fill = 0.3 * up + 0.6 * cam_back - 0.8 * cam_left
        self.fill = fill / np.linalg.norm(fill)
        self._background()

    def _background(self) -> None:
        cam = self.camera
        H, W = cam.height, cam.width
        v, u = np.mgrid[0:H, 0:W].astype(np.float64)
        rays = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1) @ cam.R_wc.T
        d_up = rays[..., self.ui]
        h = cam.position[self.ui]
        t = np.where(d_up < -1e-6, -h / np.minimum(d_up, -1e-6), np.inf)
        on_floor = t < 40.0
        floor_pt = cam.position + rays * np.where(on_floor, t, 0.0)[..., None]
        # Wall: vertical gradient; floor: 1 m tiles, darkening slightly with distance.
        frac = np.clip(v / max(H - 1, 1), 0, 1)[..., None]
        img = np.array(WALL_TOP) * (1 - frac) + np.array(WALL_BOTTOM) * frac
        hi = [i for i in range(3) if i != self.ui]
        tiles = (np.floor(floor_pt[..., hi[0]]) + np.floor(floor_pt[..., hi[1]])) % 2 == 0
        floor_col = np.where(tiles[..., None], np.array(FLOOR), np.array(FLOOR_ALT))
        fade = np.clip(1.0 - t / 60.0, 0.55, 1.0)[..., None]
        img = np.where(on_floor[..., None], floor_col * fade, img)
        self.background = img.astype(np.float32)
        self.floor_mask = on_floor
        floor_xy = np.where(on_floor[..., None], floor_pt[..., hi], 1e3).astype(np.float32)
        self.floor_xy_small = np.ascontiguousarray(floor_xy[2::4, 2::4])

    def render(self, vertices: np.ndarray, feet: np.ndarray | None = None) -> np.ndarray:
        """vertices (N, 3) world metres -> BGR uint8 image (H, W, 3).

        feet: optional (K, 3) world points (e.g. ankles, pelvis) under which a soft contact
        shadow darkens the floor (computed at 1/4 resolution: it is blurry anyway).
        """
        cam = self.camera
        img = self.background.copy()
        if feet is not None:
            hi = [i for i in range(3) if i != self.ui]
            shade = np.zeros(self.floor_xy_small.shape[:2], dtype=np.float32)
            for p in np.asarray(feet):
                height = max(float(p[self.ui]), 0.0)
                sigma = 0.18 + 0.15 * height
                d2 = ((self.floor_xy_small - p[hi].astype(np.float32)) ** 2).sum(-1)
                shade = np.maximum(shade, np.exp(-d2 / (2 * sigma * sigma)) * (0.45 / (1.0 + 2.0 * height)))
            shade = cv2.resize(shade, (cam.width, cam.height), interpolation=cv2.INTER_LINEAR)
            img *= (1.0 - shade * self.floor_mask)[..., None]
        uv, z = cam.project(vertices)
        frag = rasterize(uv, z, self.faces, cam.width, cam.height)
        if frag.pixel.size:
            b = frag.bary.astype(np.float64)
            corners = self.faces[frag.face]                               # (P, 3)
            vn = vertex_normals_np(vertices, self.faces)
            n = (vn[corners] * b[..., None]).sum(1)
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
            # Normals facing away from the camera (silhouette interpolation) are flipped.
            pts = (vertices[corners] * b[..., None]).sum(1)
            view = cam.position - pts
            n = np.where(((n * view).sum(1) < 0)[:, None], -n, n)
            alb = (self.albedo[corners] * b[..., None]).sum(1)
            light = 0.32 + 0.58 * np.clip(n @ self.key, 0, None) + 0.22 * np.clip(n @ self.fill, 0, None)
            img.reshape(-1, 3)[frag.pixel] = np.clip(alb * light[:, None], 0, 1)
        return np.ascontiguousarray((img[..., ::-1] * 255.0 + 0.5).astype(np.uint8))


def render_video(model, betas: np.ndarray, poses: np.ndarray, trans: np.ndarray, camera: PinholeCamera,
                 path: str | Path, fps: float, up_axis: str = "+z", supersample: int = 1, progress=None) -> dict:
    """Render posed frames to an mp4v ``path``.

    betas (B,), poses (K, 72) world axis-angle, trans (K, 3): one video frame each.
    supersample: render at k x resolution and area-downsample (anti-aliasing).
    Returns {"frames", "seconds_per_frame"}.
    """
    import time

    import torch

    from uuomocap.solver_core.lbs import forward

    path = Path(path)
    cam = camera.scaled(camera.width * supersample, camera.height * supersample) if supersample > 1 else camera
    renderer = BodyRenderer(model, cam, up_axis)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (camera.width, camera.height))
    if not writer.isOpened():
        raise RuntimeError(f"OpenCV cannot open an mp4v writer for {path}")
    t0 = time.perf_counter()
    b = torch.as_tensor(np.asarray(betas, dtype=np.float32)).reshape(1, -1)
    try:
        for s in range(0, poses.shape[0], 64):
            with torch.no_grad():
                out = forward(model, b, torch.as_tensor(poses[s:s + 64], dtype=torch.float32),
                              torch.as_tensor(trans[s:s + 64], dtype=torch.float32))
            verts = out.vertices.double().numpy()
            joints = out.joints.double().numpy()
            for k in range(verts.shape[0]):
                frame = renderer.render(verts[k], feet=joints[k, [7, 8, 10, 11, 0]])
                if supersample > 1:
                    frame = cv2.resize(frame, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
                writer.write(frame)
                if progress is not None:
                    progress.update(1)
    finally:
        writer.release()
    n = poses.shape[0]
    return {"frames": int(n), "seconds_per_frame": (time.perf_counter() - t0) / max(n, 1)}


# ----------------------------------------------------------------------------- solve contact sheet

# Marker colours (BGR) by the body part they were labelled with; unlabelled markers are red.
_PART_BGR = ((200, 120, 0), (0, 160, 0), (170, 0, 170), (0, 150, 200), (120, 60, 0), (0, 110, 90), (140, 140, 0),
             (60, 60, 160), (0, 90, 200), (110, 0, 90), (80, 160, 80), (160, 80, 40))
UNLABELLED_BGR = (0, 0, 230)


def view_azimuth(facing: np.ndarray, up_axis: str) -> float:
    """Azimuth (``place_camera``'s convention) of a camera that looks against ``facing`` (3,): at
    the front of a body facing that way."""
    ui = up_index(up_axis)
    up = np.zeros(3)
    up[ui] = 1.0
    view = -(np.asarray(facing, np.float64) - up * facing[ui])
    if np.linalg.norm(view) < 1e-6:
        return 0.0
    fwd0 = np.array([0.0, 1.0, 0.0]) if up_axis == "+z" else np.array([0.0, 0.0, 1.0])
    return float(np.arctan2(np.dot(up, np.cross(fwd0, view)), np.dot(fwd0, view)))


def facing_azimuth(root_orient: np.ndarray, up_axis: str) -> float:
    """``view_azimuth`` of a pelvis orientation (3,) world axis-angle (SMPL: the body faces its local +z)."""
    from uuomocap.solver_core.motions import axis_angle_to_matrices

    return view_azimuth(axis_angle_to_matrices(np.asarray(root_orient, np.float64))[:, 2], up_axis)


def mean_facing_azimuth(root_orient: np.ndarray, up_axis: str) -> float:
    """``view_azimuth`` of the take's mean facing (root_orient (F, 3))."""
    from uuomocap.solver_core.motions import axis_angle_to_matrices

    return view_azimuth(axis_angle_to_matrices(np.asarray(root_orient, np.float64))[:, :, 2].mean(axis=0), up_axis)


def part_palette(marker_parts: list[str] | None) -> dict[str, tuple[int, int, int]]:
    """A BGR colour per labelled part name (sorted, so the same parts get the same colours)."""
    palette: dict[str, tuple[int, int, int]] = {}
    for name in sorted(set(marker_parts or [])):
        if name:
            palette[name] = _PART_BGR[len(palette) % len(_PART_BGR)]
    return palette


def draw_overlays(img: np.ndarray, cam: PinholeCamera, markers: np.ndarray | None = None, marker_points: np.ndarray | None = None,
                  marker_parts: list[str] | None = None, palette: dict | None = None, gt_joints: np.ndarray | None = None,
                  label: str = "") -> np.ndarray:
    """Draw one frame's markers (M, 3) (NaN = unseen; dots by part, red ring = unlabelled), the line
    from each to its solved surface point (M, 3), the reference skeleton (24, 3) in white and a
    label onto ``img`` (BGR, in place) as ``cam`` sees them."""
    from uuomocap.solver_core.body_model import SMPL_PARENTS

    def px(p):
        uv, z = cam.project(np.asarray(p, np.float64))
        return (int(round(uv[0])), int(round(uv[1]))) if z > 0 and np.isfinite(uv).all() else None

    if gt_joints is not None:
        for child, parent in enumerate(SMPL_PARENTS):
            if parent < 0:
                continue
            a, b = px(gt_joints[parent]), px(gt_joints[child])
            if a and b:
                cv2.line(img, a, b, (255, 255, 255), 1, cv2.LINE_AA)
    if markers is not None:
        palette = palette if palette is not None else part_palette(marker_parts)
        for m in range(markers.shape[0]):
            if not np.isfinite(markers[m]).all():
                continue
            a = px(markers[m])
            if a is None:
                continue
            colour = palette.get(marker_parts[m] if marker_parts is not None else "", UNLABELLED_BGR)
            if marker_points is not None and np.isfinite(marker_points[m]).all():
                b = px(marker_points[m])
                if b:
                    cv2.line(img, a, b, (0, 220, 255), 1, cv2.LINE_AA)
            cv2.circle(img, a, 3, colour, -1, cv2.LINE_AA)
            if colour == UNLABELLED_BGR:
                cv2.circle(img, a, 5, colour, 1, cv2.LINE_AA)
    if label:
        cv2.putText(img, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (20, 20, 20), 1, cv2.LINE_AA)
    return img


def marker_surface_points(model, vertices: np.ndarray, faces: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Posed surface points (..., M, 3) of markers labelled with face ``faces`` (M,) (-1 =
    unlabelled: NaN) and barycentric ``bary`` (M, 3) on ``vertices`` (..., N, 3)."""
    faces = np.asarray(faces, dtype=np.int64)
    ok = faces >= 0
    tri = model.faces.numpy()[np.where(ok, faces, 0)]  # (M, 3)
    points = (vertices[..., tri, :] * np.asarray(bary, np.float64)[:, :, None]).sum(-2)
    return np.where(ok[:, None], points, np.nan)


def _frame(a: np.ndarray | None, f: int) -> np.ndarray | None:
    return None if a is None else a[f]


def contact_sheet(model, vertices: np.ndarray, joints: np.ndarray, root_orient: np.ndarray,
                  up_axis: str = "+z", markers: np.ndarray | None = None, marker_points: np.ndarray | None = None,
                  marker_parts: list[str] | None = None, gt_joints: np.ndarray | None = None,
                  captions: list[str] | None = None, tile: tuple[int, int] = (240, 320), title: str = "") -> np.ndarray:
    """A BGR image: one column per frame, rows = front and side views of the solved body.

    vertices (K, N, 3), joints (K, 24, 3), root_orient (K, 3): the K frames to draw, world metres /
    axis-angle.  markers (K, M, 3) with NaN where unseen, marker_points (K, M, 3) their solved
    surface points, gt_joints (K, 24, 3) the reference: ``draw_overlays``.  Each tile's camera is
    placed for its own frame (``place_camera``), facing the body (front) and from its left (side).
    """
    from uuomocap.solver_core.camera import place_camera

    w, h = tile
    palette = part_palette(marker_parts)
    rows = []
    for side in (0.0, 0.5 * np.pi):
        tiles = []
        for f in range(len(vertices)):
            az = facing_azimuth(root_orient[f], up_axis) + side
            cam = place_camera(joints[f, :1], up_axis, az, w, h, vfov_deg=32.0, camera_height_m=1.0, body_height_m=1.9)
            img = BodyRenderer(model, cam, up_axis).render(vertices[f], feet=joints[f, [7, 8, 10, 11, 0]])
            label = (captions[f] if captions else f"frame {f}") + ("" if side == 0.0 else " (side)")
            tiles.append(draw_overlays(img, cam, _frame(markers, f), _frame(marker_points, f), marker_parts, palette,
                                       _frame(gt_joints, f), label))
        rows.append(np.concatenate(tiles, axis=1))
    sheet = np.concatenate(rows, axis=0)
    if title:
        strip = np.full((22, sheet.shape[1], 3), 255, np.uint8)
        cv2.putText(strip, title[: sheet.shape[1] // 7], (4, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        sheet = np.concatenate([strip, sheet], axis=0)
    return sheet


def solve_video(model, betas: np.ndarray, poses: np.ndarray, trans: np.ndarray, joints: np.ndarray, path: str | Path,
                fps: float, up_axis: str = "+z", markers: np.ndarray | None = None, marker_faces: np.ndarray | None = None,
                marker_bary: np.ndarray | None = None, marker_parts: list[str] | None = None,
                gt_joints: np.ndarray | None = None, captions: dict[int, str] | None = None, size: tuple[int, int] = (640, 480),
                frames: np.ndarray | None = None, progress=None) -> dict:
    """An mp4v video of a solve from one fixed camera facing the body's mean facing, with the overlays
    of ``draw_overlays`` on every frame.  betas (B,) or (F, B); poses (F, 72), trans (F, 3), joints
    (F, 24, 3); markers (F, M, 3) NaN where unseen; marker_faces (M,) (-1 = unlabelled) and
    marker_bary (M, 3) the solved surface points; captions: per drawn frame index; frames: the
    indices to draw (default all).
    Vertices are posed 64 frames at a time, so memory does not grow with the take."""
    from uuomocap.solver_core.camera import place_camera
    from uuomocap.solver_core.metrics import posed_vertices

    idx = np.arange(poses.shape[0]) if frames is None else np.asarray(frames, dtype=np.int64)
    w, h = size
    cam = place_camera(joints[idx, 0], up_axis, mean_facing_azimuth(poses[idx, :3], up_axis), w, h, vfov_deg=40.0,
                       camera_height_m=1.0, body_height_m=1.9)
    renderer = BodyRenderer(model, cam, up_axis)
    palette = part_palette(marker_parts)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
    if not writer.isOpened():
        raise RuntimeError(f"OpenCV cannot open an mp4v writer for {path}")
    b_all = np.asarray(betas, np.float64)
    try:
        for s in range(0, len(idx), 64):
            chunk = idx[s:s + 64]
            verts = posed_vertices(model, b_all[chunk] if b_all.ndim == 2 else b_all, poses[chunk], trans[chunk])
            for k, f in enumerate(chunk):
                img = renderer.render(verts[k], feet=joints[f, [7, 8, 10, 11, 0]])
                points = marker_surface_points(model, verts[k], marker_faces, marker_bary) if marker_faces is not None else None
                writer.write(draw_overlays(img, cam, _frame(markers, f), points, marker_parts, palette, _frame(gt_joints, f),
                                           captions[f] if captions else f"frame {f}"))
                if progress is not None:
                    progress(1)
    finally:
        writer.release()
    return {"frames": int(len(idx)), "width": w, "height": h, "fps": float(fps)}
