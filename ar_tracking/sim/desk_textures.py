"""Grey-level textures of the desk scene, painted in metres (all sizes below are metres).

The desk top (wood grain, printed sheets with text-like word blobs, bar charts, tables and
pictures, a calendar pad, a keyboard, a mouse pad, sticky notes, pens, coasters, stickers), the
boxes on it (cardboard, a stack of books, a printed box), the wall behind it and the tiled floor:
corners at full, half and quarter resolution for the SLAM of Klein & Murray 2009.
"""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from .model import DESK_DENSITY, DESK_SIZE_M, FLOOR_Z_M, Box, Face
from .textures import Painter, smooth_noise

def _text(p: Painter, rng: np.random.Generator, x: float, y: float, w: float, n_lines: int,
          size: float, val: float, pitch: float | None = None) -> None:
    """Lines of text-like word blobs (x-height bodies with a few ascenders)."""
    pitch = pitch or size * 1.7
    for i in range(n_lines):
        yy = y + i * pitch
        end = x + (w if i < n_lines - 1 else w * rng.uniform(0.3, 0.8))
        cx = x + (size * 2 if i == 0 and rng.random() < 0.3 else 0.0)
        while True:
            wl = int(rng.integers(1, 10)) * size * 0.55
            if cx + wl > end:
                break
            p.rect(cx, yy + size * 0.3, wl, size * 0.5, val)
            for _ in range(int(rng.integers(0, 3))):
                ax = cx + rng.uniform(0, max(wl - size * 0.15, 1e-4))
                p.rect(ax, yy, size * 0.15, size * 0.35, val)
            cx += wl + size * 0.5


def _picture(p: Painter, rng: np.random.Generator, x: float, y: float, w: float, h: float,
             lo: float = 20, hi: float = 235) -> None:
    """An abstract 'photo': a background and overlapping random polygons and discs."""
    p.rect(x, y, w, h, rng.uniform(lo, hi))
    for _ in range(int(rng.integers(12, 25))):
        val = rng.uniform(lo, hi)
        cx, cy = x + rng.uniform(0, w), y + rng.uniform(0, h)
        r = rng.uniform(0.08, 0.35) * min(w, h)
        if rng.random() < 0.3:
            p.circle(cx, cy, r * 0.6, val)
        else:
            n = int(rng.integers(3, 6))
            ang = np.sort(rng.uniform(0, 2 * np.pi, n))
            rad = r * rng.uniform(0.5, 1.0, n)
            pts = np.column_stack([np.clip(cx + rad * np.cos(ang), x, x + w),
                                   np.clip(cy + rad * np.sin(ang), y, y + h)])
            p.poly(pts, val)


def _bar_chart(p: Painter, rng: np.random.Generator, x: float, y: float, w: float, h: float) -> None:
    p.line([[x, y], [x, y + h], [x + w, y + h]], 40, 0.0008)
    n = int(rng.integers(4, 9))
    bw = w / (n * 1.5 + 0.5)
    for i in range(n):
        bh = rng.uniform(0.15, 0.95) * h
        p.rect(x + bw * (0.5 + 1.5 * i), y + h - bh, bw, bh, rng.choice([40.0, 90.0, 140.0]))


def _table(p: Painter, rng: np.random.Generator, x: float, y: float, w: float, rows: int, cols: int) -> None:
    rh = 0.007
    cw = w / cols
    p.rect(x, y, w, rh, 70)
    for r in range(rows + 1):
        p.line([[x, y + r * rh], [x + w, y + r * rh]], 50, 0.0004)
    for c in range(cols + 1):
        p.line([[x + c * cw, y], [x + c * cw, y + rows * rh]], 50, 0.0004)
    for r in range(1, rows):
        for c in range(cols):
            p.rect(x + c * cw + 0.002, y + r * rh + 0.002, rng.uniform(0.3, 0.8) * (cw - 0.004), 0.0028, 30)


