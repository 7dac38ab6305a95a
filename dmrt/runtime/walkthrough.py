"""Camera paths (walkthroughs): interpolated between photo cameras, saved and loaded as JSON."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from dmrt.io.bundle import camera_from_json, camera_to_json
from dmrt.camera import Camera
from dmrt.errors import InputError


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
    Path(path).write_text(json.dumps({"cameras": [camera_to_json(c) for c in cameras]}, indent=1))


def load_path(path) -> list[Camera]:
    path = Path(path)
    try:
        return [camera_from_json(c) for c in json.loads(path.read_text())["cameras"]]
    except FileNotFoundError as exc:
        raise InputError(path, "camera path file not found") from exc
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise InputError(path, f"not a camera path (JSON {{'cameras': [...]}}): {exc}") from exc
