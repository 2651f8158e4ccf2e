"""World frame choices (REP-103 / REP-145): ENU is native, NED and NWU are offered as output."""
from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

#: R_world_enu for each supported world frame: rotates ENU vectors into the chosen world frame.
WORLD_FROM_ENU: dict[str, NDArray[np.float64]] = {
    'enu': np.eye(3),
    # NED: x north, y east, z down.
    'ned': np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]),
    # NWU: x north, y west, z up.
    'nwu': np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
}


def check_world_frame(name: str) -> str | None:
    """None if ``name`` is a supported world frame, else the reason (for parameter checks)."""
    return None if name in WORLD_FROM_ENU else f'world_frame must be one of {sorted(WORLD_FROM_ENU)}'