def _paper(p: Painter, rng: np.random.Generator, x: float, y: float, angle: float) -> None:
    """An A4 sheet (its centre at x, y) with a title, paragraphs and a figure."""
    W, H = 0.210, 0.297
    with p.at(x, y, angle), p.at(-W / 2, -H / 2):
        p.rect(0, 0, W, H, rng.uniform(215, 235))
        m, yy = 0.022, 0.025
        _text(p, rng, m, yy, W * 0.6, 1, 0.007, 25, 0.012)
        yy += 0.018
        while yy < H - 0.03:
            kind = rng.random()
            if kind < 0.6:
                n = int(rng.integers(3, 8))
                _text(p, rng, m, yy, W - 2 * m, n, 0.0032, 35)
                yy += n * 0.0032 * 1.7 + 0.006
            elif kind < 0.75 and yy < H - 0.09:
                fw = rng.uniform(0.08, W - 2 * m)
                _bar_chart(p, rng, m + 0.005, yy, fw, 0.05)
                yy += 0.062
            elif kind < 0.88 and yy < H - 0.08:
                rows = int(rng.integers(3, 7))
                _table(p, rng, m, yy, W - 2 * m, rows, int(rng.integers(3, 6)))
                yy += rows * 0.007 + 0.008
            elif yy < H - 0.09:
                pw = rng.uniform(0.06, 0.12)
                _picture(p, rng, m, yy, pw, 0.06)
                _text(p, rng, m + pw + 0.006, yy, W - 2 * m - pw - 0.006, 6, 0.0032, 35)
                yy += 0.068
            else:
                break


def _sticky(p: Painter, rng: np.random.Generator, x: float, y: float, angle: float) -> None:
    with p.at(x, y, angle):
        p.rect(-0.038, -0.038, 0.076, 0.076, rng.uniform(185, 210))
        for _ in range(int(rng.integers(2, 5))):
            n = int(rng.integers(3, 7))
            pts = np.column_stack([rng.uniform(-0.03, 0.03, n), rng.uniform(-0.03, 0.03, n)])
            p.line(pts, rng.uniform(30, 80), 0.0012)


def _keyboard(p: Painter, rng: np.random.Generator, x: float, y: float, angle: float) -> None:
    with p.at(x, y, angle), p.at(-0.22, -0.07):
        p.rect(0, 0, 0.44, 0.14, 45)
        pitch, k = 0.019, 0.0155
        for r in range(5):
            c = 0.0
            while c < 0.42 - pitch:
                kw = k if rng.random() > 0.12 else k + pitch * int(rng.integers(1, 3))
                if c + kw > 0.43:
                    break
                p.rect(0.008 + c, 0.012 + r * pitch * 1.3 * 0.97, kw, k, 85)
                p.rect(0.011 + c, 0.015 + r * pitch * 1.3 * 0.97, 0.0025, 0.0035, 215)
                c += kw + pitch - k
        p.rect(0.12, 0.012 + 5 * pitch * 1.26, 0.2, 0.008, 85)


def _mousepad(p: Painter, rng: np.random.Generator, x: float, y: float, angle: float) -> None:
    with p.at(x, y, angle):
        p.rect(-0.11, -0.09, 0.22, 0.18, 55)
        p.circle(0.04, 0.03, 0.03, 190)
        p.poly([[0.02, 0.045], [0.06, 0.045], [0.04, 0.01]], 55)
        _text(p, rng, -0.09, -0.07, 0.12, 1, 0.008, 200, 0.012)
        p.rect(-0.09, 0.06, 0.05, 0.012, 160)


def _calendar(p: Painter, rng: np.random.Generator, x: float, y: float, angle: float, w: float, h: float,
              bg: float = 225) -> None:
    with p.at(x, y, angle), p.at(-w / 2, -h / 2):
        p.rect(0, 0, w, h, bg)
        p.rect(0, 0, w, h * 0.12, 70)
        _text(p, rng, w * 0.05, h * 0.025, w * 0.4, 1, h * 0.05, 220, h * 0.07)
        cols, rows = 7, 5
        cw, rh = w / cols, h * 0.88 / rows
        for r in range(rows + 1):
            p.line([[0, h * 0.12 + r * rh], [w, h * 0.12 + r * rh]], 90, 0.0006)
        for c in range(cols + 1):
            p.line([[c * cw, h * 0.12], [c * cw, h]], 90, 0.0006)
        for r in range(rows):
            for c in range(cols):
                x0, y0 = c * cw + cw * 0.08, h * 0.12 + r * rh + rh * 0.08
                n = int(rng.integers(1, 3))
                for i in range(n):
                    p.rect(x0 + i * cw * 0.1, y0, cw * 0.07, rh * 0.16, 40)
                if rng.random() < 0.25:
                    _text(p, rng, x0, y0 + rh * 0.35, cw * 0.8, 2, min(0.003, rh * 0.15), 60)


