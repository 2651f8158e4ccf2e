"""Lighting of the two scenes.

Street: the sun and sky of a session (:func:`make_lighting`): the authoring session is late
afternoon (low sun, long shadows, flare near the horizon), browsing around midday, as in the
experiments of Langlotz et al. 2011 (section 6.1); exact cast shadows on facades and on the
ground (parallel projection between planes is affine); lit, hazed plane textures. Desk: one
Lambertian light from above-front-left plus ambient light, baked into the face textures.
"""
from __future__ import annotations

import math
from typing import Callable

import cv2
import numpy as np

from .model import EYE_HEIGHT_M, UP, Array, Image, Lighting, Plane, World, visible_from
from .rng import rng_stream
from .textures import smoothstep

def make_lighting(seed: int, session: str, world: World | None = None) -> Lighting:
    """Sun and sky for a session: low warm afternoon sun (authoring) or high midday sun (browsing).

    When ``world`` is given, the sun azimuth is chosen where the sun is not hidden behind a
    building (within the few tries), so that the session shows a sun glare somewhere.
    """
    rng = rng_stream(seed, 'lighting', session)
    if session == 'authoring':
        el = math.radians(rng.uniform(10.0, 20.0))
        sun_rgb = np.array([1.0, 0.82, 0.62]) * 2.0
        ambient = np.array([0.39, 0.44, 0.54])
        zenith, horizon = np.array([0.16, 0.28, 0.62]), np.array([0.85, 0.75, 0.62])
    else:
        el = math.radians(rng.uniform(34.0, 44.0))
        sun_rgb = np.array([1.0, 0.97, 0.92]) * 3.6
        ambient = np.array([0.62, 0.68, 0.80])
        zenith, horizon = np.array([0.20, 0.38, 0.82]), np.array([0.78, 0.84, 0.92])
    az = rng.uniform(0, 2 * math.pi)
    if world is not None:
        for _ in range(24):
            d = np.array([math.cos(el) * math.sin(az), math.cos(el) * math.cos(az), math.sin(el)])
            if visible_from(world, 1e4 * d, np.zeros(3)):
                break
            az = rng.uniform(0, 2 * math.pi)
    return Lighting(sun_az_rad=float(az), sun_el_rad=float(el), sun_rgb=sun_rgb,
                    ambient_rgb=ambient, sky_zenith_rgb=zenith, sky_horizon_rgb=horizon)


def _plane_sun_terms(plane: Plane, sun: Array) -> tuple[float, float, float]:
    """Sun direction in the plane's frame: (along tangent, up, along the outward normal)."""
    return float(sun @ plane.tangent), float(sun[2]), float(sun @ plane.normal)


def _affine_between(src: Plane, project: Callable[[Array], Array],
                    dst_coords: Callable[[Array], tuple[Array, Array]]) -> Array:
    """The 2x3 affine map from ``src`` texture pixels to destination pixels of a projection."""
    pts = np.array([[0.5, 0.5], [1.5, 0.5], [0.5, 1.5]])
    world = src.world_point(pts[:, 0], pts[:, 1])
    dc, dr = dst_coords(project(world))
    dst = np.stack([dc - 0.5, dr - 0.5], 1).astype(np.float32)
    return cv2.getAffineTransform((pts - 0.5).astype(np.float32), dst)


