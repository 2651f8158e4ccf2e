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


def label_timeline(out_bag: str | Path, png: str | Path, correct_deg: float = 1.0) -> Path | None:
    """What a user saw, label by label (one row each) over the bag's time since the first
    panorama frame: green placed within ``correct_deg`` of the truth, red placed further off,
    grey shown as approximate, blank not shown; the wrong share of the label-time in the title.
    None when the bag has no markers or no truth to score them."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    from .annotation_metrics import CONFIDENT_NS
    from .annotation_metrics import label_timeline as timeline_data

    got = timeline_data(out_bag)
    if got is None:
        return None
    t0, t_end, labels, spans = got
    colours = {'right': (0.16, 0.75, 0.25), 'wrong': (0.85, 0.15, 0.15), 'approximate': (0.7, 0.7, 0.7)}
    fig, ax = plt.subplots(figsize=(9.0, 0.45 * len(labels) + 1.4))
    shown = wrong = 0.0
    for row, label in enumerate(labels):
        for a, b, states in spans:
            if label not in states or b <= a:
                continue
            err, ns = states[label]
            kind = 'approximate' if ns not in CONFIDENT_NS else ('right' if err <= correct_deg else 'wrong')
            if kind != 'approximate':
                shown += (b - a) * 1e-9
                wrong += (b - a) * 1e-9 if kind == 'wrong' else 0.0
            ax.broken_barh([((a - t0) * 1e-9, (b - a) * 1e-9)], (row - 0.35, 0.7), color=colours[kind])
    ax.set_yticks(range(len(labels)), [lab[:28] for lab in labels], fontsize=7)
    ax.set_xlim(0.0, max((t_end - t0) * 1e-9, 1e-3))
    ax.set_xlabel('time since the first panorama frame, s (header stamps)')
    share = f'{wrong / shown:.3f}' if shown > 0 else 'n/a'
    ax.set_title(f'labels shown: green within {correct_deg:g} deg, red further off, grey approximate '
                 f'(wrong label-time share {share})', fontsize=8)
    ax.invert_yaxis()
    fig.tight_layout()
    png = Path(png)
    fig.savefig(png, dpi=110)
    plt.close(fig)
    return png
