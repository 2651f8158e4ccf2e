"""GPS fixes of a simulated scenario: the true position with slowly wandering metre-level
errors (a Gauss-Markov process per axis), at 1 Hz, as a phone's fused location gives them."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from .rng import rng_stream

Array = NDArray[np.float64]

GPS_RATE_HZ = 1
EARTH_RADIUS_M = 6_378_137.0


class _Path(Protocol):
    def position(self, t_s: Array) -> Array: ...


class Located(Protocol):
    """What a scenario gives the GPS: its random streams' key, its path and its origin."""

    seed: int
    session: str
    trajectory: _Path
    origin_lat_lon_alt: tuple[float, float, float]


@dataclass(frozen=True)
class GpsSamples:
    """GPS fixes (degrees, metres) and the noise they were made with."""

    t_s: Array
    latitude_deg: Array
    longitude_deg: Array
    altitude_m: Array
    sigma_horizontal_m: float
    sigma_vertical_m: float


def simulate_gps(scn: Located, t_s: Array, sigma_h_m: float = 3.0, sigma_v_m: float = 5.0,
                 correlation_s: float = 20.0) -> GpsSamples:
    """Fixes of the true position with slowly wandering (Gauss-Markov) metre-level errors."""
    rng = rng_stream(scn.seed, 'gps', scn.session)
    n = len(t_s)
    phi = math.exp(-1.0 / (GPS_RATE_HZ * correlation_s))
    err = np.zeros((n, 3))
    sig = np.array([sigma_h_m, sigma_h_m, sigma_v_m])
    err[0] = rng.normal(0, sig)
    for k in range(1, n):
        err[k] = phi * err[k - 1] + math.sqrt(1 - phi * phi) * rng.normal(0, sig)
    pos = scn.trajectory.position(t_s) + err
    lat0, lon0, alt0 = scn.origin_lat_lon_alt
    lat = lat0 + np.degrees(pos[:, 1] / EARTH_RADIUS_M)
    lon = lon0 + np.degrees(pos[:, 0] / (EARTH_RADIUS_M * math.cos(math.radians(lat0))))
    return GpsSamples(np.asarray(t_s, float), lat, lon, alt0 + pos[:, 2], sigma_h_m, sigma_v_m)
