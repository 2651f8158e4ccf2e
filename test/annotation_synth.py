"""Seeded synthetic panorama maps and annotations for the annotation tests.

A source map of smooth random texture (rows 96..416 mapped), annotations cut from it, and a
target map = the source turned about the cylinder axis by ``shift_px`` columns (a pure rotation
R_target_source = rotation_about_axis_y(shift / f)) with a different gain, offset and noise
(changed lighting)."""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ar_tracking.core.annotations.store import Annotation
from ar_tracking.core.panorama.cylinder import CylinderGeometry, rotation_about_axis_y

GEO = CylinderGeometry()
ROWS = (96, 416)


def texture(seed: int, h: int = 512, w: int = 2048) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w), np.float32)
    for sigma, amp in ((1.0, 40.0), (3.0, 60.0), (8.0, 50.0)):
        n = rng.normal(0, 1, (h, w)).astype(np.float32)
        n = cv2.GaussianBlur(n, (0, 0), sigma, borderType=cv2.BORDER_WRAP if False else cv2.BORDER_REFLECT)
        img += amp * n / n.std()
    return np.clip(img + 128.0, 0, 255)


@dataclass
class Case:
    source: np.ndarray
    target: np.ndarray
    mapped: np.ndarray
    patches: list[np.ndarray]
    dirs: np.ndarray          # (n, 3) in the source panorama
    truth_uv: np.ndarray      # (n, 2) in the target map
    R_target_source: np.ndarray


def make_case(seed: int = 0, n: int = 6, shift_px: int = 300, gain: float = 0.7, offset: float = 25.0,
              noise: float = 2.0, side: int = 16) -> Case:
    rng = np.random.default_rng(seed + 1000)
    src = texture(seed)
    mapped = np.zeros(src.shape, bool)
    mapped[ROWS[0]:ROWS[1]] = True
    tgt = np.roll(src, shift_px, axis=1) * gain + offset + rng.normal(0, noise, src.shape).astype(np.float32)
    tgt = np.where(mapped, np.clip(tgt, 1, 255), 0).astype(np.float32)
    src = np.where(mapped, src, 0).astype(np.float32)
    patches, dirs, truth = [], [], []
    us = np.sort(rng.choice(np.arange(50, 2000, 80), n, replace=False)) + rng.integers(0, 20, n)
    vs = rng.integers(ROWS[0] + 30, ROWS[1] - 30, n)
    for u, v in zip(us, vs):
        x0, y0 = int(u), int(v)
        p = src[y0:y0 + side, x0:x0 + side]
        patches.append(np.round((p - p.min()) * 255 / (p.max() - p.min())).astype(np.uint8))
        cu, cv_ = x0 + (side - 1) / 2, y0 + (side - 1) / 2
        dirs.append(GEO.unproject(np.array(cu), np.array(cv_)))
        truth.append(((cu + shift_px) % GEO.width, cv_))
    return Case(src, tgt, mapped, patches, np.array(dirs), np.array(truth),
                rotation_about_axis_y(shift_px / GEO.f))


def tiles_of(mapped: np.ndarray, tile: int = 64) -> np.ndarray:
    """mono8 tile image: 255 where a tile is fully mapped."""
    h, w = mapped.shape
    full = mapped.reshape(h // tile, tile, w // tile, tile).all(axis=(1, 3))
    return np.where(full, 255, 0).astype(np.uint8)


def annotation(patch: np.ndarray, d: np.ndarray, text: str = 'a', lat: float = 47.0, lon: float = 15.0,
               pano: str = 'p1', q: np.ndarray | None = None) -> Annotation:
    return Annotation(text=text, patch=patch, direction=np.asarray(d, float), latitude_deg=lat,
                      longitude_deg=lon, altitude_m=350.0, panorama_id=pano, author='peter',
                      created_ns=1_700_000_000_000_000_000,
                      panorama_in_world_quat_xyzw=np.full(4, np.nan) if q is None else q)


#: R_enu_panorama of a level panorama (x east, y down, z north) and the up direction in it.
M_ENU_PANO = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
UP = M_ENU_PANO[2]  # ENU z in the panorama frame: (0, -1, 0)


def rotated_by(R: np.ndarray, deg: float, axis=(0.0, 0.0, 1.0)) -> np.ndarray:
    """R turned by ``deg`` about ``axis`` (applied after R)."""
    return Rotation.from_rotvec(np.radians(deg) * np.asarray(axis)).as_matrix() @ R


def displaced_spot_case(seed: int, t_enu: np.ndarray, depths: np.ndarray):
    """make_case's annotations seen from a browsing spot displaced by ``t_enu`` (m) with anchors
    at ``depths`` (m): (case, their true target directions, their map positions)."""
    case = make_case(seed=seed, n=len(depths))
    d_enu = (case.dirs @ case.R_target_source.T) @ M_ENU_PANO.T * depths[:, None]  # anchors
    seen = d_enu - t_enu
    seen /= np.linalg.norm(seen, axis=1, keepdims=True)
    truth = seen @ M_ENU_PANO  # back into the target panorama frame
    uv = np.stack(GEO.project(truth), axis=1)
    return case, truth, uv