def _splat_max(src: Image, M: Array, dst: Image) -> None:
    """``dst = max(dst, warp(src))`` computed only over the warped footprint of ``src``."""
    h, w = src.shape[:2]
    corners = np.array([[0, 0, 1], [w, 0, 1], [0, h, 1], [w, h, 1]], float) @ M.T
    x0, y0 = np.floor(corners.min(0)).astype(int)
    x1, y1 = np.ceil(corners.max(0)).astype(int) + 1
    x0, y0 = max(x0, 0), max(y0, 0)
    x1, y1 = min(x1, dst.shape[1]), min(y1, dst.shape[0])
    if x1 <= x0 or y1 <= y0:
        return
    M2 = M.copy()
    M2[:, 2] -= (x0, y0)
    warped = cv2.warpAffine(src, M2.astype(np.float32), (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    np.maximum(dst[y0:y1, x0:x1], warped, out=dst[y0:y1, x0:x1])


def _caster_alpha(caster: Plane, receiver_normal: Array, receiver_foot: Array, sun: Array
                  ) -> Image:
    """Alpha of a caster restricted to its part on the sun side of the receiver plane."""
    a = caster.albedo[..., 3]
    h, w = a.shape
    corners = caster.world_point(np.array([0.5, w - 0.5, 0.5]), np.array([0.5, 0.5, h - 0.5]))
    t = (corners - receiver_foot) @ receiver_normal
    if np.all(t > 0):
        return a
    if np.all(t <= 0):
        return np.zeros_like(a)
    # t is linear in (col, row): build it from the three corners.
    cols = np.arange(w, dtype=np.float32)[None, :] / max(1, w - 1)
    rows = np.arange(h, dtype=np.float32)[:, None] / max(1, h - 1)
    tt = t[0] + (t[1] - t[0]) * cols + (t[2] - t[0]) * rows
    return a * (tt > 0.05)


def facade_shadow(receiver: Plane, casters: list[Plane], light: Lighting) -> Image:
    """Shadow mask (0 lit .. 1 shadow) on a facade from other planes and its own reliefs."""
    sun = light.sun_dir
    st, sz, sn = _plane_sun_terms(receiver, sun)
    h, w = receiver.shape
    shadow = np.zeros((h, w), np.float32)
    if sn <= 0.02:
        return np.ones((h, w), np.float32)
    ppm = receiver.px_per_m
    # Window recesses: the lintel and the jamb on the sun side shade the glass.
    for x0, y0, x1, y1, depth in receiver.windows:
        top = depth * sz / sn * ppm
        side = depth * abs(st) / sn * ppm
        yb = int(round(min(y1, y0 + top)))
        shadow[int(y0):max(int(y0), yb), int(x0):int(x1)] = 1.0
        if st > 0:
            shadow[int(y0):int(y1), max(int(x0), int(round(x1 - side))):int(x1)] = 1.0
        else:
            shadow[int(y0):int(y1), int(x0):int(round(min(x1, x0 + side)))] = 1.0
    # Awnings shade the wall below them, shifted away from the sun.
    for x0, _y0, x1, y1, depth in receiver.awnings:
        drop = depth * sz / sn * ppm
        shift = -depth * st / sn * ppm
        xa, xb = int(round(x0 + shift)), int(round(x1 + shift))
        shadow[int(y1):int(min(h, y1 + drop)), max(0, xa):max(0, min(w, xb))] = 1.0
    # Cast shadows of other planes: parallel projection along the sun onto this plane.
    n, foot = receiver.normal, receiver.foot

    def project(p: Array) -> Array:
        return p - (((p - foot) @ n) / sn)[:, None] * sun

    for c in casters:
        if c is receiver:
            continue
        a = _caster_alpha(c, n, foot, sun)
        if not a.any():
            continue
        M = _affine_between(c, project, receiver.texture_coords)
        _splat_max(a, M, shadow)
    return shadow


GROUND_RASTER_HALF_M = 110.0
GROUND_RASTER_RES_M = 0.1


def ground_shadow(casters: list[Plane], light: Lighting) -> Image:
    """Top-down shadow raster of the ground (rows north to south), 0 lit .. 1 shadow."""
    n = int(2 * GROUND_RASTER_HALF_M / GROUND_RASTER_RES_M)
    shadow = np.zeros((n, n), np.float32)
    sun = light.sun_dir

    def project(p: Array) -> Array:
        return p - ((p[:, 2] + EYE_HEIGHT_M) / sun[2])[:, None] * sun

    def coords(p: Array) -> tuple[Array, Array]:
        return ((p[:, 0] + GROUND_RASTER_HALF_M) / GROUND_RASTER_RES_M,
                (GROUND_RASTER_HALF_M - p[:, 1]) / GROUND_RASTER_RES_M)

    for c in casters:
        M = _affine_between(c, project, coords)
        _splat_max(c.albedo[..., 3], M, shadow)
    return cv2.GaussianBlur(shadow, (0, 0), 1.2)


def light_plane(plane: Plane, shadow: Image | None, light: Lighting) -> Image:
    """Premultiplied linear RGBA radiance of a plane under the session's lighting."""
    alb = plane.albedo
    sun = light.sun_dir
    if plane.normals is not None:  # round object: per-pixel normal in (tangent, up, out)
        nrm = plane.normals
        world_n = (nrm[..., :1] * plane.tangent + nrm[..., 1:2] * UP + nrm[..., 2:] * plane.normal)
        cos_i = np.clip(world_n @ sun, 0, None).astype(np.float32)
        self_shadow = 0.35 + 0.65 * smoothstep(0.0, 0.3, cos_i)
        direct = cos_i * self_shadow
    else:
        direct = np.full(plane.shape, max(0.0, float(sun @ plane.normal)), np.float32)
        if plane.kind == 'pole':
            direct[:] = 0.2 + 0.5 * max(0.0, float(np.hypot(sun[0], sun[1])))
    if shadow is not None:
        direct = direct * (1.0 - shadow)
    irr = light.ambient_rgb[None, None, :] + direct[..., None] * light.sun_rgb[None, None, :]
    rgb = alb[..., :3] * irr.astype(np.float32)
    if plane.kind == 'far':  # aerial perspective: distant blocks fade toward the horizon sky
        haze = 1.0 - math.exp(-plane.distance_m / 900.0)
        rgb = (1 - haze) * rgb + haze * (light.sky_horizon_rgb * 1.1).astype(np.float32)
    a = alb[..., 3:]
    return np.dstack([rgb * a, a]).astype(np.float32)



# --------------------------------------------------------------------------------------------
# Desk scene (handheld_desk)


def desk_shade(normal: Array) -> float:
    """Lambertian shading by a light from above-front-left plus ambient light."""
    light = np.array([-0.3, -0.5, 1.0])
    light = light / np.linalg.norm(light)
    return float(0.45 + 0.55 * max(0.0, float(normal @ light)))
