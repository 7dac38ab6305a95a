"""The interactive viewer's core: fly through a scene bundle with DMRT, the coarse splats or DMT.

:class:`Viewer` owns the state - camera, method, layer count, buffer shown, leveling, recording -
and turns input (:meth:`Viewer.key`, :meth:`Viewer.drag`, :meth:`Viewer.scroll`,
:meth:`Viewer.step`) into frames (:meth:`Viewer.render` returns the displayed image). It needs a GL
context, not a window, so tests drive it headless through scripted input. The window
(moderngl-window) lives in :mod:`dmrt.app.viewer_window`, which only forwards events to a Viewer and
draws its frame; ``dmrt view BUNDLE`` opens it.

Keys (names as :meth:`Viewer.key` takes them; the README lists them too)::

    w s a d      fly forward / back / left / right     q e    down / up     shift  4x faster
    left right up down, mouse drag   turn              + -, mouse wheel   field of view
    1..9 0       photo camera 1..10                    page_down page_up  next / previous photo
    m            method (dmrt, splats, dmt)            [ ]    fewer / more layers (1..11)
    b            buffer shown (BUFFERS)                l      leveling on / off
    r            record a camera path (again: save)    f12    screenshot    h  overlay
    o            orbit around the surface point at the image centre (drag / arrows orbit,
                 w s move toward / away from it; o again: fly)
    p            proxy set: the k coarsest octree levels of the bundle's proxies, k = K, K-1, .., 1

Recorded paths are :func:`dmrt.runtime.walkthrough.save_path` files: ``dmrt render BUNDLE --path FILE
--out DIR`` replays them (one PNG per frame and each frame's stage timings).
"""

from __future__ import annotations

import dataclasses
import time
import typing
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Literal

import moderngl
import numpy as np
from scipy.spatial.transform import Rotation

from dmrt.io.bundle import Bundle
from dmrt.camera import Camera
from dmrt.errors import ConfigError
from dmrt.gl.context import get_context
from dmrt.gl.timer import format_ms
from dmrt.gl.shaders import load_program, set_uniforms
from dmrt.options import option, validate
from dmrt.runtime.protocol import GpuColorRenderer, LayeredRenderer
from dmrt.runtime.renderer import RenderConfig, Renderer
from dmrt.runtime.walkthrough import save_path

# The buffers the viewer shows, in the order ``b`` cycles through them; the value is the display
# shader's mode (shaders/viewer_display.glsl gets them as MODE_* defines). The paper's Fig. 3:
# (a) splat_label, (b) depth, (c) label, (d) color.
BUFFERS = {
    "color": 0,        # textured frame
    "depth": 1,        # raytraced depth, normalised to the frame's nearest..farthest surface
    "label": 2,        # per-pixel labels (after the labeling pass), one hashed colour per photo
    "splat_label": 3,  # label of the first splat layer (the visibility stage's output)
    "iterations": 4,   # iterative-search steps per pixel, heat map scaled to the frame's maximum
    "holes": 5,        # pixels no layer's raytracing resolved (layer_used < 0) in red over grey
}
MAX_LAYERS = 11  # the paper's worst case (Fig. 13)

# Held keys: flying direction as (right, up, forward) and turning as (yaw right, pitch up).
MOVE_KEYS = {"w": (0, 0, 1), "s": (0, 0, -1), "d": (1, 0, 0), "a": (-1, 0, 0), "e": (0, 1, 0), "q": (0, -1, 0)}
TURN_KEYS = {"right": (1, 0), "left": (-1, 0), "up": (0, 1), "down": (0, -1)}
# Short stage names for the overlay (others are shown as they come).
_STAGE_ABBREV = {"visibility": "vis", "raytracing": "ray", "labeling": "lab", "image_management": "img",
                 "texturing": "tex", "leveling": "lev"}


Buffer = Literal["color", "depth", "label", "splat_label", "iterations", "holes"]
assert set(typing.get_args(Buffer)) == set(BUFFERS)


