"""Rendering of the two scenes.

Street: :func:`render_panorama` renders an equirectangular radiance map (4096 x 2048 for 360 x
180 degrees) from a standing point under a lighting: sky, shadowed ground, then the planes far to
near (painter's order) with true parallax, prefiltered and antialiased.

Desk: per-pixel ray casting against the textured faces (vectorised numpy; each face only in its
projected bounding box), with one camera pose per image ROW, so the rolling shutter is exact;
motion blur averages 1-6 sub-exposure renders; textures are looked up trilinearly in the
mip-mapped atlas (the level from the pixel footprint), then a slight optical blur, mild
vignetting and sensor noise (:func:`render_image`).
"""
from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np
from numpy.typing import NDArray

from ..core.rotations import trace_angle
from .camera import DeskCamera
from .lighting import GROUND_RASTER_HALF_M, GROUND_RASTER_RES_M, facade_shadow, ground_shadow, light_plane
from .model import (BACKGROUND, EYE_HEIGHT_M, GAMMA, MIP_LEVELS, PANO_HEIGHT, PANO_MAX_ABS_EL,
                    PANO_WIDTH, Array, DeskScene, Face, Image, Lighting, Panorama, Plane, World,
                    direction_to_pano, pano_directions)
from .textures import smoothstep

logger = logging.getLogger(__name__)

PoseFn = Callable[[Array], tuple[Array, Array]]

def _band_rows() -> tuple[int, int]:
    r0 = int(math.floor((math.pi / 2 - PANO_MAX_ABS_EL) / math.pi * PANO_HEIGHT))
    return r0, PANO_HEIGHT - r0


ROW_CHUNK = 128  # rows of the panorama computed at once (bounds the memory of rendering)


