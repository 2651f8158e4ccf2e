"""camera_replay: plays the camera topics of a bag (image or compressed image, camera_info) and /clock.

The same player as bag_replay with the camera topics selected by default; every option of
bag_replay (rate, start offset, loop, remap) applies.
"""
from __future__ import annotations

from typing import Any

from ..ros.node_base import run_node
from .bag_replay import BagReplayNode


class CameraReplayNode(BagReplayNode):
    DEFAULT_TOPICS = ['/camera/image_raw', '/camera/image_raw/compressed', '/camera/camera_info']
    OUTPUTS = {
        'camera/image_raw': 'sensor_msgs/msg/Image',
        'camera/image_raw/compressed': 'sensor_msgs/msg/CompressedImage',
        'camera/camera_info': 'sensor_msgs/msg/CameraInfo',
    }

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('camera_replay', **kwargs)


def main(args: list[str] | None = None) -> int:
    return run_node(CameraReplayNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
