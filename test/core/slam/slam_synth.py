"""A seeded synthetic desk scene for the SLAM front-end tests: exact ray-cast images and poses.

World frame: the desk is the plane z = 0 (z up), textured over a square; a couple of textured
boxes stand on it. Cameras are given as ``R_c_w, t_c_w`` (world -> camera, camera_optical).
Rendering ray-casts every (optionally supersampled) pixel against every planar rectangle and
samples its texture with ``cv2.remap``; nearest hit wins. Textures are random multi-scale
rectangles and blobs so the scene has Shi-Tomasi corners at several pyramid levels.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ar_tracking.core.slam.camera import Camera


def make_texture(rng: np.random.Generator, h: int, w: int, n_rects: int = 900) -> np.ndarray:
    """Random rectangles of many sizes over smooth noise, float32 in [0, 255]."""
    base = rng.random((max(2, h // 64), max(2, w // 64))).astype(np.float32)
    tex = cv2.resize(base, (w, h), interpolation=cv2.INTER_CUBIC) * 80 + 90
    for _ in range(n_rects):
        s = int(np.exp(rng.uniform(np.log(4), np.log(max(8, min(h, w) / 8)))))
        x0 = int(rng.integers(0, max(1, w - s)))
        y0 = int(rng.integers(0, max(1, h - s)))
        sx = max(2, int(s * rng.uniform(0.5, 1.5)))
        val = float(rng.uniform(0, 255))
        if rng.random() < 0.3:
            cv2.circle(tex, (x0 + s // 2, y0 + s // 2), max(2, s // 2), val, -1)
        else:
            tex[y0:y0 + s, x0:x0 + sx] = val
    tex = cv2.GaussianBlur(tex, (0, 0), 0.8)
    return np.clip(tex, 0, 255).astype(np.float32)


@dataclass
class Face:
    origin: np.ndarray  # corner (3,)
    a: np.ndarray  # edge along texture x (3,)
    b: np.ndarray  # edge along texture y (3,)
    texture: np.ndarray  # float32 (th, tw)
    normal: np.ndarray = None  # outward unit normal (3,)


class DeskScene:
    """Textured desk plane plus boxes; ``render(camera, R_c_w, t_c_w)`` gives a uint8 image."""

    def __init__(self, seed: int = 0, desk_size: float = 1.2, texels_per_m: float = 1000.0,
                 boxes: bool = True) -> None:
        rng = np.random.default_rng(seed)
        n = int(desk_size * texels_per_m)
        self.faces: list[Face] = []
        half = desk_size / 2
        self.faces.append(Face(np.array([-half, -half, 0.0]), np.array([desk_size, 0, 0.0]),
                               np.array([0, desk_size, 0.0]), make_texture(rng, n, n, n_rects=n * n // 600),
                               np.array([0, 0, 1.0])))
        self.boxes: list[tuple[np.ndarray, np.ndarray]] = []
        if boxes:
            for centre, size in (((0.12, -0.08), (0.10, 0.08, 0.07)), ((-0.15, 0.10), (0.08, 0.12, 0.05))):
                self._add_box(rng, np.array([centre[0], centre[1]]), np.array(size), texels_per_m)

    def _add_box(self, rng: np.random.Generator, c: np.ndarray, size: np.ndarray, tpm: float) -> None:
        sx, sy, sz = size
        x0, y0 = c[0] - sx / 2, c[1] - sy / 2
        p = np.array([x0, y0, 0.0])
        ex, ey, ez = np.array([sx, 0, 0.0]), np.array([0, sy, 0.0]), np.array([0, 0, sz])
        self.boxes.append((p.copy(), size.copy()))

        def tex(la: float, lb: float) -> np.ndarray:
            h, w = max(8, int(lb * tpm)), max(8, int(la * tpm))
            return make_texture(rng, h, w, n_rects=max(20, h * w // 500))
        faces = [
            Face(p + ez, ex, ey, tex(sx, sy)),  # top
            Face(p, ex, ez, tex(sx, sz)),  # y = y0 side
            Face(p + ey, ex, ez, tex(sx, sz)),  # y = y1 side
            Face(p, ey, ez, tex(sy, sz)),  # x = x0 side
            Face(p + ex, ey, ez, tex(sy, sz)),  # x = x1 side
        ]
        centre = p + (ex + ey + ez) / 2
        for f in faces:
            n = np.cross(f.a, f.b)
            n /= np.linalg.norm(n)
            if n @ (f.origin + (f.a + f.b) / 2 - centre) < 0:
                n = -n
            f.normal = n
        self.faces += faces

    def render(self, camera: Camera, R_c_w: np.ndarray, t_c_w: np.ndarray, supersample: int = 1,
               noise_sigma: float = 0.0, rng: np.random.Generator | None = None,
               background: float = 40.0) -> np.ndarray:
        """Image (uint8, camera.height x camera.width) of the scene from a pose.

        Per face: the plane-induced homography warps the texture (``cv2.warpPerspective``); a
        z-buffer of the plane's per-pixel inverse depth (affine in u, v) resolves occlusion.
        """
        s = int(supersample)
        W, H = camera.width * s, camera.height * s
        cam = camera
        K = np.array([[cam.fx * s, 0, (cam.cx + 0.5) * s - 0.5], [0, cam.fy * s, (cam.cy + 0.5) * s - 0.5], [0, 0, 1.0]])
        Kinv = np.linalg.inv(K)
        u, v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
        C = -R_c_w.T @ t_c_w
        best = np.zeros((H, W), np.float32)  # inverse depth of the nearest hit so far
        img = np.full((H, W), background, np.float32)
        for f in self.faces:
            if float((C - f.origin) @ f.normal) <= 0:
                continue  # back face
            G = K @ np.column_stack([R_c_w @ f.a, R_c_w @ f.b, R_c_w @ f.origin + t_c_w])
            Ginv = np.linalg.inv(G)
            A = Ginv  # pixel -> (alpha w, beta w, w)
            w = A[2, 0] * u + A[2, 1] * v + A[2, 2]
            with np.errstate(divide='ignore', invalid='ignore'):
                al = (A[0, 0] * u + A[0, 1] * v + A[0, 2]) / w
                be = (A[1, 0] * u + A[1, 1] * v + A[1, 2]) / w
            # inverse depth of the plane n_c . X = d_c along pixel rays: (n_c . K^-1 x) / d_c
            n_c = R_c_w @ f.normal
            d_c = float(n_c @ (R_c_w @ f.origin + t_c_w))
            q = (Kinv.T @ n_c) / d_c
            invz = (q[0] * u + q[1] * v + q[2]).astype(np.float32)
            hit = (invz > 0) & (al >= 0) & (al <= 1) & (be >= 0) & (be <= 1) & (invz > best)
            if not np.any(hit):
                continue
            th, tw = f.texture.shape
            T = np.array([[tw, 0, -0.5], [0, th, -0.5], [0, 0, 1.0]])
            M = T @ Ginv
            val = cv2.warpPerspective(f.texture, M, (W, H), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                      borderMode=cv2.BORDER_REPLICATE)
            img[hit] = val[hit]
            best[hit] = invz[hit]
        if s > 1:
            img = cv2.resize(img, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
        if noise_sigma > 0:
            rng = rng or np.random.default_rng(0)
            img = img + rng.normal(0, noise_sigma, img.shape).astype(np.float32)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)


    def points_at(self, camera: Camera, R_c_w: np.ndarray, t_c_w: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """World points (N, 3) seen at level-0 pixels ``uv`` (nearest face hit; NaN for none)."""
        uv = np.asarray(uv, float).reshape(-1, 2)
        d = camera.unproject(uv) @ R_c_w  # world directions (rows)
        C = -R_c_w.T @ t_c_w
        best = np.full(len(uv), np.inf)
        out = np.full((len(uv), 3), np.nan)
        for f in self.faces:
            den = d @ f.normal
            with np.errstate(divide='ignore', invalid='ignore'):
                s = float(f.normal @ (f.origin - C)) / den
            P = C + s[:, None] * d
            al = ((P - f.origin) @ f.a) / float(f.a @ f.a)
            be = ((P - f.origin) @ f.b) / float(f.b @ f.b)
            hit = (s > 1e-6) & (al >= 0) & (al <= 1) & (be >= 0) & (be <= 1) & (s < best)
            out[hit] = P[hit]
            best[hit] = s[hit]
        return out


def make_camera(width: int = 320, height: int = 240, hfov_deg: float = 60.0, readout_s: float = 0.0) -> Camera:
    f = width / 2 / np.tan(np.radians(hfov_deg) / 2)
    return Camera(f, f, (width - 1) / 2, (height - 1) / 2, width, height, readout_s)


def rotvec(w: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(w, float).reshape(3, 1))[0]


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pose (R_c_w, t_c_w) of a camera at ``eye`` looking at ``target`` (optical z forward;
    ``up`` default +y)."""
    up = np.array([0, 1.0, 0]) if up is None else up
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, np.array([1.0, 0, 0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R_w_c = np.column_stack([x, y, z])
    R_c_w = R_w_c.T
    return R_c_w, -R_c_w @ np.asarray(eye, float)


def sideways_then_6dof(n_side: int = 30, n_free: int = 60, height: float = 0.5, side: float = 0.10,
                       seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Camera ~0.5 m above the desk looking down-forward: sideways ``side`` metres, then 6-DoF."""
    rng = np.random.default_rng(seed)
    poses = []
    x0 = -side / 2
    for i in range(n_side):
        x = x0 + side * i / max(1, n_side - 1)
        poses.append(look_at(np.array([x, -0.15, height]), np.array([x, 0.0, 0.0])))
    ph = rng.uniform(0, 2 * np.pi, 6)
    for i in range(1, n_free + 1):
        s = i / n_free
        eye = np.array([x0 + side + 0.06 * np.sin(2 * np.pi * s + ph[0]) - 0.06 * np.sin(ph[0]),
                        -0.15 + 0.05 * np.sin(2 * np.pi * s * 0.7 + ph[1]) - 0.05 * np.sin(ph[1]),
                        height + 0.05 * np.sin(2 * np.pi * s * 0.5 + ph[2]) - 0.05 * np.sin(ph[2])])
        target = np.array([eye[0] + 0.05 * np.sin(2 * np.pi * s + ph[3]), 0.03 * np.sin(2 * np.pi * s + ph[4]), 0.0])
        R, t = look_at(eye, target)
        roll = rotvec(np.array([0, 0, 0.15 * np.sin(2 * np.pi * s + ph[5])]))
        poses.append((roll @ R, roll @ t))
    return poses


def umeyama_sim3(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """s, R, t minimising |dst - (s R src + t)|^2 (Umeyama 1991)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / (a ** 2).sum(1).mean())
    return s, R, mu_d - s * R @ mu_s
