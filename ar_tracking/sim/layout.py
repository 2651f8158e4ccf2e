"""Where things are in the two scenes: the street around the spot, and the desk with its boxes.

Street (:func:`build_world`, seed only, so the authoring and the browsing session see the same
spot): a far skyline, a ring of 11-15 buildings with streets between some, trees and lamp posts
in front of them, zebra crossings, manholes, clouds, and 4-6 annotation anchors on distinctive,
unoccluded spots (Langlotz et al. 2011, section 6.1). Desk (:func:`desk_scene`): the desk top,
its front edge, the wall, the floor and three boxes, with their textures packed into one
mip-mapped atlas.
"""
from __future__ import annotations

import functools
import math
from dataclasses import replace

import cv2
import numpy as np
from numpy.typing import NDArray

from .desk_textures import box_texture, desk_texture, floor_texture, room_wall_texture
from .lighting import desk_shade
from .model import (ATLAS_GUTTER, DESK_DENSITY, DESK_SIZE_M, DESK_THICKNESS_M, EYE_HEIGHT_M,
                    FAR_PX_PER_M, FLOOR_Z_M, NEAR_PX_PER_M, PANO_HEIGHT, PANO_WIDTH, SIGN_WORDS,
                    WALL_Y_M, Anchor, Array, Box, DeskScene, Face, Image, Plane, World, clear_view,
                    mip_pyramid)
from .rng import rng_stream
from .street_textures import draw_facade, draw_far_block, draw_pole, draw_tree, to_albedo
from .textures import fbm, periodic_noise, pick_colour, smooth_noise, smoothstep, srgb_to_linear

def build_world(seed: int) -> World:
    """The spot of ``seed``: buildings, trees, posts, ground, clouds and 4-6 annotation anchors."""
    rng = rng_stream(seed, 'world')
    planes: list[Plane] = []
    planes += _far_ring(rng)
    buildings = _building_ring(rng)
    planes += buildings
    planes += _street_furniture(rng, buildings)
    planes.sort(key=lambda p: -p.distance_m)
    world = World(
        seed=seed, planes=planes, anchors=[], ground_tile_m=float(rng.uniform(0.4, 0.6)),
        ground_grain=periodic_noise(rng, 256, 8, 4),
        ground_stains=periodic_noise(rng, 256, 4, 3),
        ground_base_rgb=srgb_to_linear(np.array(pick_colour(rng, [(146, 140, 132), (156, 150, 140),
                                                              (132, 128, 124)], 6)) / 255.0),
        crossings=_crossings(rng, buildings), manholes=_manholes(rng),
        clouds=np.zeros((0, 0), np.float32), cloud_detail=np.zeros((0, 0), np.float32),
    )
    world.clouds, world.cloud_detail = _clouds(rng)
    world.anchors = _choose_anchors(rng, world, buildings)
    return world


def _building_ring(rng: np.random.Generator) -> list[Plane]:
    """11-15 buildings around the spot, each filling an azimuth sector (streets between some)."""
    n = int(rng.integers(11, 16))
    widths = rng.uniform(0.6, 1.4, n)
    widths *= 2 * math.pi / widths.sum()
    start = rng.uniform(0, 2 * math.pi)
    edges = start + np.concatenate([[0.0], np.cumsum(widths)])
    words = list(SIGN_WORDS)
    rng.shuffle(words)
    tower_at = int(rng.integers(n))
    out = []
    for i in range(n):
        gap = math.radians(rng.uniform(2.0, 6.0)) if rng.random() < 0.4 else 0.0
        a0, a1 = edges[i] + gap / 2, edges[i + 1] - gap / 2
        dist = rng.uniform(28.0, 75.0)
        skew = math.radians(rng.uniform(-18.0, 18.0))
        phi = (a0 + a1) / 2 + skew
        s0, s1 = dist * math.tan(a0 - phi), dist * math.tan(a1 - phi)
        tower = i == tower_at
        el_top = math.radians(rng.uniform(30.0, 40.0) if tower else rng.uniform(9.0, 32.0))
        height = float(np.clip(dist * math.tan(el_top) + EYE_HEIGHT_M, 7.0, 48.0))
        f = draw_facade(rng, s1 - s0, height, NEAR_PX_PER_M, words, tower=tower)
        out.append(Plane(
            kind='building', index=i + 1, foot_az_rad=phi % (2 * math.pi), distance_m=dist,
            s_min_m=s0, z_max_m=height + 4.5 - EYE_HEIGHT_M, px_per_m=NEAR_PX_PER_M,
            albedo=to_albedo(f.img, f.alpha), windows=np.array(f.windows, float).reshape(-1, 5),
            awnings=np.array(f.awnings, float).reshape(-1, 5), features=f.features,
        ))
    return out


