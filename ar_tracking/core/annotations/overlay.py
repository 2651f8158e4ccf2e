"""Drawing annotation labels on the live camera image (Langlotz 2011 sec. 3.2, 5; Fig. 2, 4).

An annotation placed in the panorama frame at unit direction d appears in the camera at
``K R_cam_pano d`` (R_cam_pano = R_pano_cam^T, the current orientation). Labels are drawn with a
dot at the anchor and the text beside it: green for matched annotations, orange for those
placed by the global alignment only (inferred), grey with a hollow dot and "~" before the text
for approximate ones (shown before the alignment is supported). numpy / OpenCV only.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from ..panorama.cylinder import project_to_image
from ..rectification import project_through_lens

Array = NDArray[np.float64]

COLOURS_RGB = {'matched': (40, 220, 60), 'inferred': (255, 150, 30), 'approximate': (170, 170, 170)}


@dataclass(frozen=True)
class Label:
    text: str
    direction: Array  # unit vector in the panorama frame
    status: str = 'matched'


def project_labels(labels: list[Label], R_pano_cam: Array, K: Array, size: tuple[int, int],
                   D: Array | None = None, model: str = '') -> list[tuple[Label, float, float]]:
    """(label, x, y) of the labels in front of the camera and inside the image (h, w); with a
    lens distortion ``D`` (camera_info's coefficients and ``model``) where the raw, distorted
    frame shows them."""
    if not labels:
        return []
    d = np.array([lab.direction for lab in labels], float)
    p_cam = d @ np.asarray(R_pano_cam, float)
    if D is not None and np.any(np.asarray(D, float) != 0):
        x, y, front = project_through_lens(np.asarray(K, float), np.asarray(D, float), p_cam, model)
    else:
        x, y, front = project_to_image(np.asarray(K, float), p_cam)
    h, w = size
    out = []
    for lab, xi, yi, f in zip(labels, x, y, front):
        if f and 0 <= xi < w and 0 <= yi < h:
            out.append((lab, float(xi), float(yi)))
    return out


def draw_labels(rgb: NDArray[np.uint8], placed: list[tuple[Label, float, float]],
                scale: float = 0.4) -> NDArray[np.uint8]:
    """A copy of the RGB image with the labels drawn at their positions."""
    out = np.ascontiguousarray(rgb).copy()
    h, w = out.shape[:2]
    for lab, x, y in placed:
        colour = COLOURS_RGB.get(lab.status, (255, 255, 255))
        p = (int(round(x)), int(round(y)))
        text = lab.text
        if lab.status == 'approximate':  # not yet aligned: marked, with a hollow dot
            text = '~' + text
            cv2.circle(out, p, 4, colour, 1, cv2.LINE_AA)
        else:
            cv2.circle(out, p, 3, colour, -1, cv2.LINE_AA)
        (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
        tx = min(max(p[0] + 5, 0), max(w - tw, 0))
        ty = min(max(p[1] - 5, th), h - 1)
        cv2.rectangle(out, (tx - 1, ty - th - 2), (tx + tw + 1, ty + 2), (0, 0, 0), -1)
        cv2.putText(out, text, (tx, ty), cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 1, cv2.LINE_AA)
    return out
