"""Camera paths (walkthroughs): interpolated between photo cameras, saved and loaded as JSON."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from dmrt.io.bundle import camera_from_json, camera_to_json, read_json
from dmrt.camera import Camera
from dmrt.errors import InputError
from dmrt.io.atomic import write_text


def camera_path(keys: list[Camera], frames: int, width: int, height: int, fov_x: float = 70.0) -> list[Camera]:
    """``frames`` cameras gliding through the key cameras' centres and orientations.

    Centres are interpolated linearly and rotations by slerp, segment by segment; every frame
    gets the same square-pixel intrinsics (``fov_x`` degrees across ``width``), so frame times are
    comparable along the path.
    """
    if len(keys) < 2:
        raise ValueError("a camera path needs at least two key cameras")
    s = np.linspace(0, len(keys) - 1, frames)
    rot = Slerp(np.arange(len(keys)), Rotation.from_matrix(np.stack([k.R for k in keys])))(s).as_matrix()
    centers = np.stack([k.center for k in keys])
    i = np.minimum(s.astype(int), len(keys) - 2)
    c = centers[i] + (s - i)[:, None] * (centers[i + 1] - centers[i])
    f = 0.5 * width / np.tan(np.radians(fov_x) / 2)
    return [Camera(f"frame_{n:05d}", width, height, f, f, width / 2, height / 2, R, -R @ cc)
            for n, (R, cc) in enumerate(zip(rot, c))]


def save_path(path, cameras: list[Camera]) -> None:
    """Write ``cameras`` as a camera path JSON (``{"cameras": [...]}``), atomically."""
    write_text(path, json.dumps({"cameras": [camera_to_json(c) for c in cameras]}, indent=1))


def load_path(path) -> list[Camera]:
    """The cameras of a camera path JSON written by :func:`save_path`.

    Raises
    ------
    InputError
        Naming the file (and the camera and field): missing, a folder, not JSON, no ``cameras``
        list, an empty path, a malformed camera.
    """
    path = Path(path)
    doc = read_json(path, "camera path", "JSON written by dmrt path")
    if not isinstance(doc, dict) or "cameras" not in doc:
        raise InputError(path, "not a camera path: expected a JSON object {\"cameras\": [...]} (dmrt path writes one)")
    if not isinstance(doc["cameras"], list):
        raise InputError(path, f"field 'cameras' must be a list, not {type(doc['cameras']).__name__}")
    if not doc["cameras"]:
        raise InputError(path, "empty camera path: field 'cameras' lists no cameras")
    return [camera_from_json(c, path, f"cameras[{i}]") for i, c in enumerate(doc["cameras"])]
