"""Shared fixtures: where the third-party test data lives, and small bags written on the fly."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` (real recordings from other projects); tests skip where a clone has none."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"third-party test data not present at {SHARED_DATA} (only in the team's workspace)")
    return SHARED_DATA


def write_minimal_bag(path: Path, *, focal: float = 400.0, images: int = 3, with_info: bool = True) -> Path:
    """A ROS 1 bag with a few JPEG frames and CameraInfo (focal length ``focal``), written with rosbags."""
    import cv2
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    Compressed = ts.types["sensor_msgs/msg/CompressedImage"]
    Info = ts.types["sensor_msgs/msg/CameraInfo"]
    RoI = ts.types["sensor_msgs/msg/RegionOfInterest"]
    ok, jpg = cv2.imencode(".jpg", np.full((48, 64), 128, np.uint8))
    assert ok
    t0 = 1_700_000_000 * 10**9
    with Writer(path) as w:
        c_img = w.add_connection("/cam/image/compressed", Compressed.__msgtype__, typestore=ts)
        c_info = w.add_connection("/cam/camera_info", Info.__msgtype__, typestore=ts) if with_info else None
        for i in range(images):
            t = t0 + i * 100_000_000
            hdr = Header(seq=i, stamp=Time(sec=t // 10**9, nanosec=t % 10**9), frame_id="cam")
            w.write(
                c_img,
                t,
                ts.serialize_ros1(Compressed(header=hdr, format="jpeg", data=jpg.ravel()), Compressed.__msgtype__),
            )
            if c_info is not None:
                K = np.array([focal, 0, 32, 0, focal, 24, 0, 0, 1], dtype=np.float64)
                info = Info(
                    header=hdr,
                    height=48,
                    width=64,
                    distortion_model="plumb_bob",
                    D=np.zeros(5),
                    K=K,
                    R=np.eye(3).ravel(),
                    P=np.zeros(12),
                    binning_x=0,
                    binning_y=0,
                    roi=RoI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
                )
                w.write(c_info, t, ts.serialize_ros1(info, Info.__msgtype__))
    return path
