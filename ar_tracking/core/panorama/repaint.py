"""The frames mapped before a rolling shutter's readout was known, painted again once it is.

A camera whose readout the bag does not give is mapped as a global shutter until the readout
estimate (:mod:`.readout`) is settled, one to two seconds into a session. Those first frames
go into the map sheared: each row is where the camera pointed when that row was read, up to
``rate x readout`` off (0.5-1 deg at 20-30 deg/s and 30 ms), and every later frame is mapped
without the shear. A map whose first part is sheared and the rest is not disagrees with itself:
a frame that sees both parts finds about half of its keypoints at one rotation and half at
another, and the tracker loses it for as long as the camera looks there (a fresh hard-profile
seed with a 29 ms readout lost 828 of its 1200 frames that way; told the readout, none). The
annotation patches cut from that part carry the shear too.

So the frames that painted the map while the readout in use was 0 are kept (:class:`EarlyFrames`,
up to a memory budget), and when the estimate is first applied the map is painted again from
them, in the same order, with their rows turned by the readout (:func:`repaint`). Their
orientations are moved from where the global-shutter fit put them - the orientation at the
mean read time of the rows its inliers were on - to their stamps (:func:`stamp_orientation`),
so the repainted map keeps the panorama frame of the first (the tracked orientations published
so far stay valid to a fraction of that shear). Done once per panorama; the map's
``generation`` counts it, so that a consumer of the finished tiles knows to read them again.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from .map import MapConfig, PanoramaMap

Array = NDArray[np.float64]


@dataclass(frozen=True)
class EarlyFrame:
    """One frame as it was mapped with a global-shutter assumption (:meth:`PanoramaMap.map_frame`
    arguments), and where its fit's rows sat."""

    index: int
    image: NDArray[np.uint8]
    #: The grey version of an RGB ``image`` (None for a grey one).
    gray: NDArray[np.uint8] | None
    K: Array
    #: The fit's inliers' mean row position, (row + 0.5) / height: 0.5 for the first frame
    #: (all its rows painted the map) or without a fit.
    row_centre: float
    offset: float
    gain: float


class EarlyFrames:
    """The frames that painted the map so far, kept while they fit in ``max_bytes`` (past that
    they are let go: :attr:`frames` is None and nothing is repainted)."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = int(max_bytes)
        self.frames: list[EarlyFrame] | None = []
        self.bytes = 0

    def add(self, frame: EarlyFrame) -> None:
        """Keep a copy of ``frame``'s images (the caller may reuse its buffers)."""
        if self.frames is None:
            return
        size = frame.image.nbytes + (0 if frame.gray is None else frame.gray.nbytes)
        if self.bytes + size > self.max_bytes:
            self.frames, self.bytes = None, 0
            return
        self.frames.append(EarlyFrame(frame.index, frame.image.copy(),
                                      None if frame.gray is None else frame.gray.copy(), frame.K,
                                      frame.row_centre, frame.offset, frame.gain))
        self.bytes += size


def stamp_orientation(R_read: Array, omega: Array, after_s: float) -> Array:
    """R_pano_cam at a frame's stamp from its orientation ``after_s`` later (the mean read time
    of the rows a fit's inliers were on: a fit as a global shutter finds that one), the camera
    turning at ``omega`` (rad/s, camera axes) in between."""
    R, _ = cv2.Rodrigues((-np.asarray(omega, float) * after_s).reshape(3, 1))
    return np.asarray(R_read @ R, dtype=np.float64)


def repaint(frames: list[EarlyFrame], painted: Mapping[int, tuple[Array, Array | None, float]], readout_s: float,
            config: MapConfig, generation: int) -> tuple[PanoramaMap, dict[int, Array]]:
    """A new map painted from ``frames`` in order, each at its stamp orientation with its rows
    turned by its rate over ``readout_s``. ``painted``: the mapper's record of each frame index
    (R_pano_cam as tracked with readout 0, the rate in rad/s camera axes or None when not known -
    taken as 0 -, the readout it was painted with). Returns the map (``generation`` set, every
    finished tile's keypoints computed) and each frame's new R_pano_cam."""
    pano = PanoramaMap(config)
    pano.generation = generation
    moved: dict[int, Array] = {}
    for f in frames:
        R_fit, rate, _ = painted[f.index]
        omega = np.zeros(3) if rate is None else np.asarray(rate, float)
        R = stamp_orientation(R_fit, omega, readout_s * f.row_centre)
        moved[f.index] = R
        pano.row_motion = (omega, float(readout_s))
        try:
            pano.map_frame(f.image, f.K, R, f.index, f.offset, f.gray, f.gain)
        finally:
            pano.row_motion = None
    pano.process_queue(len(pano.queue))
    return pano, moved