def _far_ring(rng: np.random.Generator) -> list[Plane]:
    """A closed ring of distant blocks so that the horizon is never empty."""
    out = []
    az = rng.uniform(0, 2 * math.pi)
    end = az + 2 * math.pi
    while az < end:
        span = math.radians(rng.uniform(6.0, 16.0))
        span = min(span, end - az + math.radians(0.5))
        dist = rng.uniform(180.0, 380.0)
        phi = az + span / 2 + math.radians(rng.uniform(-10, 10))
        s0, s1 = dist * math.tan(az - phi), dist * math.tan(az + span - phi)
        height = dist * math.tan(math.radians(rng.uniform(2.5, 9.0))) + EYE_HEIGHT_M
        img, a = draw_far_block(rng, s1 - s0, height, FAR_PX_PER_M)
        out.append(Plane(kind='far', index=0, foot_az_rad=phi % (2 * math.pi), distance_m=dist,
                         s_min_m=s0, z_max_m=height + 12.0 - EYE_HEIGHT_M, px_per_m=FAR_PX_PER_M,
                         albedo=to_albedo(img, a)))
        az += span - math.radians(0.3)
    return out


def _building_distance_at(buildings: list[Plane], az: float) -> float:
    """Distance from the origin to the building ring in direction ``az`` (inf in a street)."""
    d = np.array([math.sin(az), math.cos(az), 0.0])
    best = math.inf
    for b in buildings:
        denom = d @ b.normal
        if denom >= -1e-6:
            continue
        lam = (b.foot @ b.normal) / denom
        s = (lam * d - b.foot) @ b.tangent
        w = b.albedo.shape[1] / b.px_per_m
        if lam > 0 and b.s_min_m <= s <= b.s_min_m + w:
            best = min(best, lam)
    return best


def _street_furniture(rng: np.random.Generator, buildings: list[Plane]) -> list[Plane]:
    """Trees and posts in front of the buildings (not too close, so parallax stays moderate)."""
    out = []
    for _ in range(int(rng.integers(5, 10))):
        az = rng.uniform(0, 2 * math.pi)
        dist = min(rng.uniform(17.0, 26.0), _building_distance_at(buildings, az) - 6.0)
        width, height = rng.uniform(4.0, 7.0), rng.uniform(6.0, 11.0)
        img, a, normals = draw_tree(rng, width, height, NEAR_PX_PER_M)
        out.append(Plane(kind='tree', index=0, foot_az_rad=az, distance_m=dist,
                         s_min_m=-width / 2, z_max_m=height - EYE_HEIGHT_M, px_per_m=NEAR_PX_PER_M,
                         albedo=to_albedo(img, a), normals=normals))
    for _ in range(int(rng.integers(4, 8))):
        az = rng.uniform(0, 2 * math.pi)
        dist = rng.uniform(9.0, 20.0)
        height = rng.uniform(3.0, 5.5)
        img, a = draw_pole(rng, height, NEAR_PX_PER_M)
        out.append(Plane(kind='pole', index=0, foot_az_rad=az, distance_m=dist,
                         s_min_m=-0.6, z_max_m=height - EYE_HEIGHT_M, px_per_m=NEAR_PX_PER_M,
                         albedo=to_albedo(img, a)))
    return out


def _crossings(rng: np.random.Generator, buildings: list[Plane]) -> Array:
    rows = []
    for _ in range(int(rng.integers(1, 3))):
        az = rng.uniform(0, 2 * math.pi)
        r1 = min(25.0, _building_distance_at(buildings, az) - 3.0)
        rows.append((az, max(4.0, r1 - rng.uniform(6, 10)), r1, rng.uniform(1.5, 2.5)))
    return np.array(rows, float)


