"""Albedo textures of the street scene: facades, the distant skyline, trees and lamp posts.

Each ``draw_*`` function paints an sRGB canvas with its coverage mask (alpha) at ``ppm`` pixels
per metre, and records the distinctive spots it drew (signs, clocks, doors) as features from
which :mod:`.layout` chooses the annotation anchors. :func:`to_albedo` turns a drawing into the
linear RGBA albedo a :class:`~.model.Plane` holds.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from .model import Image
from .textures import fbm, pick_colour, srgb_to_linear, value_noise

_WALL_COLOURS = [(214, 190, 150), (236, 226, 200), (176, 92, 70), (160, 160, 156),
                 (200, 214, 222), (206, 222, 196), (230, 200, 120), (190, 140, 110),
                 (240, 236, 228), (130, 120, 110), (222, 170, 150), (170, 190, 200)]
_TRIM_COLOURS = [(250, 250, 245), (60, 50, 45), (120, 110, 100), (210, 200, 180), (40, 60, 50)]
_ACCENT_COLOURS = [(180, 30, 30), (30, 90, 160), (30, 120, 60), (200, 150, 20), (120, 40, 120),
                   (20, 20, 20), (220, 90, 20), (0, 120, 130)]
_CURTAIN_COLOURS = [(230, 230, 220), (200, 60, 60), (240, 220, 160), (120, 140, 180),
                    (90, 60, 40), (250, 250, 250)]


@dataclass
class _FacadeDraw:
    """A facade being drawn (sRGB uint8 canvas) with the features found on the way."""

    img: NDArray[np.uint8]
    alpha: NDArray[np.uint8]
    ppm: float
    wall_top_px: int  # row of the top of the wall (roof items above it)
    windows: list[tuple[float, float, float, float, float]] = field(default_factory=list)
    awnings: list[tuple[float, float, float, float, float]] = field(default_factory=list)
    features: list[tuple[str, float, float]] = field(default_factory=list)  # kind, col, row

    def px(self, metres: float) -> int:
        return max(1, int(round(metres * self.ppm)))

    def row_of(self, height_above_ground_m: float) -> int:
        """Canvas row of a height above the ground."""
        return int(round(self.img.shape[0] - height_above_ground_m * self.ppm))


def _facade_wall_texture(rng: np.random.Generator, h: int, w: int, ppm: float,
                  colour: tuple[int, int, int]) -> NDArray[np.uint8]:
    """Plaster, stone blocks or panels with dirt: never a flat area."""
    style = int(rng.integers(3))
    base = np.empty((h, w, 3), np.float32)
    base[:] = colour
    shade = 1.0 + 0.07 * fbm(rng, (h, w), 2.0 * ppm, 4) + 0.05 * fbm(rng, (h, w), 0.25 * ppm, 2)
    if style == 1:  # stone blocks in running bond, each block its own tint
        bh, bw = rng.uniform(0.3, 0.5), rng.uniform(0.6, 1.1)
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32) / ppm
        row_i = np.floor(yy / bh)
        xs = xx + 0.5 * bw * (row_i % 2)
        col_i = np.floor(xs / bw)
        tint = (np.sin(row_i * 12.9898 + col_i * 78.233) * 43758.5453) % 1.0
        shade *= 0.9 + 0.2 * tint
        joint = np.minimum(np.minimum(yy % bh, bh - yy % bh), np.minimum(xs % bw, bw - xs % bw))
        shade *= np.where(joint < 0.025, 0.72, 1.0)
    elif style == 2:  # large panels with dark joints
        ph, pw = rng.uniform(0.8, 1.6), rng.uniform(1.2, 2.5)
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32) / ppm
        joint = np.minimum(np.minimum(yy % ph, ph - yy % ph), np.minimum(xx % pw, pw - xx % pw))
        tint = (np.sin(np.floor(yy / ph) * 3.1 + np.floor(xx / pw) * 17.7) * 9137.3) % 1.0
        shade *= (0.94 + 0.12 * tint) * np.where(joint < 0.03, 0.65, 1.0)
    # Rain streaks: darker vertical stripes fading downwards.
    streaks = value_noise(rng, (1, w), 0.4 * ppm)[0]
    fade = np.linspace(1.0, 0.3, h, dtype=np.float32)[:, None]
    shade *= 1.0 - 0.06 * np.clip(streaks, 0, 1)[None, :] * fade
    return np.clip(base * shade[..., None], 0, 255).astype(np.uint8)


def _draw_window(rng: np.random.Generator, f: _FacadeDraw, x0: int, y0: int, x1: int, y1: int,
                 trim: tuple[int, int, int], classic: bool, shutters: bool,
                 special: bool = False) -> None:
    img = f.img
    t = max(1, f.px(0.08))
    glass_top = np.array([90, 110, 140]) + rng.integers(-20, 20, 3)
    glass_bot = np.array([40, 45, 55]) + rng.integers(-10, 10, 3)
    ramp = np.linspace(0, 1, max(1, y1 - y0))[:, None, None]
    img[y0:y1, x0:x1] = (glass_top * (1 - ramp) + glass_bot * ramp).astype(np.uint8)
    if rng.random() < 0.55:  # curtain on one side or both
        c = pick_colour(rng, _CURTAIN_COLOURS, 15)
        cw = int((x1 - x0) * rng.uniform(0.2, 0.5))
        if rng.random() < 0.5:
            cv2.rectangle(img, (x0, y0), (x0 + cw, y1 - 1), c, -1)
        else:
            cv2.rectangle(img, (x1 - cw, y0), (x1 - 1, y1 - 1), c, -1)
    if rng.random() < 0.15:  # a lit room
        cv2.rectangle(img, (x0 + t, y0 + t), (x1 - t, (y0 + y1) // 2), (235, 215, 150), -1)
    cv2.rectangle(img, (x0, y0), (x1 - 1, y1 - 1), trim, t)
    if classic:
        xm, ym = (x0 + x1) // 2, y0 + (y1 - y0) // 3
        cv2.line(img, (xm, y0), (xm, y1), trim, max(1, t // 2 + 1))
        cv2.line(img, (x0, ym), (x1, ym), trim, max(1, t // 2 + 1))
        # window head: a pediment or a flat lintel
        if rng.random() < 0.5:
            pts = np.array([[x0 - t, y0 - t], [x1 + t, y0 - t], [(x0 + x1) // 2, y0 - f.px(0.45)]])
            cv2.fillPoly(img, [pts.astype(np.int32)], trim)
        else:
            cv2.rectangle(img, (x0 - t, y0 - f.px(0.2)), (x1 + t, y0 - 1), trim, -1)
    cv2.rectangle(img, (x0 - t, y1), (x1 + t, y1 + f.px(0.1)), (200, 200, 195), -1)  # sill
    if shutters:
        sc = pick_colour(rng, [(40, 90, 50), (120, 70, 40), (60, 80, 120), (150, 150, 140)], 10)
        sw = (x1 - x0) // 2
        for xa in (x0 - sw - t, x1 + t):
            cv2.rectangle(img, (xa, y0), (xa + sw, y1), sc, -1)
            for yy in range(y0 + 2, y1, max(2, f.px(0.12))):
                cv2.line(img, (xa, yy), (xa + sw, yy), tuple(int(v * 0.6) for v in sc), 1)
    if special:  # a flower box: the one window an author would label
        fc = [(200, 30, 60), (240, 200, 40), (230, 230, 240), (220, 80, 160)]
        cv2.rectangle(img, (x0 - t, y1 + f.px(0.1)), (x1 + t, y1 + f.px(0.35)), (90, 60, 40), -1)
        for _ in range(int((x1 - x0) * 1.5)):
            cx = int(rng.integers(x0 - t, x1 + t + 1))
            cy = int(rng.integers(y1 - f.px(0.15), y1 + f.px(0.15)))
            cv2.circle(img, (cx, cy), max(1, f.px(0.06)), fc[int(rng.integers(len(fc)))], -1)
    f.windows.append((x0, y0, x1, y1, float(rng.uniform(0.12, 0.3))))


def _draw_sign(rng: np.random.Generator, f: _FacadeDraw, x0: int, x1: int, y0: int, y1: int,
               word: str) -> None:
    bg = pick_colour(rng, _ACCENT_COLOURS, 15)
    fg = (250, 245, 230) if sum(bg) < 400 else (20, 20, 20)
    cv2.rectangle(f.img, (x0, y0), (x1, y1), bg, -1)
    cv2.rectangle(f.img, (x0, y0), (x1, y1), tuple(int(c * 0.5) for c in bg), max(1, f.px(0.05)))
    font = cv2.FONT_HERSHEY_DUPLEX
    th = max(4, int((y1 - y0) * 0.6))
    (tw, tht), _ = cv2.getTextSize(word, font, 1.0, 2)
    scale = min(th / tht, 0.9 * (x1 - x0) / tw)
    (tw, tht), _ = cv2.getTextSize(word, font, scale, 1)
    org = ((x0 + x1 - tw) // 2, (y0 + y1 + tht) // 2)
    cv2.putText(f.img, word, org, font, scale, fg, max(1, int(round(scale * 1.5))), cv2.LINE_AA)


def _draw_ground_floor(rng: np.random.Generator, f: _FacadeDraw, bays: list[tuple[int, int]],
                       gf_h: float, trim: tuple[int, int, int], words: list[str]) -> None:
    """Shops, doors, signs and awnings along the ground floor."""
    img = f.img
    ground = img.shape[0]
    door_bays = set(rng.choice(len(bays), size=max(1, len(bays) // 3), replace=False).tolist())
    # Signs over runs of 1-3 bays.
    i = 0
    while i < len(bays):
        run = int(min(len(bays) - i, rng.integers(1, 4)))
        if words and rng.random() < 0.7:
            xa, xb = bays[i][0], bays[i + run - 1][1]
            ya, yb = f.row_of(gf_h - 0.3), f.row_of(gf_h - 1.1)
            word = words.pop()
            _draw_sign(rng, f, xa + f.px(0.2), xb - f.px(0.2), ya, yb, word)
            f.features.append((f'Sign "{word}"', (xa + xb) / 2, (ya + yb) / 2))
            if rng.random() < 0.6:  # striped awning under the sign
                ac = pick_colour(rng, _ACCENT_COLOURS, 10)
                top, bot = yb + 1, f.row_of(gf_h - 1.8)
                stripe = max(2, f.px(0.3))
                for k, x in enumerate(range(xa + f.px(0.2), xb - f.px(0.2), stripe)):
                    col = ac if k % 2 == 0 else (240, 240, 235)
                    cv2.rectangle(img, (x, top), (min(x + stripe, xb - f.px(0.2)), bot), col, -1)
                f.awnings.append((xa + f.px(0.2), top, xb - f.px(0.2), bot,
                                  float(rng.uniform(1.0, 1.6))))
        i += run
    for k, (xa, xb) in enumerate(bays):
        if k in door_bays:
            dw = f.px(rng.uniform(1.0, 1.6))
            xc = (xa + xb) // 2
            x0, x1 = xc - dw // 2, xc + dw // 2
            y0 = f.row_of(rng.uniform(2.2, 2.7))
            dc = pick_colour(rng, [(90, 55, 30), (40, 40, 45), (120, 30, 30), (30, 70, 50),
                              (60, 80, 110)], 10)
            cv2.rectangle(img, (x0 - f.px(0.15), y0 - f.px(0.15)), (x1 + f.px(0.15), ground),
                          trim, -1)
            cv2.rectangle(img, (x0, y0), (x1, ground), dc, -1)
            # panels, a glass pane and a handle
            cv2.rectangle(img, (x0 + f.px(0.12), y0 + f.px(0.12)), (x1 - f.px(0.12),
                          (y0 + ground) // 2), (70, 85, 100), -1)
            cv2.line(img, (xc, y0), (xc, ground), tuple(int(c * 0.6) for c in dc), 1)
            cv2.circle(img, (xc + f.px(0.15), f.row_of(1.0)), max(1, f.px(0.05)),
                       (210, 190, 90), -1)
            f.features.append(('Door', (x0 + x1) / 2, (y0 + ground) / 2))
        else:
            x0, x1 = xa + f.px(0.4), xb - f.px(0.4)
            y0, y1 = f.row_of(gf_h - 2.0), f.row_of(0.5)
            if x1 - x0 > 4:
                _draw_shop_window(rng, f, x0, y0, x1, y1, trim)


def _solid_rect(img: NDArray[np.uint8], alpha: NDArray[np.uint8], p0: tuple[int, int],
                p1: tuple[int, int], colour: tuple[int, int, int]) -> None:
    """A filled rectangle drawn into the colour image and marked opaque in the alpha mask."""
    cv2.rectangle(img, p0, p1, colour, -1)
    cv2.rectangle(alpha, p0, p1, 255, -1)


def _solid_poly(img: NDArray[np.uint8], alpha: NDArray[np.uint8], pts: NDArray[np.int32],
                colour: tuple[int, int, int]) -> None:
    cv2.fillPoly(img, [pts.astype(np.int32)], colour)
    cv2.fillPoly(alpha, [pts.astype(np.int32)], 255)


def _draw_shop_window(rng: np.random.Generator, f: _FacadeDraw, x0: int, y0: int, x1: int,
                      y1: int, trim: tuple[int, int, int]) -> None:
    img = f.img
    img[y0:y1, x0:x1] = (55, 60, 70)
    for _ in range(int(rng.integers(3, 9))):  # goods on display
        w, h = f.px(rng.uniform(0.1, 0.5)), f.px(rng.uniform(0.1, 0.6))
        cx = int(rng.integers(x0, max(x0 + 1, x1 - w)))
        cy = int(rng.integers(y0 + (y1 - y0) // 3, max(y0 + 1, y1 - h)))
        colour = pick_colour(rng, _ACCENT_COLOURS + _CURTAIN_COLOURS, 30)
        cv2.rectangle(img, (cx, cy), (cx + w, cy + h), colour, -1)
    cv2.rectangle(img, (x0, y0), (x1, y1), trim, max(1, f.px(0.08)))
    if rng.random() < 0.5:
        xm = (x0 + x1) // 2
        cv2.line(img, (xm, y0), (xm, y1), trim, max(1, f.px(0.06)))
    f.windows.append((x0, y0, x1, y1, float(rng.uniform(0.08, 0.2))))


def _draw_roof(rng: np.random.Generator, f: _FacadeDraw, trim: tuple[int, int, int]) -> None:
    """Cornice at the wall top, and chimneys, antennas or a pitched roof above it."""
    img, a = f.img, f.alpha
    top = f.wall_top_px
    w = img.shape[1]
    cv2.rectangle(img, (0, top), (w, top + f.px(0.5)), trim, -1)
    step = max(3, f.px(0.35))
    for x in range(0, w, step):  # dentils
        cv2.rectangle(img, (x, top + f.px(0.5)), (x + step // 2, top + f.px(0.7)),
                      tuple(int(c * 0.7) for c in trim), -1)
    if rng.random() < 0.5:  # a pitched roof seen from below: a tiled band
        rh = f.px(rng.uniform(1.2, 2.6))
        rc = pick_colour(rng, [(150, 60, 40), (80, 80, 85), (110, 70, 50)], 15)
        inset = f.px(rng.uniform(0.5, 2.0))
        pts = np.array([[0, top], [w - 1, top], [w - 1 - inset, top - rh], [inset, top - rh]])
        _solid_poly(img, a, pts, rc)
        for y in range(top - rh, top, max(2, f.px(0.25))):
            cv2.line(img, (0, y), (w, y), tuple(int(c * 0.75) for c in rc), 1)
        roof_top = top - rh
    else:
        roof_top = top
    for _ in range(int(rng.integers(1, 5))):  # chimneys
        cw, ch = f.px(rng.uniform(0.5, 1.0)), f.px(rng.uniform(0.8, 1.8))
        cx = int(rng.integers(0, max(1, w - cw)))
        col = pick_colour(rng, [(150, 70, 50), (120, 120, 120), (180, 170, 150)], 15)
        _solid_rect(img, a, (cx, roof_top - ch), (cx + cw, roof_top + 2), col)
        _solid_rect(img, a, (cx - 1, roof_top - ch), (cx + cw + 1, roof_top - ch + f.px(0.15)),
                    (60, 60, 60))
    if rng.random() < 0.6:  # an antenna
        ax = int(rng.integers(0, w))
        ah = f.px(rng.uniform(1.5, 3.0))
        cv2.line(img, (ax, roof_top), (ax, roof_top - ah), (50, 50, 50), 1)
        cv2.line(a, (ax, roof_top), (ax, roof_top - ah), 255, 1)
        for k in range(3):
            y = roof_top - ah + k * f.px(0.4)
            hw = f.px(0.5 - 0.1 * k)
            cv2.line(img, (ax - hw, y), (ax + hw, y), (50, 50, 50), 1)
            cv2.line(a, (ax - hw, y), (ax + hw, y), 255, 1)


def _draw_clock(f: _FacadeDraw, xc: int, yc: int, r: int) -> None:
    img = f.img
    cv2.circle(img, (xc, yc), r + 2, (60, 50, 40), -1)
    cv2.circle(img, (xc, yc), r, (245, 240, 225), -1)
    for k in range(12):
        ang = k * math.pi / 6
        p0 = (int(xc + 0.8 * r * math.sin(ang)), int(yc - 0.8 * r * math.cos(ang)))
        p1 = (int(xc + 0.95 * r * math.sin(ang)), int(yc - 0.95 * r * math.cos(ang)))
        cv2.line(img, p0, p1, (20, 20, 20), 1 + (k % 3 == 0))
    cv2.line(img, (xc, yc), (int(xc + 0.5 * r), int(yc - 0.3 * r)), (10, 10, 10), 2)
    cv2.line(img, (xc, yc), (int(xc - 0.2 * r), int(yc - 0.8 * r)), (10, 10, 10), 1)
    f.features.append(('Clock', float(xc), float(yc)))


def draw_facade(rng: np.random.Generator, width_m: float, height_m: float, ppm: float,
                words: list[str], tower: bool = False) -> _FacadeDraw:
    """A building facade: wall texture, floors of windows, ground floor shops, roof items."""
    roof_m = 4.5
    h = int(round((height_m + roof_m) * ppm))
    w = max(8, int(round(width_m * ppm)))
    img = np.zeros((h, w, 3), np.uint8)
    alpha = np.zeros((h, w), np.uint8)
    wall_top = int(round(roof_m * ppm))
    f = _FacadeDraw(img, alpha, ppm, wall_top)
    wall_colour = pick_colour(rng, _WALL_COLOURS, 14)
    trim = pick_colour(rng, _TRIM_COLOURS, 10)
    img[wall_top:] = _facade_wall_texture(rng, h - wall_top, w, ppm, wall_colour)
    alpha[wall_top:] = 255
    classic = rng.random() < 0.6
    shutters = classic and rng.random() < 0.4
    gf_h = rng.uniform(3.8, 4.8)
    fl_h = rng.uniform(3.0, 3.6)
    bay_w = rng.uniform(2.4, 3.6)
    n_bays = max(1, int(width_m / bay_w))
    margin = (width_m - n_bays * bay_w) / 2
    bays = [(f.px(margin + k * bay_w), f.px(margin + (k + 1) * bay_w)) for k in range(n_bays)]
    win_w, win_h = rng.uniform(0.9, 1.4), rng.uniform(1.4, 1.9)
    n_floors = max(0, int((height_m - gf_h - 0.8) / fl_h))
    special = (int(rng.integers(n_floors)), int(rng.integers(n_bays))) if n_floors else (-1, -1)
    clock_floor = n_floors - 1 if tower and n_floors >= 3 else -1
    for fl in range(n_floors):
        base = gf_h + fl * fl_h
        if classic:  # string course between floors
            y = f.row_of(base)
            cv2.rectangle(img, (0, y - f.px(0.12)), (w, y + f.px(0.12)), trim, -1)
        for b, (xa, xb) in enumerate(bays):
            if fl == clock_floor and b == n_bays // 2:
                continue
            xc = (xa + xb) // 2
            x0, x1 = xc - f.px(win_w / 2), xc + f.px(win_w / 2)
            y1 = f.row_of(base + 0.9)
            y0 = f.row_of(base + 0.9 + win_h)
            is_special = (fl, b) == special
            _draw_window(rng, f, x0, y0, x1, y1, trim, classic, shutters, is_special)
            if is_special:
                f.features.append(('Window', (x0 + x1) / 2, (y0 + y1) / 2))
    if clock_floor >= 0:
        xa, xb = bays[n_bays // 2]
        r = f.px(min(1.2, bay_w * 0.4))
        _draw_clock(f, (xa + xb) // 2, f.row_of(gf_h + clock_floor * fl_h + fl_h / 2), r)
    _draw_ground_floor(rng, f, bays, gf_h, trim, words)
    if rng.random() < 0.7:  # a drainpipe
        x = int(rng.integers(0, w))
        cv2.line(img, (x, wall_top), (x, h), (90, 90, 95), max(1, f.px(0.1)))
    for _ in range(int(rng.integers(0, 4))):  # posters and plates at street level
        pw, ph = f.px(rng.uniform(0.3, 0.8)), f.px(rng.uniform(0.4, 1.0))
        px, py = int(rng.integers(0, max(1, w - pw))), f.row_of(rng.uniform(1.2, 2.2))
        cv2.rectangle(img, (px, py), (px + pw, py + ph), pick_colour(rng, _ACCENT_COLOURS, 40), -1)
        cv2.line(img, (px + 2, py + ph // 3), (px + pw - 2, py + ph // 3), (240, 240, 240), 1)
    _draw_roof(rng, f, trim)
    # ambient occlusion near the ground
    gh = f.px(0.5)
    img[h - gh:] = (img[h - gh:] * np.linspace(1.0, 0.75, gh)[:, None, None]).astype(np.uint8)
    return f


def draw_far_block(rng: np.random.Generator, width_m: float, height_m: float, ppm: float
                   ) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """A distant building: flat colour, a grid of window dots, sometimes a spire or crane."""
    extra = 12.0
    h, w = int(round((height_m + extra) * ppm)), max(4, int(round(width_m * ppm)))
    img = np.zeros((h, w, 3), np.uint8)
    a = np.zeros((h, w), np.uint8)
    top = int(round(extra * ppm))
    col = np.array(pick_colour(rng, _WALL_COLOURS, 20), dtype=np.float32)
    tex = 1.0 + 0.08 * fbm(rng, (h - top, w), 3 * ppm, 3)
    img[top:] = np.clip(col * tex[..., None], 0, 255).astype(np.uint8)
    a[top:] = 255
    dark = tuple(int(c * 0.45) for c in col)
    fy, fx = rng.uniform(3.0, 3.6), rng.uniform(2.5, 3.5)
    for y in np.arange(top + ppm * 1.5, h - ppm * 1.0, fy * ppm):
        for x in np.arange(ppm * 0.8, w - ppm * 0.8, fx * ppm):
            if rng.random() < 0.9:
                p1 = (int(x + 1.2 * ppm), int(y + 1.5 * ppm))
                cv2.rectangle(img, (int(x), int(y)), p1, dark, -1)
    if rng.random() < 0.25:  # spire or crane
        x = int(rng.integers(0, w))
        sh = int(rng.uniform(0.4, 1.0) * top)
        _solid_poly(img, a, np.array([[x - 3, top], [x + 3, top], [x, top - sh]]), dark)
    roof_c = tuple(int(c * 0.6) for c in col)
    cv2.rectangle(img, (0, top), (w, top + 2), roof_c, -1)
    return img, a


def draw_tree(rng: np.random.Generator, width_m: float, height_m: float, ppm: float
              ) -> tuple[NDArray[np.uint8], NDArray[np.uint8], Image]:
    """A deciduous tree: trunk and a crown of leaf clumps; returns rgb, alpha, local normals."""
    h, w = int(round(height_m * ppm)), int(round(width_m * ppm))
    img = np.zeros((h, w, 3), np.uint8)
    a = np.zeros((h, w), np.uint8)
    tw = max(2, int(0.35 * ppm))
    trunk_top = int(h * 0.45)
    _solid_rect(img, a, (w // 2 - tw // 2, trunk_top), (w // 2 + tw // 2, h), (70, 55, 40))
    cx, cy = w / 2, h * 0.36
    rx, ry = w * 0.48, h * 0.35
    greens = [(60, 100, 40), (80, 120, 50), (50, 85, 35), (100, 130, 60), (70, 110, 30)]
    n = int(rx * ry / (0.25 * ppm) ** 2 * 0.9)
    for _ in range(n):
        ang, rad = rng.uniform(0, 2 * math.pi), math.sqrt(rng.uniform(0, 1))
        px, py = cx + rx * rad * math.cos(ang), cy + ry * rad * math.sin(ang)
        r = int(rng.uniform(0.15, 0.45) * ppm)
        shade = 0.75 + 0.5 * (1 - rad)
        c = tuple(int(min(255, v * shade)) for v in pick_colour(rng, greens, 12))
        cv2.circle(img, (int(px), int(py)), max(1, r), c, -1)
        cv2.circle(a, (int(px), int(py)), max(1, r), 255, -1)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    nx, ny = (xx - cx) / rx, (cy - yy) / ry
    nz = np.sqrt(np.clip(1 - nx ** 2 - ny ** 2, 0.05, 1))
    normals = np.stack([nx, ny, nz], -1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    trunk = yy > trunk_top + 0.2 * ppm
    normals[trunk] = (0.0, 0.0, 1.0)
    return img, a, normals.astype(np.float32)


def draw_pole(rng: np.random.Generator, height_m: float, ppm: float
              ) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """A lamp post or a sign post."""
    w, h = int(1.2 * ppm), int(round(height_m * ppm))
    img = np.zeros((h, w, 3), np.uint8)
    a = np.zeros((h, w), np.uint8)
    col = pick_colour(rng, [(40, 45, 40), (70, 70, 75), (30, 50, 40)], 8)
    pw = max(2, int(0.14 * ppm))
    xc = w // 2

    def dx(metres: float) -> int:
        return int(metres * ppm)

    _solid_rect(img, a, (xc - pw // 2, int(0.08 * h)), (xc + pw // 2, h), col)
    if rng.random() < 0.6:  # lamp head
        yl = int(0.12 * h)
        _solid_poly(img, a, np.array([[xc - dx(0.45), yl], [xc + dx(0.45), yl],
                                      [xc + dx(0.2), 0], [xc - dx(0.2), 0]]), col)
        _solid_rect(img, a, (xc - dx(0.3), yl), (xc + dx(0.3), yl + 3), (230, 230, 200))
    else:  # a street sign
        sc = pick_colour(rng, [(20, 80, 160), (240, 240, 240), (200, 30, 30)], 5)
        y0 = int(0.1 * h)
        _solid_rect(img, a, (xc - dx(0.5), y0), (xc + dx(0.5), y0 + dx(0.5)), sc)
        cv2.rectangle(img, (xc - dx(0.4), y0 + 3), (xc + dx(0.4), y0 + dx(0.5) - 3),
                      (250, 250, 250) if sum(sc) < 600 else (30, 30, 30), 1)
    return img, a


def to_albedo(img: NDArray[np.uint8], alpha: NDArray[np.uint8]) -> Image:
    """Linear RGBA albedo from an sRGB drawing and its coverage mask."""
    rgb = srgb_to_linear(img.astype(np.float32) / 255.0)
    return np.dstack([rgb, alpha.astype(np.float32) / 255.0]).astype(np.float32)
