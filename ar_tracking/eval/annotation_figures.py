"""Report figure of the annotation area (Langlotz 2011 Fig. 4): the browsing panorama with the
re-detected labels (green matched, orange inferred by the global alignment) and a few frames of
the AR view (``/ar/overlay``) when the output bag has them."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..core.annotations.overlay import COLOURS_RGB
from ..core.panorama.cylinder import CylinderGeometry
from ..io.bags import BagReader


def _image(msg) -> np.ndarray:
    from ..ros.conversions import image_to_array

    return image_to_array(msg)


def annotation_figure(out_bag: str | Path, png: str | Path, overlay_frames: int = 3) -> Path | None:
    """Write the figure to ``png``; None when the bag has no panorama map or markers."""
    import cv2
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    with BagReader(out_bag) as bag:
        topics = bag.topics
        if '/panorama/image' not in topics or '/annotations/markers' not in topics:
            return None
        pano = None
        for m in bag.messages(['/panorama/image']):
            pano = m
        pano = _image(bag.deserialize(pano))
        markers = bag.read_all('/annotations/markers')[-1][1].markers
        overlays = []
        if '/ar/overlay' in topics:
            n = bag.message_count(['/ar/overlay'])
            keep = set(np.linspace(n // 4, n - 1, overlay_frames).astype(int).tolist()) if n else set()
            for k, m in enumerate(bag.messages(['/ar/overlay'])):
                if k in keep:
                    overlays.append(_image(bag.deserialize(m)))
    g = pano.astype(np.float32)
    g = (g * 255.0 / max(float(g.max()), 1.0)).astype(np.uint8)
    rgb = cv2.cvtColor(g if g.ndim == 2 else g[:, :, 0], cv2.COLOR_GRAY2RGB)
    geo = CylinderGeometry(rgb.shape[1], rgb.shape[0])
    for mk in markers:
        if mk.action != 0:
            continue
        d = np.array([mk.pose.position.x, mk.pose.position.y, mk.pose.position.z])
        if not np.all(np.isfinite(d)) or not d.any():
            continue
        u, v = geo.project(d / np.linalg.norm(d))
        colour = COLOURS_RGB.get(mk.ns, (255, 255, 255))
        p = (int(round(float(u))), int(round(float(v))))
        cv2.circle(rgb, p, 6, colour, 2, cv2.LINE_AA)
        cv2.putText(rgb, mk.text, (p[0] + 8, p[1] - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.6, colour, 2, cv2.LINE_AA)
    rows = 2 if overlays else 1
    fig = plt.figure(figsize=(14, 3.5 * rows))
    ax = fig.add_subplot(rows, 1, 1)
    ax.imshow(rgb)
    ax.set_title('browsing panorama: re-detected annotations (green matched, orange inferred)')
    ax.axis('off')
    for k, img in enumerate(overlays):
        a = fig.add_subplot(rows, len(overlays), len(overlays) + k + 1)
        a.imshow(img)
        a.axis('off')
        a.set_title('ar/overlay')
    fig.tight_layout()
    png = Path(png)
    fig.savefig(png, dpi=80)
    plt.close(fig)
    return png