def _manholes(rng: np.random.Generator) -> Array:
    n = int(rng.integers(3, 7))
    r = rng.uniform(3.0, 15.0, n)
    az = rng.uniform(0, 2 * math.pi, n)
    return np.stack([r * np.sin(az), r * np.cos(az), rng.uniform(0.3, 0.45, n)], 1)


def _clouds(rng: np.random.Generator) -> tuple[Image, Image]:
    """Cloud density of the upper panorama half: many cumulus with crisp edges, so that a camera
    looking up still sees structure (no big flat regions)."""
    h, w = PANO_HEIGHT // 2, PANO_WIDTH
    base = fbm(rng, (h, w), 140.0, 6, gain=0.6, wrap_x=True)
    el = (math.pi / 2 - (np.arange(h) + 0.5) * math.pi / PANO_HEIGHT)[:, None]
    cover = rng.uniform(0.04, 0.12)
    dens = smoothstep(0.0 - cover, 0.06 - cover, base)
    dens *= (0.8 + 0.2 * np.cos(el)).astype(np.float32)
    # Bright sunlit tops, grey bases and billows inside the clouds.
    detail = 1.0 + 0.45 * fbm(rng, (h, w), 40.0, 4, gain=0.6, wrap_x=True)
    return dens.astype(np.float32), detail.astype(np.float32)


def _choose_anchors(rng: np.random.Generator, world: World, buildings: list[Plane]
                    ) -> list[Anchor]:
    """4-6 features (doors, signs, windows, a clock) of different buildings, seen from the spot."""
    cands = []
    for b in buildings:
        for kind, col, row in b.features:
            p = b.world_point(np.array(col), np.array(row))
            el = math.degrees(math.asin(p[2] / np.linalg.norm(p)))
            if not -6.0 < el < 32.0 or not clear_view(world, b, p):
                continue
            label = f'{kind} of building {b.index}' if not kind.startswith('Sign') else \
                f'{kind} on building {b.index}'
            cands.append((math.atan2(p[0], p[1]) % (2 * math.pi), b.index, label, p))
    order = rng.permutation(len(cands))
    n_want = int(rng.integers(4, 7))
    chosen: list[tuple[float, int, str, Array]] = []
    for sep in (25.0, 12.0, 0.0):  # prefer anchors spread around the horizon
        for i in order:
            az, idx, label, p = cands[i]
            if len(chosen) >= n_want or any(c[1] == idx or c[2] == label for c in chosen):
                continue
            if all(abs((math.degrees(az - c[0]) + 180) % 360 - 180) >= sep for c in chosen):
                chosen.append(cands[i])
    chosen.sort(key=lambda c: c[0])
    return [Anchor(label=c[2], position_enu=c[3]) for c in chosen]



# --------------------------------------------------------------------------------------------
# Desk scene (handheld_desk)


def place_boxes(rng: np.random.Generator) -> list[Box]:
    kinds = [('cardboard', (0.16, 0.21), (0.12, 0.16), (0.15, 0.23), 0.14),
             ('books', (0.22, 0.26), (0.16, 0.19), (0.05, 0.09), -0.08),
             ('small', (0.09, 0.13), (0.07, 0.10), (0.06, 0.14), -0.1)]
    boxes: list[Box] = []
    for kind, lx, ly, hz, y_min in kinds:
        size = (rng.uniform(*lx), rng.uniform(*ly), rng.uniform(*hz))
        r = math.hypot(size[0], size[1]) / 2
        for _ in range(200):
            c = np.array([rng.uniform(-0.6 + r + 0.02, 0.6 - r - 0.02), rng.uniform(y_min, 0.4 - r - 0.02)])
            if all(np.linalg.norm(c - b.centre) > r + math.hypot(b.size[0], b.size[1]) / 2 + 0.03 for b in boxes):
                break
        boxes.append(Box(kind, c, float(rng.uniform(-0.6, 0.6)), size))
    return boxes