@dataclass
class ViewerConfig:
    """What ``dmrt view`` starts with; every field is a ``--option`` of the command."""

    width: int = option(960, "frame width in pixels; the window opens at this size and the frame follows the "
                             "window when it is resized", minimum=1, level="common")
    height: int = option(640, "frame height in pixels", minimum=1, level="common")
    method: str = option("dmrt", "method shown first: dmrt, splats (coarse splats: the first splat layer "
                                 "textured, no raytracing) or dmt; m switches", level="common")
    layers: int = option(5, "label layers k (paper Fig. 13: 3-5 suffice); [ and ] switch", minimum=1,
                         maximum=MAX_LAYERS, level="common")
    buffer: Buffer = option("color", "buffer shown first; b switches", level="common")
    leveling: bool = option(False, "screen-space leveling (where the renderer implements it); l switches",
                            level="common")
    photo: int = option(0, "photo camera to start at (0-based index into the bundle's cameras)", minimum=0,
                        level="common")
    fov: float | None = option(None, "horizontal field of view, degrees; default the start photo's", minimum=1.0,
                               maximum=179.0, level="common")
    speed: float | None = option(None, "flying speed, metres per second; default a tenth of the proxies' "
                                       "bounding-box diagonal (a room and a city block take as many seconds to "
                                       "cross)", minimum=0.0, level="common")
    drag_degrees: float = option(0.2, "turning: degrees per pixel of mouse drag", minimum=0.0)
    turn_rate: float = option(60.0, "turning: degrees per second while an arrow key is held", minimum=0.0)
    overlay: bool = option(True, "overlay with method, layers, buffer, per-stage GPU ms and fps; h toggles")
    # each renderer holds its own copy of the bundle on the GPU
    max_renderers: int = option(3, "renderers kept alive at once (each switch of method, layers or leveling "
                                   "builds one)", minimum=1)
    path_file: Path = option(Path("viewer_path.json"), "where r writes camera paths (numbered when the file "
                                                        "exists)")
    screenshot_file: Path = option(Path("viewer.png"), "where F12 writes screenshots (numbered when the file "
                                                        "exists)")

    def __post_init__(self):
        validate(self)
        self.path_file, self.screenshot_file = Path(self.path_file), Path(self.screenshot_file)


# ----------------------------------------------------------------------------------------------
# Methods: name -> how to build its renderer
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Method:
    """A renderer the viewer can switch to.

    ``make(bundle, config, ctx)`` returns an object whose ``render(camera, width, height)`` gives
    the frame dict of :mod:`dmrt.io.frames`; ``config`` is a :class:`RenderConfig` carrying the
    viewer's layer count and leveling switch. ``uses_layers`` / ``uses_leveling`` say whether
    those switches change this method's frames (they decide when a new renderer is needed).
    """

    name: str
    make: Callable
    uses_layers: bool
    uses_leveling: bool


def _make_dmrt(bundle, config, ctx):
    return Renderer(bundle, config, ctx)


def _make_splats(bundle, config, ctx):
    return Renderer(bundle, dataclasses.replace(config, raytrace=False), ctx)


def _make_dmt(bundle, config, ctx):
    from baselines.dmt import DMTConfig, DMTRenderer

    # Only the settings that mean the same for both methods carry over.
    shared = ("leveling", "discontinuity_threshold", "async_photos", "max_uploads_per_frame", "cache_mb",
              "cpu_cache_mb")
    names = {f.name for f in dataclasses.fields(DMTConfig)}
    dmt_config = DMTConfig(**{k: getattr(config, k) for k in shared if k in names})
    return DMTRenderer(bundle, dmt_config, ctx=ctx)


def available_methods() -> dict[str, Method]:
    """The methods the viewer switches between: DMRT, its coarse-splats ablation and DMT."""
    return {"dmrt": Method("dmrt", _make_dmrt, True, True),
            "splats": Method("splats", _make_splats, True, True),
            "dmt": Method("dmt", _make_dmt, False, True)}


# ----------------------------------------------------------------------------------------------
# Small helpers
# ----------------------------------------------------------------------------------------------
def check_photo(index: int, bundle: Bundle) -> None:
    """:class:`ConfigError` naming ``--photo`` unless ``index`` is one of ``bundle``'s photos."""
    n = len(bundle.cameras)
    if not 0 <= index < n:
        raise ConfigError("photo", f"{index} is out of range: the bundle {bundle.root} has {n} photos "
                                   f"(0..{n - 1})")


