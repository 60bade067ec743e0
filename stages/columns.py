"""Column names that several stages' tables share, each declared once with its type and meaning.

A :class:`pipeline.contracts.Column` is a ``str``: ``table[STAMP_NS]`` and ``row[STAMP_NS]`` read the
``stamp_ns`` column. Columns that belong to one table only are declared in that stage's ``artifacts``
module.
"""

from __future__ import annotations

import pyarrow as pa

from pipeline.contracts import Column

STAMP_NS = Column("stamp_ns", pa.int64(), "time on the bag clock, ns (the message header stamp, else the log time)")
FRAME = Column("frame", pa.int64(), "index of the image message on its topic from 0 in bag order")
TAG_ID = Column("tag_id", pa.int64(), "AprilTag id")
FAMILY = Column("family", pa.string(), "tag family, e.g. `tag36h11`")
CORNERS = Column(
    "corners", pa.list_(pa.float64(), 8), "x0 y0 … x3 y3, pixels of the distorted image, OpenCV corner order"
)
TOPIC = Column("topic", pa.string(), "the recording's topic the row came from")
FRAME_ID = Column("frame_id", pa.string(), "ROS frame id")
KEY = Column("key", pa.uint64(), "GTSAM key of the variable")
X = Column("x", pa.float64(), "position x, m")
Y = Column("y", pa.float64(), "position y, m")
Z = Column("z", pa.float64(), "position z, m")
QX = Column("qx", pa.float64(), "orientation quaternion x")
QY = Column("qy", pa.float64(), "orientation quaternion y")
QZ = Column("qz", pa.float64(), "orientation quaternion z")
QW = Column("qw", pa.float64(), "orientation quaternion w")
YAW = Column("yaw", pa.float64(), "heading about z, rad")
POSITION = (X, Y, Z)
QUATERNION = (QX, QY, QZ, QW)