def _wood(rng: np.random.Generator, shape: tuple[int, int], density: float, base: float) -> NDArray[np.uint8]:
    """Wood grain: warped stripes along the texture's x axis plus low-frequency colour."""
    h, w = shape
    warp = smooth_noise(rng, shape, (w // 240, h // 60)) * 1.2 + smooth_noise(rng, shape, (w // 40, h // 20)) * 0.25
    yy = (np.arange(h, dtype=np.float32)[:, None] / density)
    period = 0.0035
    grain = np.sin(2 * np.pi * (yy / period + warp))
    low = smooth_noise(rng, shape, (max(2, w // 400), max(2, h // 400)))
    img = base + 9.0 * grain + 10.0 * low + 3.0 * smooth_noise(rng, shape, (w // 8, h // 8))
    return np.clip(img, 0, 255).astype(np.uint8)


def desk_texture(rng: np.random.Generator) -> NDArray[np.uint8]:
    W, H = DESK_SIZE_M
    shape = (int(math.ceil(H * DESK_DENSITY)), int(math.ceil(W * DESK_DENSITY)))
    img = _wood(rng, shape, DESK_DENSITY, rng.uniform(135, 160))
    p = Painter(img, DESK_DENSITY)
    # small stickers, screws, coins and scraps everywhere (corners on the bare wood too)
    for _ in range(90):
        x, y, s = rng.uniform(0, W), rng.uniform(0, H), rng.uniform(0.006, 0.03)
        val = rng.choice([rng.uniform(20, 80), rng.uniform(190, 245)])
        with p.at(x, y, rng.uniform(0, np.pi)):
            kind = rng.random()
            if kind < 0.4:
                p.rect(-s / 2, -s / 2 * rng.uniform(0.4, 1), s, s * rng.uniform(0.4, 1), val)
            elif kind < 0.7:
                p.poly([[0, -s / 2], [s / 2, s / 2], [-s / 2, s / 2]], val)
            else:
                p.circle(0, 0, s / 2, val)
                p.rect(-s / 4, -s / 10, s / 2, s / 5, 255 - val)
    _calendar(p, rng, rng.uniform(0.45, 0.75), rng.uniform(0.3, 0.42), rng.uniform(-0.08, 0.08), 0.42, 0.30)
    _keyboard(p, rng, rng.uniform(0.45, 0.7), rng.uniform(0.1, 0.15), rng.uniform(-0.1, 0.1))
    _mousepad(p, rng, rng.uniform(0.95, 1.05), rng.uniform(0.15, 0.3), rng.uniform(-0.3, 0.3))
    for x, y in ((rng.uniform(0.12, 0.3), rng.uniform(0.2, 0.45)), (rng.uniform(0.3, 0.5), rng.uniform(0.5, 0.68)),
                 (rng.uniform(0.8, 1.05), rng.uniform(0.45, 0.65)), (rng.uniform(0.55, 0.8), rng.uniform(0.2, 0.5))):
        _paper(p, rng, x, y, rng.uniform(-0.7, 0.7))
    for _ in range(5):
        _sticky(p, rng, rng.uniform(0.05, 1.15), rng.uniform(0.05, 0.75), rng.uniform(-0.5, 0.5))
    for _ in range(3):
        with p.at(rng.uniform(0.1, 1.1), rng.uniform(0.1, 0.7), rng.uniform(0, np.pi)):
            val = rng.uniform(20, 220)
            p.rect(-0.07, -0.0045, 0.14, 0.009, val)
            p.rect(0.045, -0.005, 0.03, 0.01, 255 - val)
            p.poly([[-0.07, -0.0045], [-0.085, 0], [-0.07, 0.0045]], 200)
    for _ in range(2):
        x, y = rng.uniform(0.1, 1.1), rng.uniform(0.1, 0.7)
        p.circle(x, y, 0.045, rng.uniform(60, 110))
        p.circle(x, y, 0.035, rng.uniform(170, 220), 0.004)
        p.circle(x, y, 0.012, 230)
    n = 8
    cable = np.column_stack([np.linspace(rng.uniform(0.2, 1.0), rng.uniform(0.2, 1.0), n) + rng.normal(0, 0.03, n),
                             np.linspace(0.8, rng.uniform(0.3, 0.6), n)])
    p.line(cable, 30, 0.006)
    return img


def _cardboard(rng: np.random.Generator, shape: tuple[int, int], density: float, w: float, h: float,
               top: bool) -> NDArray[np.uint8]:
    """Cardboard with tape (top) or shipping labels, a barcode, a printed logo and arrows (sides)."""
    img = np.clip(150 + 6 * smooth_noise(rng, shape, (max(2, shape[1] // 6), max(2, shape[0] // 6)))
                  + 8 * smooth_noise(rng, shape, (3, 3)), 0, 255).astype(np.uint8)
    p = Painter(img, density)
    if top:
        p.rect(0, h / 2 - 0.025, w, 0.05, 178)
        _text(p, rng, 0.02, h / 2 - 0.015, w * 0.6, 2, 0.008, 60, 0.014)
        p.rect(rng.uniform(0.01, w * 0.4), rng.uniform(0.005, 0.02), 0.07, 0.035, 228)
        _picture(p, rng, w * 0.55, h * 0.7, w * 0.35, h * 0.25, 40, 120)
        return img
    lx, ly = rng.uniform(0.005, max(0.006, w - 0.105)), rng.uniform(0.005, max(0.006, h - 0.07))
    p.rect(lx, ly, 0.1, 0.065, 232)
    bx = lx + 0.008
    while bx < lx + 0.07:
        bw = rng.uniform(0.0005, 0.002)
        p.rect(bx, ly + 0.006, bw, 0.025, 20)
        bx += bw + rng.uniform(0.0005, 0.002)
    _text(p, rng, lx + 0.008, ly + 0.036, 0.08, 3, 0.004, 30)
    # printed logo and brand name, 'this side up' arrows, a glass and an umbrella-like icon
    cx, cy = rng.uniform(0.03, max(0.031, w - 0.03)), rng.uniform(0.03, max(0.031, h - 0.03))
    p.circle(cx, cy, 0.022, 60)
    p.poly([[cx - 0.012, cy + 0.01], [cx, cy - 0.014], [cx + 0.012, cy + 0.01]], 150)
    _text(p, rng, max(0.0, cx - 0.05), min(h - 0.02, cy + 0.028), 0.1, 1, 0.012, 60, 0.02)
    ax, ay = rng.uniform(0.005, max(0.006, w - 0.05)), rng.uniform(0.005, max(0.006, h - 0.05))
    for k in range(2):
        x0 = ax + k * 0.025
        p.poly([[x0, ay + 0.02], [x0 + 0.01, ay], [x0 + 0.02, ay + 0.02], [x0 + 0.013, ay + 0.02],
                [x0 + 0.013, ay + 0.045], [x0 + 0.007, ay + 0.045], [x0 + 0.007, ay + 0.02]], 60)
    gx, gy = rng.uniform(0.005, max(0.006, w - 0.03)), rng.uniform(0.005, max(0.006, h - 0.04))
    p.line([[gx, gy], [gx + 0.025, gy], [gx + 0.018, gy + 0.02], [gx + 0.007, gy + 0.02]], 60, 0.002, True)
    p.rect(gx + 0.011, gy + 0.02, 0.003, 0.015, 60)
    p.rect(gx + 0.004, gy + 0.033, 0.017, 0.003, 60)
    for _ in range(int(rng.integers(2, 5))):  # stamped lot numbers and scuffs
        _text(p, rng, rng.uniform(0, w * 0.7), rng.uniform(0, h - 0.01), w * 0.25, 1, 0.005, 70)
    return img


def _book_top(rng: np.random.Generator, shape: tuple[int, int], density: float, w: float, h: float
              ) -> NDArray[np.uint8]:
    bg = rng.uniform(40, 200)
    img = np.full(shape, bg, np.uint8)
    p = Painter(img, density)
    fg = 230 if bg < 120 else 25
    _text(p, rng, 0.02, 0.02, w - 0.04, 2, 0.012, fg, 0.02)
    _picture(p, rng, 0.03, 0.07, w - 0.06, h * 0.45)
    _text(p, rng, 0.02, h - 0.035, w * 0.5, 1, 0.008, fg)
    return img


def _book_side(rng: np.random.Generator, shape: tuple[int, int], density: float, w: float, h: float,
               bands: list[tuple[float, float]], spine: bool) -> NDArray[np.uint8]:
    img = np.full(shape, 215, np.uint8)
    p = Painter(img, density)
    z = 0.0
    for thick, cover in bands:
        if spine:
            p.rect(0, z, w, thick, cover)
            _text(p, rng, 0.02, z + thick * 0.25, w * 0.6, 1, thick * 0.45, 255 - cover, thick)
        else:
            p.rect(0, z, w, thick, 220)
            for k in range(1, 6):
                p.line([[0, z + k * thick / 6], [w, z + k * thick / 6]], 195, 0.0004)
            p.rect(0, z, w, 0.0015, cover)
            p.rect(0, z + thick - 0.0015, w, 0.0015, cover)
        z += thick
    return img


def _pattern_box(rng: np.random.Generator, shape: tuple[int, int], density: float, w: float, h: float
                 ) -> NDArray[np.uint8]:
    img = np.full(shape, rng.uniform(170, 230), np.uint8)
    p = Painter(img, density)
    step = rng.uniform(0.015, 0.025)
    val = rng.uniform(40, 110)
    for i, y in enumerate(np.arange(0, h, step)):
        for x in np.arange((i % 2) * step / 2, w, step):
            if rng.random() < 0.5:
                p.circle(x, y, step * 0.3, val)
            else:
                p.poly([[x - step * 0.3, y + step * 0.3], [x, y - step * 0.3], [x + step * 0.3, y + step * 0.3]], val)
    p.rect(w * 0.1, h * 0.35, w * 0.8, min(0.03, h * 0.3), 240)
    _text(p, rng, w * 0.14, h * 0.35 + 0.004, w * 0.7, 1, min(0.012, h * 0.15), 30)
    return img


def room_wall_texture(rng: np.random.Generator, shape: tuple[int, int], density: float, w: float, h: float
                      ) -> NDArray[np.uint8]:
    """The wall from the floor up (local b = height above the floor); things hang above the desk."""
    img = np.clip(172 + 4 * smooth_noise(rng, shape, (shape[1] // 4, shape[0] // 4))
                  + 8 * smooth_noise(rng, shape, (4, 3)), 0, 255).astype(np.uint8)
    p = Painter(img, density, origin_m=(0.0, -FLOOR_Z_M))  # y = 0 at desk height
    px = rng.uniform(0.5, 0.9)
    p.rect(px - 0.01, 0.19, 0.37, 0.52, 40)
    _picture(p, rng, px, 0.2, 0.35, 0.4)
    _text(p, rng, px + 0.02, 0.62, 0.3, 2, 0.02, 220, 0.035)
    _calendar(p, rng, rng.uniform(1.3, 1.5), 0.45, 0.0, 0.3, 0.36)
    sx = rng.uniform(0.2, 0.4)
    p.rect(sx, 0.08, 0.08, 0.08, 235)
    p.rect(sx + 0.02, 0.11, 0.008, 0.02, 50)
    p.rect(sx + 0.05, 0.11, 0.008, 0.02, 50)
    return img


def floor_texture(rng: np.random.Generator, shape: tuple[int, int], density: float) -> NDArray[np.uint8]:
    h, w = shape
    tile = 0.4
    ii, jj = np.mgrid[0:h, 0:w]
    checker = ((ii / density // tile + jj / density // tile) % 2).astype(np.float32)
    img = 95 + 20 * checker + 6 * smooth_noise(rng, shape, (w // 3, h // 3))
    return np.clip(img, 0, 255).astype(np.uint8)


def box_texture(rng: np.random.Generator, box: Box, face: Face, role: str) -> NDArray[np.uint8]:
    shape = face.texture_shape()
    w, h = face.size
    if box.kind == 'cardboard':
        return _cardboard(rng, shape, face.density, w, h, role == 'top')
    if box.kind == 'books':
        if role == 'top':
            return _book_top(rng, shape, face.density, w, h)
        n = max(2, int(round(box.size[2] / 0.025)))
        cover_rng = np.random.default_rng(int(box.size[2] * 1e6))  # same bands on all four sides
        bands = [(box.size[2] / n, float(cover_rng.uniform(30, 200))) for _ in range(n)]
        return _book_side(rng, shape, face.density, w, h, bands, spine=role == 'side0')
    return _pattern_box(rng, shape, face.density, w, h)
