"""The scenario protocol that :mod:`.bagmaker` dispatches on, and the simulator's error.

A scenario module (or adapter) offers one object with a ``name``, a ``write_bag`` that writes all
its messages into an open bag in log-time order, and a ``write_sidecars`` that writes the
``<stem>.params.yaml`` beside the bag. :func:`.bagmaker.make_bag` checks the arguments, opens
the bag and calls these; the scenarios never import :mod:`.bagmaker` (they take shared message
builders and constants from :mod:`.messages`), so the import graph has no cycle.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Protocol

from ..errors import ArTrackingError

Progress = Callable[[float], None]


class SimError(ArTrackingError):
    """Bad arguments to the simulator; the message is one line meant for the user."""


@dataclass(frozen=True)
class BagRequest:
    """The checked arguments of one :func:`.bagmaker.make_bag` call.

    ``session`` and ``lighting`` are rotation_sweep's; ``profile`` rotation_sweep's and
    robot_arcs'; a scenario ignores what it has no use for."""

    seed: int
    duration_s: float
    session: str = 'authoring'
    image_format: str = 'raw'
    lighting: str | None = None
    profile: str = 'hard'
    #: rotation_sweep: the camera-IMU time offset instead of the profile's, s (None: the profile's)
    imu_time_offset_s: float | None = None
    #: rotation_sweep: the camera's rolling-shutter readout time, s, instead of the profile's (0: a
    #: global shutter; None: the profile's)
    readout_s: float | None = None
    #: rotation_sweep: how long after its stamp a camera frame is logged, s (None: the profile's)
    camera_latency_s: float | None = None
    #: rotation_sweep: a folder of photos of a full turn to cut the frames from instead of the
    #: rendered street (:mod:`.photo_world`); None: the street
    world_photos: str | None = None
    #: rotation_sweep: the frames show the parallax of the camera's offset from the spot (the
    #: phone in front of the body's turning axis, the hand's sway), from the street's depth;
    #: None: the profile's (on in 'hard', off in 'kind'; a photo world has no depth)
    parallax: bool | None = None


class ScenarioBag(Protocol):
    """What :func:`.bagmaker.make_bag` needs of a scenario."""

    name: str

    def write_bag(self, bag: Any, req: BagRequest, progress: Progress | None) -> None:
        """Every message of the scenario into the open ``bag`` (an io.bags.BagWriter)."""

    def write_sidecars(self, sidecar: Path, bag_path: Path, req: BagRequest) -> None:
        """The ``<stem>.params.yaml`` (device calibration or node parameters) beside the bag."""

    def summary(self, req: BagRequest) -> str:
        """A few words for the 'wrote ...' log line (scenario, seed, ...)."""
