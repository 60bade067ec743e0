"""Tag family names as detectors and bags spell them, mapped to the names focusmap uses (``tag36h11``, ...).

Bags of AprilTag detections (apriltag_msgs) name the family as their detector does: ``tag36h11`` (AprilTag 3,
apriltag_ros), ``36h11``, or ``mit``: TagSLAM's detector wrapper names the MIT/Kaess C++ AprilTag library
``mit``, whose family there is tag36h11. The shared TagSLAM recordings confirm it: their ``mit`` detections
carry ``bits: 6`` (a 6x6 = 36-bit code), at most 1 corrected bit, and ids up to 586, the last of tag36h11's
587 codes. An empty family is the default family of the detector that wrote it, tag36h11 in practice.
"""

from __future__ import annotations

KNOWN_FAMILIES = (
    "tag36h11",
    "tag36h10",
    "tag25h9",
    "tag16h5",
    "tagCircle21h7",
    "tagCircle49h12",
    "tagCustom48h12",
    "tagStandard41h12",
    "tagStandard52h13",
)
_BY_KEY = {name.lower(): name for name in KNOWN_FAMILIES} | {
    name.lower().removeprefix("tag"): name for name in KNOWN_FAMILIES
}
ALIASES = {"mit": "tag36h11", "": "tag36h11", "apriltag": "tag36h11", "t36h11": "tag36h11"}
"""Other names of known families (lower case)."""


def bag_family(name: str) -> str:
    """The family a detection message names: a known family by its focusmap name, else the name as given."""
    key = name.strip().lower()
    if key in ALIASES:
        return ALIASES[key]
    return _BY_KEY.get(key, name.strip())