def _render_sky(light: Lighting, world: World, out: Image) -> None:
    """Sky gradient, sun halo and disc, lit clouds into the upper half of ``out`` (linear)."""
    r0, _ = _band_rows()
    for a in range(r0, PANO_HEIGHT // 2, ROW_CHUNK):
        rows = np.arange(a, min(a + ROW_CHUNK, PANO_HEIGHT // 2))
        out[rows[0]:rows[-1] + 1] = _sky_rows(light, world, rows)


def _sky_rows(light: Lighting, world: World, rows: NDArray[np.int64]) -> Image:
    f32 = np.float32
    d = pano_directions(rows, np.arange(PANO_WIDTH)).astype(f32)
    t = np.sqrt(np.clip(d[..., 2:3], 0, 1))
    sky = light.sky_horizon_rgb.astype(f32) * (1 - t) + light.sky_zenith_rgb.astype(f32) * t
    cos_sun = np.clip(d @ light.sun_dir.astype(f32), -1, 1)[..., None]
    ang = np.arccos(cos_sun)
    halo = 1.0 + f32(1.6) * np.exp(-ang / f32(0.07)) + f32(0.5) * np.exp(-ang / f32(0.5))
    sky *= halo
    dens = world.clouds[rows][..., None]
    detail = world.cloud_detail[rows][..., None]
    cloud = (light.ambient_rgb.astype(f32) * f32(1.5)
             + f32(0.35) * light.sun_rgb.astype(f32) * (f32(0.6) + f32(0.4) * cos_sun)) * detail
    cloud *= (1.0 - f32(0.35) * dens) * np.sqrt(halo)  # grey bases, silver linings
    rgb = sky * (1 - f32(0.85) * dens) + cloud * f32(0.85) * dens
    rgb += ((ang < math.radians(0.6)) * (1 - f32(0.9) * dens) * f32(60.0))  # the sun's disc
    return rgb


def _ground_albedo(world: World, x: Image, y: Image, footprint: Image) -> Image:
    """Paving of the square at ground points (x, y) in metres, faded where it would alias."""
    tile = world.ground_tile_m
    row_i = np.floor(y / tile)
    xs = x + 0.5 * tile * (row_i % 2)
    col_i = np.floor(xs / tile)
    tint = (np.sin(row_i * 12.9898 + col_i * 78.233) * 43758.5453) % 1.0
    fy, fx = y - row_i * tile, xs - col_i * tile
    edge = np.minimum(np.minimum(fy, tile - fy), np.minimum(fx, tile - fx))
    soft = np.maximum(footprint, 0.01)
    grout = smoothstep(0.0, 1.0, (edge - 0.015) / soft)
    fade = np.clip(1.0 - footprint / (0.35 * tile), 0.0, 1.0)
    pattern = (0.82 + 0.36 * tint) * (0.55 + 0.45 * grout)
    mean_pattern = 1.0 * (1 - 0.45 * 0.05 / tile)
    shade = fade * pattern + (1 - fade) * mean_pattern
    n = world.ground_grain.shape[0]
    gx = (x / 3.0 * n).astype(np.float32)
    gy = (y / 3.0 * n).astype(np.float32)
    grain = cv2.remap(world.ground_grain, gx, gy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    m = world.ground_stains.shape[0]
    stains = cv2.remap(world.ground_stains, (x / 60.0 * m).astype(np.float32),
                       (y / 60.0 * m).astype(np.float32), cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_WRAP)
    grain_fade = np.clip(1.0 - footprint / 0.06, 0.0, 1.0)
    shade = shade * (1.0 + 0.25 * grain * grain_fade) * (1.0 + 0.18 * stains)
    paint = np.zeros_like(x)
    for caz, r0, r1, hw in world.crossings:  # zebra crossings: stripes across the walkway
        dx, dy = math.sin(caz), math.cos(caz)
        along = x * dx + y * dy
        across = -x * dy + y * dx
        inside = (along > r0) & (along < r1) & (np.abs(across) < hw)
        stripes = (np.floor(along / 0.5) % 2 == 0) & inside
        paint = np.maximum(paint, stripes.astype(np.float32) * np.clip(1 - footprint / 0.4, 0, 1))
    albedo = world.ground_base_rgb.astype(np.float32) * shade[..., None]
    albedo = albedo * (1 - paint[..., None]) + 0.75 * paint[..., None]
    for mx, my, mr in world.manholes:  # dark cast-iron covers with a grid
        dd = np.hypot(x - mx, y - my)
        cover = dd < mr
        if cover.any():
            grid = (np.floor((x[cover] - mx) / 0.08) + np.floor((y[cover] - my) / 0.08)) % 2
            albedo[cover] = (0.05 + 0.04 * grid)[:, None] * np.array([1.0, 1.0, 1.05], np.float32)
            albedo[cover & (dd > mr - 0.05)] = 0.02
    return albedo


def _render_ground(world: World, light: Lighting, viewpoint: Array, out: Image,
                   depth: Image) -> None:
    """Paved ground below the horizon, with the cast shadows of the session's sun."""
    _, r1 = _band_rows()
    casters = [p for p in world.planes if p.kind != 'far']
    shadow_raster = ground_shadow(casters, light)
    for a in range(PANO_HEIGHT // 2, r1, ROW_CHUNK):  # every row here looks below the horizon
        rows = np.arange(a, min(a + ROW_CHUNK, r1))
        rgb, lam = _ground_rows(world, light, viewpoint, shadow_raster, rows)
        out[rows[0]:rows[-1] + 1] = rgb
        depth[rows[0]:rows[-1] + 1] = lam


def _ground_rows(world: World, light: Lighting, viewpoint: Array, shadow_raster: Image,
                 rows: NDArray[np.int64]) -> tuple[Image, Image]:
    d = pano_directions(rows, np.arange(PANO_WIDTH))
    h_eye = EYE_HEIGHT_M + viewpoint[2]
    lam = h_eye / np.maximum(-d[..., 2], 1e-4)
    x = (viewpoint[0] + lam * d[..., 0]).astype(np.float32)
    y = (viewpoint[1] + lam * d[..., 1]).astype(np.float32)
    lam = lam.astype(np.float32)
    footprint = lam * lam * np.float32(math.pi / PANO_HEIGHT / h_eye)
    albedo = _ground_albedo(world, x, y, footprint)
    sx = (x + GROUND_RASTER_HALF_M) / np.float32(GROUND_RASTER_RES_M) - np.float32(0.5)
    sy = (GROUND_RASTER_HALF_M - y) / np.float32(GROUND_RASTER_RES_M) - np.float32(0.5)
    shadow = cv2.remap(shadow_raster, sx, sy, cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    direct = np.float32(max(0.0, float(light.sun_dir[2]))) * (1.0 - shadow)
    irr = light.ambient_rgb + direct[..., None] * light.sun_rgb.astype(np.float32)
    rgb = albedo * irr.astype(np.float32)
    haze = (1.0 - np.exp(-lam / np.float32(900.0)))[..., None]
    return (1 - haze) * rgb + haze * light.sky_horizon_rgb.astype(np.float32), lam


def _plane_bbox(plane: Plane, viewpoint: Array) -> tuple[int, int, int, int] | None:
    """Panorama column and row range covered by a plane seen from ``viewpoint``."""
    h, w = plane.shape
    k = 17
    cols = np.concatenate([np.linspace(0, w, k), np.linspace(0, w, k), np.zeros(k), np.full(k, w)])
    rows = np.concatenate([np.zeros(k), np.full(k, h), np.linspace(0, h, k), np.linspace(0, h, k)])
    pts = plane.world_point(cols, rows) - viewpoint
    if np.any(pts @ plane.normal >= 0):  # seen from behind or edge-on: not drawn
        return None
    u, v = direction_to_pano(pts)
    uc, _ = direction_to_pano(plane.foot - viewpoint)
    du = (u - uc + PANO_WIDTH / 2) % PANO_WIDTH - PANO_WIDTH / 2
    return (int(math.floor(uc + du.min())) - 1, int(math.ceil(uc + du.max())) + 1,
            max(0, int(math.floor(v.min())) - 1), min(PANO_HEIGHT, int(math.ceil(v.max())) + 1))


def _prefilter(rgba: Image, plane: Plane, viewpoint: Array) -> Image:
    """Blur a plane's texture to the panorama's sampling at its distance (no aliasing)."""
    dist = float(np.linalg.norm(plane.foot - viewpoint))
    step = dist * (2 * math.pi / PANO_WIDTH) * plane.px_per_m  # texture px per panorama px
    if step <= 1.2:
        return rgba
    return cv2.GaussianBlur(rgba, (0, 0), 0.5 * step)


def _render_plane(plane: Plane, rgba: Image, viewpoint: Array, out: Image, depth: Image) -> None:
    """Composite a lit plane (premultiplied RGBA) over the panorama, painter's style."""
    box = _plane_bbox(plane, viewpoint)
    if box is None:
        return
    u0, u1, v0, v1 = box
    cols = np.arange(u0, u1)
    rows = np.arange(v0, v1)
    d = pano_directions(rows, cols)
    n = plane.normal
    denom = d @ n
    lam = np.where(denom < -1e-6, ((plane.foot - viewpoint) @ n) / np.minimum(denom, -1e-6), -1.0)
    pts = viewpoint + lam[..., None] * d
    tc, tr = plane.texture_coords(pts)
    sample = cv2.remap(rgba, (tc - 0.5).astype(np.float32), (tr - 0.5).astype(np.float32),
                       cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    a = sample[..., 3] * (lam > 0)
    wrap = cols % PANO_WIDTH
    dst = out[v0:v1][:, wrap]
    dst = sample[..., :3] * (lam > 0)[..., None] + (1 - a[..., None]) * dst
    out[v0:v1, wrap] = dst
    dep = depth[v0:v1][:, wrap]
    depth[v0:v1, wrap] = np.where(a > 0.5, lam, dep).astype(np.float32)


def _antialias(enc: Image) -> Image:
    """Blur for the camera's ~2x coarser sampling; wider horizontally toward the poles."""
    out = cv2.GaussianBlur(enc, (1, 0), sigmaX=0.01, sigmaY=0.85)
    bands = np.linspace(0, PANO_HEIGHT, 25).astype(int)
    for a, b in zip(bands[:-1], bands[1:], strict=True):
        el = abs(math.pi / 2 - (a + b) / 2 * math.pi / PANO_HEIGHT)
        sx = min(6.0, 0.85 / max(math.cos(el), 0.1))
        pad = int(math.ceil(4 * sx)) + 1
        strip = out[a:b]
        wrapped = np.concatenate([strip[:, -pad:], strip, strip[:, :pad]], axis=1)
        blurred = cv2.GaussianBlur(wrapped, (0, 0), sigmaX=sx, sigmaY=0.01)
        out[a:b] = blurred[:, pad:pad + PANO_WIDTH]
    return out


def render_panorama(world: World, light: Lighting, viewpoint_enu: Array) -> Panorama:
    """Render the world's equirectangular panorama from a standing point (eye height)."""
    viewpoint = np.asarray(viewpoint_enu, dtype=float)
    lin = np.zeros((PANO_HEIGHT, PANO_WIDTH, 3), np.float32)
    depth = np.full((PANO_HEIGHT, PANO_WIDTH), np.inf, np.float32)
    r0, r1 = _band_rows()
    lin[:r0] = light.sky_zenith_rgb
    lin[r1:] = world.ground_base_rgb * light.ambient_rgb
    _render_sky(light, world, lin)
    _render_ground(world, light, viewpoint, lin, depth)
    casters = [p for p in world.planes if p.kind != 'far']
    order = sorted(world.planes, key=lambda p: -float(np.linalg.norm(p.foot - viewpoint)))
    for plane in order:
        shadow = facade_shadow(plane, casters, light) if plane.kind == 'building' else None
        rgba = _prefilter(light_plane(plane, shadow, light), plane, viewpoint)
        _render_plane(plane, rgba, viewpoint, lin, depth)
    band = lin[PANO_HEIGHT // 2 - 500:PANO_HEIGHT // 2 + 400]
    mean_rad = float(np.mean(np.minimum(band, 4.0)))
    np.maximum(lin, 0.0, out=lin)
    enc = _antialias(np.power(lin, np.float32(1.0 / GAMMA), out=lin))
    sun_u, sun_v = direction_to_pano(light.sun_dir)
    sun_visible = bool(np.isinf(depth[int(sun_v) % PANO_HEIGHT, int(sun_u) % PANO_WIDTH]))
    logger.debug('panorama from %s: mean radiance %.3f, sun visible %s', viewpoint.round(2),
                 mean_rad, sun_visible)
    return Panorama(encoded=enc, depth_m=depth, viewpoint_enu=viewpoint, sun_visible=sun_visible,
                    mean_radiance=mean_rad)



# --------------------------------------------------------------------------------------------
# Desk scene (handheld_desk): per-row ray casting


OPTICAL_BLUR_SIGMA_PX = 0.5
PIXEL_NOISE = 2.0
VIGNETTING = 0.18
#: Largest image motion between two sub-exposure renders (px).
BLUR_STEP_PX = 2.5
MAX_SUBFRAMES = 6


@dataclass
class _RayGrid:
    """Camera-frame ray components of a camera: x/z per column, y/z per row, |ray| per pixel."""

    xc: NDArray[np.float32]
    yc: Array
    norm: NDArray[np.float32]
    vignette: NDArray[np.float32]

    @staticmethod
    @functools.lru_cache(maxsize=4)
    def of(cam: DeskCamera) -> '_RayGrid':
        xc = ((np.arange(cam.width) - cam.cx) / cam.fx).astype(np.float32)
        yc = (np.arange(cam.height) - cam.cy) / cam.fy
        norm = np.sqrt(1.0 + xc[None, :].astype(np.float64) ** 2 + yc[:, None] ** 2).astype(np.float32)
        r2 = (xc[None, :] ** 2 + yc[:, None].astype(np.float32) ** 2)
        vig = (1.0 - VIGNETTING * r2 / r2.max()).astype(np.float32)
        return _RayGrid(xc, yc, norm, vig)


def _face_window(face: Face, cam: DeskCamera, R: Array, p: Array) -> tuple[int, int, int, int] | None:
    """Image rows/cols [r0, r1) x [c0, c1) that may see the face, from its corners projected with
    the poses of the first, middle and last rows; None when it cannot be seen."""
    idx = [0, len(p) // 2, len(p) - 1]
    n = face.normal
    if all(float(n @ (p[i] - face.origin)) <= 1e-9 for i in idx):
        return None  # the camera is behind the face's plane
    uvs = []
    for i in idx:
        Xc = (face.corners - p[i]) @ R[i]
        if np.any(Xc[:, 2] < 0.02):
            return 0, cam.height, 0, cam.width
        uvs.append(Xc[:, :2] / Xc[:, 2:3] * [cam.fx, cam.fy] + [cam.cx, cam.cy])
    uv = np.concatenate(uvs)
    c0, r0 = np.floor(uv.min(0)).astype(int) - 4
    c1, r1 = np.ceil(uv.max(0)).astype(int) + 5
    r0, r1, c0, c1 = max(r0, 0), min(r1, cam.height), max(c0, 0), min(c1, cam.width)
    if r1 <= r0 or c1 <= c0:
        return None
    return int(r0), int(r1), int(c0), int(c1)


def _along(vec: Array, R: Array, xw: NDArray[np.float32], yc: Array) -> NDArray[np.float32]:
    """``vec . d`` for the (unnormalised) ray ``d = R_h [x, y, 1]`` of every pixel of a window:
    rows with poses ``R`` (h, 3, 3) and ray y/z ``yc`` (h,), columns with ray x/z ``xw`` (1, w).
    (A module function, not a closure over the loop's window: ruff B023.)"""
    vr = np.einsum('hij,i->hj', R, vec)  # vec . (R_h [x, y, 1]) = vr0 x + vr1 y + vr2
    return (vr[:, 0, None].astype(np.float32) * xw + (vr[:, 1] * yc + vr[:, 2])[:, None].astype(np.float32))


def render_radiance(scene: DeskScene, cam: DeskCamera, R_rows: Array, p_rows: Array) -> NDArray[np.float32]:
    """One instantaneous render (float32 grey levels): row v seen from pose (R_rows[v], p_rows[v])."""
    H, W = cam.height, cam.width
    g = _RayGrid.of(cam)
    xc = g.xc[None, :]
    best_t = np.full((H, W), np.inf, np.float32)
    best_x = np.full((H, W), -100.0, np.float32)
    best_y = np.full((H, W), -100.0, np.float32)
    best_k = np.zeros((H, W), np.float32)  # density / sqrt(|n . d|): for the mip level
    for face in scene.faces:
        win = _face_window(face, cam, R_rows, p_rows)
        if win is None:
            continue
        r0, r1, c0, c1 = win
        R, p, yc = R_rows[r0:r1], p_rows[r0:r1], g.yc[r0:r1]
        xw = xc[:, c0:c1]
        n = face.normal
        dn = _along(n, R, xw, yc)
        num = ((face.origin - p) @ n).astype(np.float32)[:, None]
        with np.errstate(divide='ignore', invalid='ignore'):
            t = num / dn
        a = ((p - face.origin) @ face.e_u).astype(np.float32)[:, None] + t * _along(face.e_u, R, xw, yc)
        b = ((p - face.origin) @ face.e_v).astype(np.float32)[:, None] + t * _along(face.e_v, R, xw, yc)
        bt = best_t[r0:r1, c0:c1]
        hit = (dn < -1e-6) & (t > 0) & (t < bt) & (a >= 0) & (a <= face.size[0]) & (b >= 0) & (b <= face.size[1])
        if not hit.any():
            continue
        np.copyto(bt, t, where=hit)
        np.copyto(best_x[r0:r1, c0:c1], face.atlas_xy[0] - 0.5 + a * np.float32(face.density), where=hit)
        np.copyto(best_y[r0:r1, c0:c1], face.atlas_xy[1] - 0.5 + b * np.float32(face.density), where=hit)
        np.copyto(best_k[r0:r1, c0:c1], np.float32(face.density) / np.sqrt(np.abs(dn)), where=hit)
    hit_any = np.isfinite(best_t)
    # footprint of a pixel in texels: distance / f / cos(incidence)^0.5 (area-like), as mip level
    with np.errstate(invalid='ignore', over='ignore'):
        fp = np.where(hit_any, best_t * g.norm * np.sqrt(g.norm) * best_k / np.float32(cam.fx), 1.0)
    lam = np.clip(np.log2(np.maximum(fp, 1.0)), 0, MIP_LEVELS - 1).astype(np.float32)
    out = np.zeros((H, W), np.float32)
    lo, hi = float(lam.min()), float(lam.max())
    for k in range(MIP_LEVELS):
        if k < math.floor(lo) or k > math.ceil(hi):
            continue
        s = np.float32(0.5 ** k)  # cv2.pyrDown centres texel i of level k on texel 2^k i of level 0
        mx = best_x * s
        my = best_y * s
        img = cv2.remap(scene.atlas[k], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        wk = np.maximum(0.0, 1.0 - np.abs(lam - k))
        out += wk * img.astype(np.float32)
    out[~hit_any] = BACKGROUND
    return out


def subframe_count(cam: DeskCamera, pose_fn: PoseFn, t_s: float) -> int:
    """How many sub-exposure renders the motion during the exposure needs (1 .. MAX_SUBFRAMES)."""
    if cam.exposure_s <= 0:
        return 1
    R, p = pose_fn(np.array([t_s - cam.exposure_s / 2, t_s + cam.exposure_s / 2]))
    rel = R[0].T @ R[1]
    ang = float(trace_angle(rel))
    px = ang * cam.fx + float(np.linalg.norm(p[1] - p[0])) * cam.fx / 0.3
    return int(min(MAX_SUBFRAMES, max(1, math.ceil(px / BLUR_STEP_PX))))


def render_image(scene: DeskScene, cam: DeskCamera, pose_fn: PoseFn, t_s: float,
                 noise_rng: np.random.Generator | None = None, subframes: int | None = None,
                 optical_blur: bool = True) -> tuple[NDArray[np.uint8], int]:
    """The mono8 image whose centre row is captured at t_s, and the number of sub-exposures.

    ``pose_fn(times) -> (R_w_c (N, 3, 3), p_w_c (N, 3))`` gives the camera poses; each row is
    rendered at its own capture time (rolling shutter), averaged over the exposure (motion blur).
    ``noise_rng`` None renders without sensor noise."""
    n_sub = subframe_count(cam, pose_fn, t_s) if subframes is None else int(subframes)
    rows = cam.row_time_offset_s(np.arange(cam.height))
    acc = np.zeros((cam.height, cam.width), np.float32)
    for j in range(n_sub):
        dt = cam.exposure_s * ((j + 0.5) / n_sub - 0.5)
        R, p = pose_fn(t_s + rows + dt)
        acc += render_radiance(scene, cam, R, p)
    img = acc / np.float32(n_sub)
    if optical_blur and OPTICAL_BLUR_SIGMA_PX > 0:
        img = cv2.GaussianBlur(img, (0, 0), OPTICAL_BLUR_SIGMA_PX)
    img *= _RayGrid.of(cam).vignette
    if noise_rng is not None:
        img += noise_rng.normal(0.0, PIXEL_NOISE, img.shape).astype(np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), n_sub
