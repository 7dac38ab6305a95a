"""Frame outputs: the dict of arrays every renderer and the reference produce, and its files.

A frame is a ``dict`` with

- ``depth``  : (h, w) float32, camera-space z in metres, 0 = background;
- ``label``  : (h, w) int32, image index, -1 = none;
- ``color``  : (h, w, 3) uint8 RGB;
- ``normal`` : (h, w, 3) float32 unit world-space normal, 0 = background;

plus optional renderer statistics (e.g. ``iterations`` (h, w) int32, ``layer_used`` (h, w) int32)
and ``timings`` (dict stage -> GPU ms). As OpenEXR it has float32 channels ``Z``, ``label``,
``R``, ``G``, ``B`` (display-referred 0..1) and ``N.X``, ``N.Y``, ``N.Z``; as PNG, the colour.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dmrt.errors import InputError
from dmrt.io.atomic import atomic_file

FRAME_KEYS = ("depth", "label", "color", "normal")


def empty_frame(height: int, width: int) -> dict:
    """A frame of background everywhere."""
    return {
        "depth": np.zeros((height, width), np.float32),
        "label": np.full((height, width), -1, np.int32),
        "color": np.zeros((height, width, 3), np.uint8),
        "normal": np.zeros((height, width, 3), np.float32),
    }


def write_frame(path, frame: dict) -> None:
    """Write ``frame`` as ``.exr`` (all channels) or ``.png`` (colour only), atomically."""
    import OpenEXR
    from PIL import Image

    path = Path(path)
    if path.suffix.lower() not in (".exr", ".png"):
        raise InputError(path, "frame files are .exr or .png")
    with atomic_file(path) as tmp:
        if path.suffix.lower() == ".exr":
            rgb = frame["color"].astype(np.float32) / 255.0
            n = frame["normal"].astype(np.float32)
            channels = {
                "Z": frame["depth"].astype(np.float32),
                "label": frame["label"].astype(np.float32),
                "R": np.ascontiguousarray(rgb[..., 0]), "G": np.ascontiguousarray(rgb[..., 1]),
                "B": np.ascontiguousarray(rgb[..., 2]),
                "N.X": np.ascontiguousarray(n[..., 0]), "N.Y": np.ascontiguousarray(n[..., 1]),
                "N.Z": np.ascontiguousarray(n[..., 2]),
            }
            header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
            OpenEXR.File(header, channels).write(str(tmp))
        else:
            Image.fromarray(frame["color"]).save(tmp)


def read_frame(path) -> dict:
    """Read a frame written by :func:`write_frame` (``.exr``: every channel; ``.png``: colour)."""
    from PIL import Image

    from dmrt.io.exr import read_exr_channels

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "frame file not found")
    if path.suffix.lower() == ".png":
        try:
            with Image.open(path) as im:
                return {"color": np.asarray(im.convert("RGB"))}
        except (OSError, ValueError) as exc:
            raise InputError(path, f"cannot read image ({exc})") from None
    channels = read_exr_channels(path)
    # OpenEXR groups R, G, B (and N.X, N.Y, N.Z) into one multi-channel entry when it reads.
    if "RGB" in channels:
        rgb = channels.pop("RGB")
        channels.update(R=rgb[..., 0], G=rgb[..., 1], B=rgb[..., 2])
    if "N" in channels:
        n = channels.pop("N")
        channels.update({"N.X": n[..., 0], "N.Y": n[..., 1], "N.Z": n[..., 2]})
    missing = [c for c in ("Z", "label", "R", "G", "B", "N.X", "N.Y", "N.Z") if c not in channels]
    if missing:
        raise InputError(path, f"frame lacks channel(s) {', '.join(missing)}")
    rgb = np.stack([channels[c] for c in "RGB"], axis=-1)
    return {
        "depth": channels["Z"].astype(np.float32),
        "label": np.rint(channels["label"]).astype(np.int32),
        "color": np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8),
        "normal": np.stack([channels[c] for c in ("N.X", "N.Y", "N.Z")], axis=-1).astype(np.float32),
    }


# ----------------------------------------------------------------------------------------------
# Pictures of a frame's buffers (the paper's Fig. 3 a-d and the statistics)
# ----------------------------------------------------------------------------------------------
def label_colors(labels: np.ndarray) -> np.ndarray:
    """The display colour of each label (mirrored by ``label_color`` in
    ``shaders/viewer_display.glsl``).

    Parameters
    ----------
    labels : (...) int
        Photo indices, -1 = none.

    Returns
    -------
    (..., 3) uint8
        Black for -1; otherwise a hue along the golden-ratio sequence (neighbouring photo indices
        get far-apart hues, any few labels distinct ones), value from a second low-discrepancy
        sequence, never below 0.7.
    """
    lab = np.asarray(labels)
    x = lab.astype(np.float64)
    h = np.mod(0.5 + x * 0.6180339887, 1.0)
    v = 0.7 + 0.3 * np.mod(x * 0.7548776662, 1.0)
    rgb = np.clip(np.abs(np.mod(h[..., None] * 6.0 + np.array([0.0, 4.0, 2.0]), 6.0) - 3.0) - 1.0, 0.0, 1.0)
    out = v[..., None] * (0.25 + 0.75 * rgb)
    out[lab < 0] = 0.0
    return np.clip(np.rint(out * 255.0), 0, 255).astype(np.uint8)


def heat_colors(values: np.ndarray, vmax: float | None = None) -> np.ndarray:
    """(..., 3) uint8 black -> red -> yellow -> white ramp of ``values`` in ``[0, vmax]``
    (default: the 99th percentile of the positive values); ``heat`` of viewer_display.glsl."""
    v = np.asarray(values, np.float64)
    if vmax is None:
        pos = v[v > 0]
        vmax = float(np.percentile(pos, 99)) if len(pos) else 1.0
    t = np.clip(v / max(vmax, 1e-12), 0.0, 1.0)[..., None] * 3.0
    rgb = np.clip(np.concatenate([t, t - 1.0, t - 2.0], axis=-1), 0.0, 1.0)
    return (rgb * 255).astype(np.uint8)


def stage_images(frame: dict, splat_labels: np.ndarray | None = None) -> dict:
    """The buffers of a rendered frame as pictures, (h, w, 3) uint8 each.

    Parameters
    ----------
    frame : dict, a renderer's frame (``depth``, ``label``, ``color``; optionally ``iterations``
        and ``layer_used``)
    splat_labels : (h, w) int32, optional, the first label layer (``Renderer.layers()["label"][0]``)

    Returns
    -------
    dict: ``a_splat_labels`` (with ``splat_labels``), ``b_raytraced_depth`` (near bright, far dark,
    background black), ``c_pixel_labels``, ``d_textured`` (the paper's Fig. 3 a-d), and with the
    statistics ``iterations`` (heat map of the iterative-search steps) and ``holes`` (red where
    a splat covers the pixel but no layer gave a surface).
    """
    depth = frame["depth"]
    hit = depth > 0
    out = {}
    if splat_labels is not None:
        out["a_splat_labels"] = label_colors(splat_labels)
    shade = np.zeros(depth.shape)
    if hit.any():
        lo, hi = np.percentile(depth[hit], [1, 99])
        shade[hit] = 1.0 - 0.8 * np.clip((depth[hit] - lo) / max(hi - lo, 1e-9), 0, 1)
    out["b_raytraced_depth"] = (np.repeat(shade[..., None], 3, axis=-1) * 255).astype(np.uint8)
    out["c_pixel_labels"] = label_colors(frame["label"])
    out["d_textured"] = frame["color"]
    if "iterations" in frame:
        out["iterations"] = heat_colors(frame["iterations"])
    if "layer_used" in frame:
        holes = (frame["layer_used"] < 0) & (~hit)
        if splat_labels is not None:
            holes &= splat_labels >= 0  # background is not a hole
        img = frame["color"] // 3
        img[holes] = (255, 0, 0)
        out["holes"] = img
    return out


def write_stage_images(folder, frame: dict, splat_labels: np.ndarray | None = None) -> list[Path]:
    """Write :func:`stage_images` as ``folder/<name>.png``; returns the paths."""
    from PIL import Image

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, img in stage_images(frame, splat_labels).items():
        path = folder / f"{name}.png"
        with atomic_file(path) as tmp:
            Image.fromarray(np.ascontiguousarray(img)).save(tmp)
        paths.append(path)
    return paths
