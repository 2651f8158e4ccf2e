"""Extra report figures from an output bag: products that are images in their own right.

Each function returns PNG bytes or None when the bag does not have the product.
"""
from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from ..io.bags import BagError, BagReader
from ..ros.conversions import ConversionError, image_to_array

logger = logging.getLogger(__name__)

PANORAMA_IMAGE_TOPIC = '/panorama/image'


def panorama_png(bag_path: str | Path) -> bytes | None:
    """The last panorama map of the bag (16-bit EDR map shown with a linear tone-mapping)."""
    with BagReader(bag_path) as bag:
        if PANORAMA_IMAGE_TOPIC not in bag.topics:
            return None
        last = None
        for m in bag.messages([PANORAMA_IMAGE_TOPIC]):
            last = m
        if last is None:
            return None
        try:
            msg = bag.deserialize(last)
        except BagError as exc:
            logger.warning('panorama image not shown: %s', exc)
            return None
    try:
        arr = image_to_array(msg)  # honours step, encoding and byte order
    except ConversionError as exc:
        logger.warning('panorama image not shown: %s', exc)
        return None
    img = arr.astype(np.float64)
    mapped = img > 0
    if mapped.any():  # linear tone-mapping of the mapped range to 8 bits
        lo, hi = np.percentile(img[mapped], [0.5, 99.5])
        img = np.clip((img - lo) / max(hi - lo, 1e-9) * 255.0, 0, 255)
    out = img.astype(np.uint8)
    if out.ndim == 3 and msg.encoding.startswith('rgb'):
        out = cv2.cvtColor(out, cv2.COLOR_RGB2BGR)
    ok, png = cv2.imencode('.png', out)
    return png.tobytes() if ok else None


def extra_figures(bag_path: str | Path) -> list[tuple[str, bytes]]:
    """(caption, PNG) of every extra product the bag holds."""
    figures: list[tuple[str, bytes]] = []
    pano = panorama_png(bag_path)
    if pano is not None:
        figures.append(('Panorama map built during the run (panorama/image, last message)', pano))
    import tempfile

    from .annotation_figures import annotation_figure

    with tempfile.TemporaryDirectory() as tmp:
        written = annotation_figure(bag_path, Path(tmp) / 'annotations.png')
        if written is not None:
            figures.append(('Annotations placed in the panorama (matched green, inferred by alignment '
                            'another colour) and AR overlay frames', written.read_bytes()))
        if _has_topic(bag_path, '/slam/pose'):
            from .slam_figures import slam_figure

            written = slam_figure(bag_path, Path(tmp) / 'slam.png')
            if written is not None:
                figures.append(('Keyframe SLAM (slam/pose) against the ground truth after a Sim(3) '
                                'alignment: top view and position error over time', written.read_bytes()))
    return figures


def _has_topic(bag_path: str | Path, topic: str) -> bool:
    from ..io.bags import BagError, BagReader

    try:
        with BagReader(bag_path) as reader:
            return topic in reader.topics
    except BagError:
        return False