def box_faces(box: Box, k: int) -> list[tuple[Face, str]]:
    c, s = math.cos(box.yaw), math.sin(box.yaw)
    ex, ey, ez = np.array([c, s, 0.0]), np.array([-s, c, 0.0]), np.array([0.0, 0.0, 1.0])
    lx, ly, h = box.size[0] / 2, box.size[1] / 2, box.size[2]
    C = np.array([box.centre[0], box.centre[1], 0.0])
    d = DESK_DENSITY
    return [
        (Face(f'box{k}_top', C - lx * ex - ly * ey + h * ez, ex, ey, (2 * lx, 2 * ly), d), 'top'),
        (Face(f'box{k}_px', C + lx * ex - ly * ey, ey, ez, (2 * ly, h), d), 'side0'),
        (Face(f'box{k}_nx', C - lx * ex + ly * ey, -ey, ez, (2 * ly, h), d), 'side1'),
        (Face(f'box{k}_py', C + lx * ex + ly * ey, -ex, ez, (2 * lx, h), d), 'side2'),
        (Face(f'box{k}_ny', C - lx * ex - ly * ey, ex, ez, (2 * lx, h), d), 'side3'),
    ]


def pack_atlas(shapes: list[tuple[int, int]], width: int) -> tuple[list[tuple[int, int]], int]:
    """Shelf packing of (h, w) rectangles with a gutter; returns top-left (x, y) and the height."""
    g = ATLAS_GUTTER
    order = sorted(range(len(shapes)), key=lambda i: -shapes[i][0])
    pos: list[tuple[int, int]] = [(0, 0)] * len(shapes)
    x, y, shelf = g, g, 0
    for i in order:
        h, w = shapes[i]
        if x + w + g > width:
            x, y, shelf = g, y + shelf + 2 * g, 0
        pos[i] = (x, y)
        x += w + 2 * g
        shelf = max(shelf, h)
    return pos, y + shelf + g


@functools.lru_cache(maxsize=2)
def desk_scene(seed: int) -> DeskScene:
    """The seed's desk, boxes, wall and floor with their texture atlas (cached; ~1 s to make)."""
    rng = rng_stream(seed, 'handheld-desk-scene')
    W, H = DESK_SIZE_M
    faces: list[Face] = [
        Face('desk', np.array([-W / 2, -H / 2, 0.0]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), (W, H),
             DESK_DENSITY),
        Face('desk_front', np.array([-W / 2, -H / 2, -DESK_THICKNESS_M]), np.array([1.0, 0, 0]), np.array([0, 0, 1.0]),
             (W, DESK_THICKNESS_M), 1000.0),
        Face('wall', np.array([-1.0, WALL_Y_M, FLOOR_Z_M]), np.array([1.0, 0, 0]), np.array([0, 0, 1.0]),
             (2.0, 1.7), 800.0),
        Face('floor', np.array([-2.0, -2.5, FLOOR_Z_M]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]),
             (4.0, 2.92), 150.0),
    ]
    textures: list[NDArray[np.uint8]] = [
        desk_texture(rng),
        np.clip(70 + 10 * smooth_noise(rng, faces[1].texture_shape(), (60, 2)), 0, 255).astype(np.uint8),
    ]
    wall_shape = faces[2].texture_shape()
    textures.append(room_wall_texture(rng, wall_shape, faces[2].density, *faces[2].size))
    textures.append(floor_texture(rng, faces[3].texture_shape(), faces[3].density))
    boxes = place_boxes(rng)
    for k, box in enumerate(boxes):
        for face, role in box_faces(box, k):
            faces.append(face)
            textures.append(box_texture(rng, box, face, role))
    textures = [np.clip(t.astype(np.float32) * desk_shade(f.normal), 0, 255).astype(np.uint8)
                for f, t in zip(faces, textures, strict=True)]
    width = 4096
    pos, height = pack_atlas([t.shape for t in textures], width)
    atlas = np.zeros((height, width), np.uint8)
    g = ATLAS_GUTTER
    for (x, y), t in zip(pos, textures, strict=True):
        atlas[y - g:y + t.shape[0] + g, x - g:x + t.shape[1] + g] = cv2.copyMakeBorder(
            t, g, g, g, g, cv2.BORDER_REPLICATE)
    faces = [replace(f, atlas_xy=xy) for f, xy in zip(faces, pos, strict=True)]
    return DeskScene(int(seed), tuple(faces), tuple(boxes), mip_pyramid(atlas))
