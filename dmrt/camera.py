"""Pinhole cameras in COLMAP's convention, and their one conversion to OpenGL clip space.

Convention (DESIGN.md): world -> camera is ``x_cam = R @ x_world + t``; camera axes are OpenCV's
(x right, y down, z forward); the centre of projection is ``C = -R.T @ t``. Pixel coordinates
``(u, v)`` follow COLMAP: the image's upper-left corner is (0, 0), so the centre of pixel
``(row i, column j)`` is ``(u, v) = (j + 0.5, i + 0.5)``. Depth is camera-space z, in metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Camera:
    """One registered photograph's pinhole camera.

    Attributes
    ----------
    name : str
        The image's file name as the COLMAP model gives it (relative to ``SCENE/images``).
    width, height : int
        Image size in pixels.
    fx, fy, cx, cy : float
        Intrinsics in pixels (principal point in the corner-origin convention above).
    R : (3, 3) float64
        World -> camera rotation.
    t : (3,) float64
        World -> camera translation, metres.
    """

    name: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self):
        self.R = np.asarray(self.R, dtype=np.float64).reshape(3, 3)
        self.t = np.asarray(self.t, dtype=np.float64).reshape(3)
        self.width, self.height = int(self.width), int(self.height)
        self.fx, self.fy, self.cx, self.cy = (float(v) for v in (self.fx, self.fy, self.cx, self.cy))

    # -- construction -------------------------------------------------------------------------
    @classmethod
    def look_at(cls, name: str, eye, target, width: int, height: int, fov_x_deg: float = 60.0,
                up=(0.0, 0.0, 1.0)) -> "Camera":
        """A camera at ``eye`` looking at ``target`` with world ``up`` (z-up scenes), square pixels."""
        eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
        z = target - eye
        z /= np.linalg.norm(z)
        x = np.cross(z, up)
        if np.linalg.norm(x) < 1e-9:  # looking straight up/down: any perpendicular will do
            x = np.cross(z, [1.0, 0.0, 0.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)  # y down in the image when up is world-up
        R = np.stack([x, y, z])
        f = 0.5 * width / np.tan(np.radians(fov_x_deg) / 2)
        return cls(name, width, height, f, f, width / 2, height / 2, R, -R @ eye)

    # -- derived quantities -------------------------------------------------------------------
    @property
    def center(self) -> np.ndarray:
        """(3,) float64: centre of projection in world coordinates, metres."""
        return -self.R.T @ self.t

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 intrinsic matrix."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def scaled(self, width: int, height: int) -> "Camera":
        """The same camera rendering to ``width`` x ``height`` pixels (intrinsics scaled per axis)."""
        sx, sy = width / self.width, height / self.height
        return Camera(self.name, width, height, self.fx * sx, self.fy * sy, self.cx * sx,
                      self.cy * sy, self.R.copy(), self.t.copy())

    def resized(self, width: int | None = None, height: int | None = None) -> "Camera":
        """:meth:`scaled` where a missing side follows the camera's aspect ratio."""
        if width is None and height is None:
            return self
        if height is None:
            height = max(1, round(width * self.height / self.width))
        if width is None:
            width = max(1, round(height * self.width / self.height))
        return self.scaled(width, height)

    def relative_to(self, origin) -> "Camera":
        """The camera in a frame whose world origin sits at ``origin`` (scene origin, metres).

        Points become ``x_local = x_world - origin``; then ``x_cam = R x_local + (t + R origin)``.
        GPU code works in this frame so that float32 keeps millimetres on UTM-sized coordinates.
        """
        origin = np.asarray(origin, dtype=np.float64)
        return Camera(self.name, self.width, self.height, self.fx, self.fy, self.cx, self.cy,
                      self.R.copy(), self.t + self.R @ origin)

    # -- projection ---------------------------------------------------------------------------
    def world_to_camera(self, points: np.ndarray) -> np.ndarray:
        """(n, 3) world points -> (n, 3) float64 camera-space points."""
        return np.asarray(points, dtype=np.float64) @ self.R.T + self.t

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points.

        Returns
        -------
        uv : (n, 2) float64
            Pixel coordinates (corner-origin convention); meaningless where ``z <= 0``.
        z : (n,) float64
            Camera-space depth, metres.
        """
        pc = self.world_to_camera(points)
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([self.fx * pc[:, 0] / z + self.cx, self.fy * pc[:, 1] / z + self.cy], axis=1)
        return uv, z

    def pixel_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Rays through every pixel centre, row-major from the top-left pixel.

        Returns
        -------
        dirs : (height * width, 3) float64
            World-space directions scaled so that a point at parameter ``s`` along the ray has
            camera depth ``z = s`` (not unit length): ``point = center + s * dirs``.
        center : (3,) float64
            The common origin.
        """
        j, i = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        d_cam = np.stack([(j.ravel() - self.cx) / self.fx, (i.ravel() - self.cy) / self.fy,
                          np.ones(j.size)], axis=1)
        return d_cam @ self.R, self.center

    def gl_view_projection(self, near: float, far: float, origin=None) -> np.ndarray:
        """(4, 4) float32 matrix taking world points (relative to ``origin``) to OpenGL clip space.

        The single place where COLMAP/OpenCV axes meet OpenGL's. Clip y is ``2 v / height - 1``,
        i.e. *not* flipped: framebuffer row 0 (GL's bottom row in memory) holds image row 0 (the
        top of the photo), so a read-back array is already in image order with no ``flipud``.
        The price is a mirrored triangle winding, which no program here culls on.
        Clip w equals camera z, so ``gl_FragCoord.w == 1 / z``.
        """
        cam = self if origin is None else self.relative_to(origin)
        W, H = self.width, self.height
        P = np.array([
            [2 * self.fx / W, 0.0, 2 * self.cx / W - 1.0, 0.0],
            [0.0, 2 * self.fy / H, 2 * self.cy / H - 1.0, 0.0],
            [0.0, 0.0, (far + near) / (far - near), -2.0 * far * near / (far - near)],
            [0.0, 0.0, 1.0, 0.0],
        ])
        V = np.eye(4)
        V[:3, :3], V[:3, 3] = cam.R, cam.t
        return (P @ V).astype(np.float32)

    def __repr__(self) -> str:
        c = self.center
        return (f"Camera({self.name!r}, {self.width}x{self.height}, f=({self.fx:.1f},{self.fy:.1f}), "
                f"center=({c[0]:.3f},{c[1]:.3f},{c[2]:.3f}))")