def _rotation(axis, degrees: float) -> np.ndarray:
    """(3, 3) rotation by ``degrees`` about the unit ``axis`` (right-hand rule)."""
    return Rotation.from_rotvec(np.radians(degrees) * np.asarray(axis, np.float64)).as_matrix()


def _free_path(path: Path) -> Path:
    """``path`` itself when it does not exist, else ``stem_1.suffix``, ``stem_2.suffix``, ..."""
    n = 1
    out = path
    while out.exists():
        out = path.with_name(f"{path.stem}_{n}{path.suffix}")
        n += 1
    return out


def scene_up(cameras: list[Camera]) -> np.ndarray:
    """(3,) float64 world up: the photos' mean image-up direction (photos are mostly taken upright;
    camera y points down in the image). Falls back to +z."""
    up = -np.mean([c.R[1] for c in cameras], axis=0)
    n = np.linalg.norm(up)
    return up / n if n > 1e-6 else np.array([0.0, 0.0, 1.0])


# ----------------------------------------------------------------------------------------------
# The viewer
# ----------------------------------------------------------------------------------------------
class Viewer:
    """Interactive viewing state and its frames, independent of any window.

    Parameters
    ----------
    bundle : Bundle
        From :func:`dmrt.io.bundle.read_bundle`.
    config : ViewerConfig, optional
    render_config : RenderConfig, optional
        Everything else the renderers use (photo streaming, search, visibility path); its
        ``layers`` and ``leveling`` are overridden by the viewer's and ``raytrace`` by the method.
        For frames that replay exactly through ``dmrt render --path``, pass
        ``async_photos=False, max_uploads_per_frame=0`` here and to the replay.
    ctx : moderngl.Context, optional
        Where the renderers run and the frame is displayed: the window's context, or by default
        the process-wide one (:func:`dmrt.gl.get_context`).

    Attributes
    ----------
    position : (3,) float64
        Camera centre, world metres.
    R : (3, 3) float64
        World -> camera rotation (COLMAP axes: x right, y down, z forward).
    fov : float
        Horizontal field of view, degrees.
    method, buffer : str
    layers : int
    leveling, overlay, recording : bool
    recorded : list of Camera
        The cameras of the frames rendered since recording started.
    last_path, last_screenshot : Path or None
        The files the last recording / screenshot wrote.
    frame : dict or None
        The last frame (the renderer's frame dict), with ``splat_label`` (h, w) int32 added while
        that buffer is shown.
    """

    def __init__(self, bundle: Bundle, config: ViewerConfig | None = None,
                 render_config: RenderConfig | None = None, ctx: moderngl.Context | None = None):
        self.bundle = bundle
        self.config = config = config or ViewerConfig()
        self.render_config = render_config or RenderConfig()
        self.ctx = ctx or get_context()
        self.methods = available_methods()
        if config.method not in self.methods:
            raise ConfigError("method", f"{config.method!r} is not available here (have: {', '.join(self.methods)})")
        check_photo(config.photo, bundle)
        self.method, self.layers, self.buffer = config.method, config.layers, config.buffer
        self.leveling = config.leveling and self.methods[self.method].uses_leveling
        self.overlay = config.overlay
        self.width, self.height = config.width, config.height

        # navigation: scene scale and up from the proxies and the photos
        p = np.asarray(bundle.proxy["positions"], np.float64)
        diagonal = float(np.linalg.norm(p.max(0) - p.min(0))) if len(p) else 10.0
        self.speed = config.speed if config.speed is not None else 0.1 * diagonal
        self.up = scene_up(bundle.cameras)
        self.held: set[str] = set()
        self.pivot: np.ndarray | None = None  # orbit centre (world), None = fly
        self.max_proxy_levels = int(bundle.meta.get("counts", {}).get("proxy_levels", 1))
        self.proxy_levels = self.max_proxy_levels
        self._proxy_bundles: dict[int, Bundle] = {self.max_proxy_levels: bundle}
        self.message = ""  # the last switch or file written, shown in the overlay
        self.jump_to_photo(config.photo)
        if config.fov is not None:
            self.fov = float(config.fov)

        self.recording = False
        self.recorded: list[Camera] = []
        self.last_path: Path | None = None
        self.last_screenshot: Path | None = None
        self.frame: dict | None = None
        self.frame_size: tuple[int, int] | None = None  # (w, h) of the last frame
        self._frame_renderer = None  # the renderer that made it (a frame left on the GPU stays there)
        self.fps = 0.0
        self.frame_ms = 0.0
        self._last_update: float | None = None
        self._renderers: OrderedDict[tuple, object] = OrderedDict()

        # display: the program, a vertex array without buffers (full-screen triangle) and the
        # frame's textures, made at the frame's size on first use
        defines = {f"MODE_{name.upper()}": mode for name, mode in BUFFERS.items()}
        self._program = load_program(self.ctx, "viewer_display", defines)
        self._vao = self.ctx.vertex_array(self._program, [])
        self._textures: dict = {}
        self._range = (0.0, 1.0)
        self._overlay_text: list[str] | None = None
        self._overlay_time = 0.0
        self._fbo = None

    # -- the camera -----------------------------------------------------------------------------
    @property
    def camera(self) -> Camera:
        """The current view: square pixels, principal point at the frame's centre, world frame."""
        w, h = self.width, self.height
        f = 0.5 * w / np.tan(np.radians(self.fov) / 2)
        return Camera("viewer", w, h, f, f, w / 2, h / 2, self.R.copy(), -self.R @ self.position)

    def jump_to_photo(self, index: int) -> None:
        """Take photo ``index``'s camera: its centre, orientation and horizontal field of view."""
        cam = self.bundle.cameras[index]
        self.photo = index
        self.position = cam.center.copy()
        self.R = cam.R.copy()
        self.fov = float(np.degrees(2 * np.arctan(cam.width / (2 * cam.fx))))
        self.message = f"photo {index + 1}/{len(self.bundle.cameras)}: {cam.name}"

    def turn(self, yaw: float, pitch: float) -> None:
        """Turn right by ``yaw`` and up by ``pitch`` degrees: yaw about the world up (the horizon
        stays level), pitch about the camera's x axis, stopping 5 degrees short of straight
        up/down (past it the view would flip over)."""
        R = self.R @ _rotation(self.up, -yaw).T  # rows are the camera axes in world: rotate each
        if pitch:
            pitched = R @ _rotation(R[0], pitch).T
            if abs(pitched[2] @ self.up) < np.cos(np.radians(5.0)):
                R = pitched
        u, _, vt = np.linalg.svd(R)  # keep it a rotation as turns accumulate rounding
        self.R = u @ vt

    def orbit(self, yaw: float, pitch: float) -> None:
        """Turn as :meth:`turn` does and move the camera on the sphere around :attr:`pivot`, so
        that the pivot keeps its place in the image and its distance."""
        offset = self.R @ (self.position - self.pivot)  # camera coordinates: kept
        self.turn(yaw, pitch)
        self.position = self.pivot + self.R.T @ offset

    def toggle_orbit(self) -> None:
        """Orbit around the surface point at the image centre (of the last frame; else a point
        ``speed`` metres ahead), or back to flying."""
        if self.pivot is not None:
            self.pivot = None
            self.message = "fly"
            return
        distance = self.speed
        if self.frame is not None:
            w, h = self.frame_size
            if "depth" in self.frame:
                z = float(self.frame["depth"][h // 2, w // 2])
            elif any(r is self._frame_renderer for r in self._renderers.values()):
                z = self._frame_renderer.depth_at(w // 2, h // 2)  # a frame left on the GPU: one pixel
            else:  # its renderer was released since (a switch of method): no depth to read
                z = 0.0
            if z > 0:  # camera z of the centre pixel, on the optical axis
                distance = z
        self.pivot = self.position + distance * self.R[2]
        self.message = f"orbit around a point {distance:.2f} m ahead"

    def zoom(self, steps: float) -> None:
        """Narrow (steps > 0) or widen the field of view by 10 % per step, within 5..150 degrees."""
        self.fov = float(np.clip(self.fov * 0.9 ** steps, 5.0, 150.0))

    # -- input ----------------------------------------------------------------------------------
    def key(self, name: str, pressed: bool = True) -> None:
        """A key went down (``pressed``) or up. Names as in the module doc (``"w"``, ``"f12"``,
        ``"page_down"``, ``"]"``); movement and turning keys act while held (:meth:`step`), the
        others once per press."""
        name = name.lower()
        if name in MOVE_KEYS or name in TURN_KEYS or name == "shift":
            (self.held.add if pressed else self.held.discard)(name)
            return
        if not pressed:
            return
        n = len(self.bundle.cameras)
        if name.isdigit() and len(name) == 1:
            index = (int(name) - 1) % 10  # keys 1..9, 0 -> photos 1..10
            if index < n:
                self.jump_to_photo(index)
        elif name in ("page_down", "page_up"):
            self.jump_to_photo((self.photo + (1 if name == "page_down" else -1)) % n)
        elif name == "m":
            names = list(self.methods)
            self.set_method(names[(names.index(self.method) + 1) % len(names)])
        elif name in ("[", "]"):
            self.set_layers(self.layers + (1 if name == "]" else -1))
        elif name == "b":
            shown = self.buffers()
            self.set_buffer(shown[(shown.index(self.buffer) + 1) % len(shown)] if self.buffer in shown else "color")
        elif name == "l":
            self.set_leveling(not self.leveling)
        elif name == "r":
            self.toggle_recording()
        elif name == "f12":
            self.screenshot()
        elif name == "h":
            self.overlay = not self.overlay
        elif name == "o":
            self.toggle_orbit()
        elif name == "p":
            self.set_proxy_levels(self.proxy_levels - 1 if self.proxy_levels > 1 else self.max_proxy_levels)
        elif name in ("+", "-"):
            self.zoom(1 if name == "+" else -1)

    def drag(self, dx: float, dy: float) -> None:
        """Mouse drag by (dx, dy) window pixels (y down): look right / down, as in a game (orbiting:
        circle the pivot the same way)."""
        (self.turn if self.pivot is None else self.orbit)(dx * self.config.drag_degrees, -dy * self.config.drag_degrees)

    def scroll(self, dy: float) -> None:
        """Mouse wheel: up narrows the field of view."""
        self.zoom(dy)

    def step(self, dt: float) -> None:
        """Advance ``dt`` seconds of held keys: fly along the view (forward/back), the camera's x
        (left/right) and the world up (q/e); turn with the arrow keys."""
        move = sum((np.array(MOVE_KEYS[k]) for k in self.held if k in MOVE_KEYS), np.zeros(3))
        if move.any():
            speed = self.speed * (4.0 if "shift" in self.held else 1.0)
            right, up, forward = move
            if self.pivot is not None:  # orbiting: w / s along the line to the pivot, not past it
                to_pivot = self.pivot - self.position
                step = min(dt * speed * forward, 0.9 * float(np.linalg.norm(to_pivot)))
                self.position = self.position + step * to_pivot / np.linalg.norm(to_pivot)
            else:
                self.position = self.position + dt * speed * (right * self.R[0] + up * self.up + forward * self.R[2])
        turn = sum((np.array(TURN_KEYS[k]) for k in self.held if k in TURN_KEYS), np.zeros(2))
        if turn.any():
            (self.turn if self.pivot is None else self.orbit)(turn[0] * self.config.turn_rate * dt,
                                                              turn[1] * self.config.turn_rate * dt)

    def resize(self, width: int, height: int) -> None:
        """Render frames of ``width`` x ``height`` pixels from now on."""
        self.width, self.height = max(1, int(width)), max(1, int(height))

    # -- switches -------------------------------------------------------------------------------
    def set_method(self, name: str) -> None:
        if name not in self.methods:
            raise ValueError(f"method {name!r} is not available here (have: {', '.join(self.methods)})")
        self.method = name
        if self.leveling and not self.methods[name].uses_leveling:
            self.leveling = False
        self.message = f"method {name}"

    def set_proxy_levels(self, k: int) -> None:
        """Render with the proxy set of the ``k`` coarsest octree levels (1..the bundle's)."""
        self.proxy_levels = int(np.clip(k, 1, self.max_proxy_levels))
        n = len(self.proxy_bundle().proxy["positions"])
        self.message = f"proxies: {self.proxy_levels} octree levels, {n} points"

    def proxy_bundle(self) -> Bundle:
        """The bundle with the current proxy set. The bundle stores P_LD coarsest level first, so
        the k coarsest levels are a prefix of it; their splat radii come from their own density,
        as preprocessing computes them (a sparser set needs larger discs), their labels stay."""
        k = self.proxy_levels
        if k not in self._proxy_bundles:
            from dmrt.preprocess.config import PreprocessConfig
            from dmrt.preprocess.proxies import label_proxies, proxy_prefix

            n = int(sum(self.bundle.meta["counts"]["octree_level_counts"][:k]))
            pre = {**dataclasses.asdict(PreprocessConfig()), **self.bundle.meta.get("parameters", {}).get("preprocess", {})}
            config = PreprocessConfig(**{f: pre[f] for f in ("radius_k", "radius_scale")})
            proxies = label_proxies(proxy_prefix(self.bundle.proxy, n), None, None, None, config, relabel=False)
            self._proxy_bundles[k] = dataclasses.replace(self.bundle, _proxy=proxies.proxy)
        return self._proxy_bundles[k]

    def set_layers(self, k: int) -> None:
        self.layers = int(np.clip(k, 1, MAX_LAYERS))
        self.message = f"{self.layers} layers"

    def set_buffer(self, name: str) -> None:
        if name not in BUFFERS:
            raise ValueError(f"buffer must be one of {', '.join(BUFFERS)}, not {name!r}")
        self.buffer = name
        self.message = f"buffer {name}"

    def set_leveling(self, on: bool) -> None:
        if on and not self.methods[self.method].uses_leveling:
            self.message = f"leveling is not available for {self.method}"
            return
        self.leveling = bool(on)
        self.message = f"leveling {'on' if on else 'off'}"

    def buffers(self) -> list[str]:
        """The buffers the current method can show (all but ``splat_label`` come from the frame;
        a renderer without ``layers()`` has no splat labels)."""
        has_layers = isinstance(self.renderer(), LayeredRenderer)
        if self.frame is not None and "depth" in self.frame:
            has_iterations = "iterations" in self.frame
        else:  # before a frame, or a frame left on the GPU: DMRT's frames have them, DMT's not
            has_iterations = has_layers
        return [b for b in BUFFERS if (b != "splat_label" or has_layers) and (b != "iterations" or has_iterations)]

    def renderer(self):
        """The renderer for the current method / layers / leveling, built on first use; the
        least recently used one is released when more than ``max_renderers`` would be alive."""
        method = self.methods[self.method]
        key = (method.name, self.layers if method.uses_layers else None, self.leveling if method.uses_leveling else None,
               self.proxy_levels if method.uses_layers else None)
        if key in self._renderers:
            self._renderers.move_to_end(key)
            return self._renderers[key]
        while len(self._renderers) >= self.config.max_renderers:
            _, old = self._renderers.popitem(last=False)
            old.release()
        config = dataclasses.replace(self.render_config, layers=self.layers, leveling=self.leveling)
        self._renderers[key] = method.make(self.proxy_bundle() if method.uses_layers else self.bundle, config, self.ctx)
        return self._renderers[key]

    # -- recording and screenshots ----------------------------------------------------------
    def toggle_recording(self) -> None:
        """Start recording the cameras of the rendered frames, or stop and write them to a free
        name beside ``config.path_file`` (:func:`dmrt.runtime.walkthrough.save_path`)."""
        if not self.recording:
            self.recording, self.recorded = True, []
            self.message = "recording"
            return
        self.recording = False
        if not self.recorded:
            self.message = "recording stopped: no frames"
            return
        path = _free_path(self.config.path_file)
        path.parent.mkdir(parents=True, exist_ok=True)
        save_path(path, self.recorded)
        self.last_path = path
        self.message = f"wrote {path} ({len(self.recorded)} frames; replay: dmrt render BUNDLE --path {path} --out DIR)"
        print(self.message)

    def screenshot(self, path=None) -> Path:
        """Save the current view as a PNG: a still, rendered again after the photos it needs were
        made resident (as ``dmrt render`` does), not recorded into a path. ``path`` defaults to a
        free name beside ``config.screenshot_file``."""
        from PIL import Image

        self.renderer().flush_photos()
        self.update(record=False)
        path = Path(path) if path is not None else _free_path(self.config.screenshot_file)
        path.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(self.image()).save(path)
        self.last_screenshot = path
        self.message = f"wrote {path}"
        print(self.message)
        return path

    # -- frames ---------------------------------------------------------------------------------
    def update(self, record: bool = True, readback: bool = True) -> dict:
        """Render a frame of the current view with the current method and upload the buffer
        shown. While recording (and ``record``), the frame's camera is appended to the path.

        ``readback=False`` (the window's loop): when the colour is shown and the renderer keeps
        its colours on the GPU (:class:`GpuColorRenderer`), the frame stays there and its colours
        are copied into the display's texture on the GPU: no per-frame read-back of the frame's
        buffers (32 bytes a pixel: ~30 MB a 720p frame). Other buffers are read back as before.

        Returns
        -------
        dict
            The renderer's frame dict (plus ``splat_label`` (h, w) int32 when that buffer is shown);
            a frame left on the GPU has only ``timings`` and ``cpu_ms``.
        """
        renderer = self.renderer()
        cam = self.camera
        live = not readback and self.buffer == "color" and isinstance(renderer, GpuColorRenderer)
        t0 = time.perf_counter()
        frame = renderer.render(cam, cam.width, cam.height, readback=not live)
        if self.buffer == "splat_label" and isinstance(renderer, LayeredRenderer):
            frame["splat_label"] = renderer.layers()["label"][0]
        now = time.perf_counter()
        self.frame_ms = (now - t0) * 1e3
        if self._last_update is not None:  # frames per second between updates, smoothed
            fps = 1.0 / max(now - self._last_update, 1e-6)
            self.fps = fps if self.fps == 0 else 0.9 * self.fps + 0.1 * fps
        self._last_update = now
        if self.recording and record:
            self.recorded.append(dataclasses.replace(cam, name=f"frame_{len(self.recorded):05d}"))
        self.frame, self.frame_size, self._frame_renderer = frame, (cam.width, cam.height), renderer
        self._upload(frame, renderer.gpu_colors() if live else None)
        return frame

    def render(self) -> np.ndarray:
        """Render a frame (:meth:`update`) and return what the display shows.

        Returns
        -------
        (height, width, 3) uint8
            The buffer shown, mapped to colours (with the overlay when on), row 0 at the top.
        """
        self.update()
        return self.image()

    def image(self) -> np.ndarray:
        """(height, width, 3) uint8: the last frame as displayed, drawn off screen at its size."""
        w, h = self.frame_size
        if self._fbo is None or self._fbo.size != (w, h):
            if self._fbo is not None:
                self._fbo.release()
            self._fbo = self.ctx.simple_framebuffer((w, h), components=4)
        previous = self.ctx.fbo
        self.draw(self._fbo, (0, 0, w, h))
        data = self._fbo.read(components=3, alignment=1)
        # bind back what was bound (a window's framebuffer, else the default one): moderngl
        # re-binds "the bound framebuffer" when it makes another, which fails once ours is released
        (previous or self.ctx.detect_framebuffer(0)).use()
        # GL rows start at the bottom; the display drew image row 0 at the top
        return np.flipud(np.frombuffer(data, np.uint8).reshape(h, w, 3)).copy()

    def draw(self, fbo, viewport) -> None:
        """Draw the last frame's shown buffer into ``fbo`` (a window's or an off-screen one) over
        ``viewport`` (x, y, width, height), scaled to fill it."""
        fbo.use()
        fbo.viewport = tuple(viewport)
        t = self._textures
        t["color"].use(0)
        t["scalar"].use(1)
        t["index"].use(2)
        t["overlay"].use(3)
        set_uniforms(self._program, u_mode=BUFFERS[self._shown], u_color=0, u_scalar=1, u_index=2, u_overlay=3,
                     u_range=self._range, u_show_overlay=int(self.overlay))
        self._vao.render(moderngl.TRIANGLES, vertices=3)

    def status(self) -> list[str]:
        """The overlay's lines (the window title shows the first)."""
        method = self.methods[self.method]
        level = ("on" if self.leveling else "off") if method.uses_leveling else "n/a"
        layers = f"{self.layers} layers  {self.proxy_levels}/{self.max_proxy_levels} proxy levels  " if method.uses_layers else ""
        lines = [f"{self.method}  {layers}{self._shown}  leveling {level}"
                 + (f"  REC {len(self.recorded)}" if self.recording else ""),
                 f"{self.fps:.1f} fps  {self.frame_ms:.1f} ms/frame  fov {self.fov:.0f} deg"]
        if self.frame is not None and self.frame.get("timings"):
            lines.append("GPU ms  " + "  ".join(f"{_STAGE_ABBREV.get(k, k)} {format_ms(v).removesuffix(' ms')}"
                                                for k, v in self.frame["timings"].items()))
        if self.message:
            lines.append(self.message)
        return lines

    def close(self) -> None:
        """Write a recording in progress and free the renderers and the display's GPU objects."""
        if self.recording:
            self.toggle_recording()
        for renderer in self._renderers.values():
            renderer.release()
        self._renderers.clear()
        for obj in [*self._textures.values(), self._fbo, self._vao]:
            if obj is not None:
                obj.release()
        self._textures, self._fbo = {}, None

    # -- internals ------------------------------------------------------------------------------
    @property
    def _shown(self) -> str:
        """The buffer actually shown: the chosen one when the method has it, else the colour."""
        return self.buffer if self.frame is None or self.buffer in self.buffers() else "color"

    def _upload(self, frame: dict, gpu_colors=None) -> None:
        """Write the textures the shown buffer needs (the colour always: the holes view greys it);
        ``gpu_colors``: the colour from the renderer's buffer on the GPU (a frame not read back)."""
        w, h = self.frame_size
        t = self._textures
        if not t or t["color"].size != (w, h):
            for tex in t.values():
                tex.release()
            t["color"] = self.ctx.texture((w, h), 4)  # RGBA8: the renderers' packed colours as they are
            t["scalar"] = self.ctx.texture((w, h), 1, dtype="f4")
            t["index"] = self.ctx.texture((w, h), 1, dtype="i4")
            t["overlay"] = self.ctx.texture((w, h), 4)
            for tex in t.values():
                tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
            self._overlay_text = None
        if gpu_colors is not None:
            self.ctx.memory_barrier(moderngl.PIXEL_BUFFER_BARRIER_BIT)  # written by a shader
            t["color"].write(gpu_colors)
            if self.overlay:
                self._draw_overlay(w, h)
            return
        rgba = np.empty((h, w, 4), np.uint8)
        rgba[..., :3], rgba[..., 3] = frame["color"], 255
        t["color"].write(rgba.tobytes())
        shown = self._shown
        if shown == "depth":
            z = frame["depth"]
            surface = z[z > 0]
            self._range = (float(surface.min()), float(surface.max())) if surface.size else (0.0, 1.0)
            t["scalar"].write(np.ascontiguousarray(z, np.float32).tobytes())
        elif shown == "iterations":
            it = frame["iterations"].astype(np.float32)
            self._range = (0.0, float(it.max()))
            t["scalar"].write(it.tobytes())
        elif shown in ("label", "splat_label", "holes"):
            if shown == "holes":
                index = frame.get("layer_used")
                if index is None:  # a renderer without layers: a hole is where it found no surface
                    index = np.where(frame["depth"] > 0, 0, -1)
            else:
                index = frame[shown]
            t["index"].write(np.ascontiguousarray(index, np.int32).tobytes())
        if self.overlay:
            self._draw_overlay(w, h)

    def _draw_overlay(self, w: int, h: int) -> None:
        """Render the status lines into the overlay texture (PIL's built-in font on a translucent
        box at the top left); redrawn only when the text changed, at most 4 times a second."""
        from PIL import Image, ImageDraw, ImageFont

        lines = self.status()
        now = time.perf_counter()
        if lines == self._overlay_text or (self._overlay_text is not None and now - self._overlay_time < 0.25):
            return
        self._overlay_text, self._overlay_time = lines, now
        size = max(9, h // 30)
        font = ImageFont.load_default(size=size)
        image = Image.new("RGBA", (w, h), (0, 0, 0, 0))
        draw = ImageDraw.Draw(image)
        text = "\n".join(lines)
        box = draw.multiline_textbbox((size // 2, size // 2), text, font=font, spacing=size // 4)
        pad = size // 3
        draw.rectangle((box[0] - pad, box[1] - pad, box[2] + pad, box[3] + pad), fill=(0, 0, 0, 150))
        draw.multiline_text((size // 2, size // 2), text, font=font, fill=(255, 255, 255, 255), spacing=size // 4)
        self._textures["overlay"].write(np.asarray(image, np.uint8).tobytes())
