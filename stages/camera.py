"""Camera models: calibration files to ingest's :class:`~stages.ingest.artifacts.CameraModel` (``camera.json``), and
that model to a pycolmap camera.

The model holds ``width``, ``height``, ``K`` (9 numbers, row-major), ``distortion_model`` (``plumb_bob``,
``rational_polynomial``, ``equidistant`` or ``none``), ``D`` (coefficients as ROS gives them), ``frame_id``,
``topic``, ``tag_topic`` and ``source``. Pixel coordinates follow ROS and OpenCV: the centre of the top-left pixel
is (0, 0).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml
from pydantic import ValidationError

from pipeline.errors import InputError
from stages.ingest.artifacts import CameraModel

if TYPE_CHECKING:
    import pycolmap

_KALIBR_DISTORTION = {
    "radtan": "plumb_bob",
    "plumb_bob": "plumb_bob",
    "equidistant": "equidistant",
    "fisheye": "equidistant",
    "none": "none",
    "": "none",
}


def load_camera_file(path: Path, topic: str | None = None) -> CameraModel:
    """Read a camera calibration file into the camera model of ``camera.json``.

    Two formats are understood: Kalibr / TagSLAM ``cameras.yaml`` (``cam0: {intrinsics, distortion_model,
    distortion_coeffs, resolution, rostopic, tagtopic}``) and the ROS ``camera_info`` YAML written by
    ``camera_calibration`` (``image_width``, ``camera_matrix: {data}``, ``distortion_coefficients``, ...) or a
    dumped ``sensor_msgs/CameraInfo`` (``width``, ``K``/``k``, ``D``/``d``).

    Args:
        path: the YAML file.
        topic: for a multi-camera ``cameras.yaml``, the camera whose image topic (``rostopic``), tag topic
            (``tagtopic``) or name (``cam1``) this is; None takes the first camera.

    Raises:
        InputError: unreadable file, unknown format, an unsupported lens model, or no camera for ``topic``.
    """
    try:
        doc = yaml.safe_load(Path(path).read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as err:
        reason = "not UTF-8 text" if isinstance(err, UnicodeDecodeError) else str(err)
        msg = f"camera file {str(path)!r} cannot be read as YAML ({reason}); pass a valid --camera FILE"
        raise InputError(msg) from err
    if not isinstance(doc, dict):
        raise InputError(f"camera file {str(path)!r} is not a YAML mapping; expected cameras.yaml or camera_info")
    if "image_width" in doc or "camera_matrix" in doc or "K" in doc or "k" in doc:
        return _from_camera_info(doc, path)
    cams = {k: v for k, v in doc.items() if isinstance(v, dict) and "intrinsics" in v}
    if not cams:
        raise InputError(
            f"camera file {str(path)!r} is neither a Kalibr/TagSLAM cameras.yaml (cam0: intrinsics ...) "
            "nor a ROS camera_info YAML (image_width, camera_matrix ...)"
        )
    if topic is None:
        name, cam = next(iter(cams.items()))
    else:
        found = [(n, c) for n, c in cams.items() if topic in (n, c.get("rostopic"), c.get("tagtopic"))]
        if not found:
            listed = ", ".join(f"{n} ({c.get('rostopic')}, {c.get('tagtopic')})" for n, c in cams.items())
            raise InputError(f"no camera for topic {topic!r} in {str(path)!r}; cameras: {listed}")
        name, cam = found[0]
    return _from_kalibr(name, cam, path)


def load_camera_files(path: Path) -> dict[str, CameraModel]:
    """Every camera of a Kalibr/TagSLAM ``cameras.yaml`` (a camera_info file gives one), by camera name."""
    doc = yaml.safe_load(Path(path).read_text())
    if isinstance(doc, dict) and any(isinstance(v, dict) and "intrinsics" in v for v in doc.values()):
        return {n: _from_kalibr(n, c, path) for n, c in doc.items() if isinstance(c, dict) and "intrinsics" in c}
    return {"camera": load_calibration(path)}


def rig_bodies(path: Path) -> dict[str, str]:
    """Camera name to the ``rig_body`` its TagSLAM ``cameras.yaml`` entry names (the body that carries it); empty
    for a file that names none (Kalibr, camera_info)."""
    doc = yaml.safe_load(Path(path).read_text())
    if not isinstance(doc, dict):
        return {}
    return {
        str(n): str(c["rig_body"])
        for n, c in doc.items()
        if isinstance(c, dict) and "intrinsics" in c and c.get("rig_body") not in (None, "")
    }


def _model(path: Path, what: str, **fields: Any) -> CameraModel:
    """The camera model, or an InputError that names the file when the numbers do not make one."""
    try:
        return CameraModel(**fields)
    except ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise InputError(f"{str(path)!r}{what}: {where}: {first['msg']}; pass a valid calibration") from None


def _from_kalibr(name: str, cam: dict[str, Any], path: Path) -> CameraModel:
    model = str(cam.get("camera_model", "pinhole"))
    if model != "pinhole":
        raise InputError(f"{str(path)!r} {name}: camera_model {model!r} unsupported; only 'pinhole' is")
    dist = str(cam.get("distortion_model", "none")).lower()
    if dist not in _KALIBR_DISTORTION:
        raise InputError(f"{str(path)!r} {name}: distortion_model {dist!r} unsupported; use radtan or equidistant")
    try:
        fx, fy, cx, cy = (float(v) for v in cam["intrinsics"])
        width, height = (int(v) for v in cam["resolution"])
    except (KeyError, TypeError, ValueError) as err:
        raise InputError(f"{str(path)!r} {name}: needs intrinsics [fx, fy, cx, cy] and resolution [w, h]") from err
    coeffs = [float(v) for v in cam.get("distortion_coeffs") or []]
    return _model(
        path,
        f" {name}",
        width=width,
        height=height,
        K=[fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0],
        distortion_model=_KALIBR_DISTORTION[dist] if coeffs or dist == "none" else "none",
        D=coeffs,
        frame_id=str(cam.get("frame_id", name)),
        topic=cam.get("rostopic"),
        tag_topic=cam.get("tagtopic"),
        source=str(path),
    )


def _matrix_data(value: Any) -> list[float]:
    if isinstance(value, dict):
        value = value.get("data", [])
    return [float(v) for v in (value or [])]


def _from_camera_info(doc: dict[str, Any], path: Path) -> CameraModel:
    K = _matrix_data(doc.get("camera_matrix", doc.get("K", doc.get("k"))))
    D = _matrix_data(doc.get("distortion_coefficients", doc.get("D", doc.get("d"))))
    width = int(doc.get("image_width", doc.get("width", 0)))
    height = int(doc.get("image_height", doc.get("height", 0)))
    if len(K) != 9 or width <= 0 or height <= 0:
        raise InputError(f"{str(path)!r}: camera_info needs a 3x3 camera_matrix, image_width and image_height")
    model = str(doc.get("distortion_model", "plumb_bob" if D else "none")).lower()
    model = {"radtan": "plumb_bob", "fisheye": "equidistant"}.get(model, model)
    if model not in ("plumb_bob", "rational_polynomial", "equidistant", "none"):
        raise InputError(f"{str(path)!r}: distortion_model {model!r} unsupported; use plumb_bob or equidistant")
    return _model(
        path,
        "",
        width=width,
        height=height,
        K=K,
        distortion_model=model if any(D) or model == "none" else "none",
        D=D,
        frame_id=str(doc.get("camera_name", doc.get("frame_id", "camera"))),
        topic=doc.get("topic"),
        source=str(path),
    )


def colmap_camera(camera: CameraModel) -> pycolmap.Camera:
    """The pycolmap camera of a camera model (PINHOLE, OPENCV, FULL_OPENCV or OPENCV_FISHEYE).

    The principal point is kept as given, so pixel coordinates stay in the ROS/OpenCV convention.

    Raises:
        InputError: a lens model or coefficient count that pycolmap cannot represent.
    """
    import pycolmap

    K = camera.K
    fx, cx, fy, cy = K[0], K[2], K[4], K[5]
    model = camera.distortion_model or "none"
    D = camera.D
    if model == "none" or not any(D):
        name, params = "PINHOLE", [fx, fy, cx, cy]
    elif model == "equidistant":
        if len(D) != 4:
            raise InputError(f"equidistant distortion needs 4 coefficients, camera has {len(D)}")
        name, params = "OPENCV_FISHEYE", [fx, fy, cx, cy, *D]
    elif model in ("plumb_bob", "rational_polynomial"):
        if len(D) not in (4, 5, 8):
            raise InputError(f"{model} distortion needs 4, 5 or 8 coefficients, camera has {len(D)}")
        if len(D) == 4 or (len(D) == 5 and D[4] == 0.0):
            name, params = "OPENCV", [fx, fy, cx, cy, *D[:4]]
        else:
            # FULL_OPENCV: k1 k2 p1 p2 k3 k4 k5 k6, the order of ROS's rational_polynomial.
            name, params = "FULL_OPENCV", [fx, fy, cx, cy, *(D + [0.0] * 8)[:8]]
    else:
        raise InputError(f"distortion model {model!r} unsupported; use plumb_bob, rational_polynomial or equidistant")
    return pycolmap.Camera(model=name, width=camera.width, height=camera.height, params=params)


load_calibration = load_camera_file
"""Alias of :func:`load_camera_file`."""
