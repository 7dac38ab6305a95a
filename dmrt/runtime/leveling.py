"""Screen-space leveling (paper Section 5.2.3, last step): balance the colours of regions of a frame
textured by different photographs.

The seams of the frame tell how the photos differ: ``shaders/dmrt_leveling_seams.glsl`` looks at
every pair of neighbouring pixels that lie on one surface but carry different labels ``a < b``,
samples both photos at the same surface point and sums ``log(colour in a) - log(colour in b)``
per channel. Exposure and white balance differences are per-photo factors, so they show up as
constant log offsets ``d_ab``; this module solves for one log gain ``x_j`` per photo and channel

    minimise   sum_(a,b) w_ab (d_ab + x_a - x_b)^2  +  reg * sum_a deg_a x_a^2

(``w_ab`` = seam samples of the pair, ``deg_a`` = seam samples of photo ``a``: the small second
term fixes the free common offset and keeps a photo without seams at gain 1), then shifts the
gains so that the frame's mean brightness (pixel-weighted over the leveled photos) is unchanged.
``shaders/dmrt_leveling_apply.glsl`` multiplies every pixel by its photo's gain.

One gain per photo is the leveling function of Lempitsky and Ivanov's seam leveling with infinite
smoothness inside each region: it removes the global exposure and white-balance steps between
photos (what a tripod camera with auto-exposure produces) without the blur of a per-pixel
correction field, and is solved per frame from what is on screen ("online").
"""

from __future__ import annotations

import numpy as np

from dmrt.gl import abi
from dmrt.gl.kernels import fill_u32
from dmrt.gl.shaders import load_program, set_uniforms

LOG_SCALE = 1024.0  # fixed point of the seam sums: shaders/dmrt_leveling_seams.glsl


def pair_offsets(pairs: np.ndarray, min_samples: int = 16) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The seam pairs with enough support, from the GPU sums.

    Parameters
    ----------
    pairs : (n, n, 4) int32
        Per ordered pair (row = smaller label): sample count, then the three channels' sums of
        ``log(c_a) - log(c_b)`` in units of ``1 / LOG_SCALE``.
    min_samples : int
        Pairs with fewer seam samples are ignored (a few pixels of a seam are mostly noise).

    Returns
    -------
    ab : (p, 2) int64, the pairs ``a < b``
    weight : (p,) float64, their sample counts
    offset : (p, 3) float64, mean ``log(c_a) - log(c_b)`` per channel
    """
    count = pairs[..., 0]
    a, b = np.nonzero(count >= max(1, min_samples))
    weight = count[a, b].astype(np.float64)
    offset = pairs[a, b, 1:].astype(np.float64) / LOG_SCALE / weight[:, None]
    return np.stack([a, b], axis=1), weight, offset


def solve_gains(pairs: np.ndarray, pixel_counts: np.ndarray, regularization: float = 0.01,
                min_samples: int = 16, max_gain: float = 2.0) -> np.ndarray:
    """Per-photo RGB gains that level the seams of a frame (the module docstring's problem).

    Parameters
    ----------
    pairs : (n, n, 4) int32, see :func:`pair_offsets`
    pixel_counts : (n,) int, pixels per label in the frame (the mean-brightness weights)
    regularization : float, ``reg`` of the module docstring
    min_samples : int, see :func:`pair_offsets`
    max_gain : float, gains are clamped to ``[1 / max_gain, max_gain]``

    Returns
    -------
    (n, 3) float32 gains, 1 for photos without seams.
    """
    n = pairs.shape[0]
    gains = np.ones((n, 3), np.float32)
    ab, w, d = pair_offsets(pairs, min_samples)
    if len(ab) == 0:
        return gains
    used = np.unique(ab)
    index = np.full(n, -1, np.int64)
    index[used] = np.arange(len(used))
    i, j = index[ab[:, 0]], index[ab[:, 1]]
    m = len(used)
    # normal equations of sum w (d + x_i - x_j)^2 + reg * deg x^2
    A = np.zeros((m, m))
    np.add.at(A, (i, i), w)
    np.add.at(A, (j, j), w)
    np.add.at(A, (i, j), -w)
    np.add.at(A, (j, i), -w)
    deg = np.diag(A).copy()
    A[np.diag_indices(m)] += regularization * deg
    rhs = np.zeros((m, 3))
    np.add.at(rhs, i, -w[:, None] * d)
    np.add.at(rhs, j, w[:, None] * d)
    x = np.linalg.solve(A, rhs)
    px = np.asarray(pixel_counts, np.float64)[used]
    if px.sum() > 0:
        x -= (px[:, None] * x).sum(axis=0) / px.sum()
    gains[used] = np.clip(np.exp(x), 1.0 / max_gain, max_gain)
    return gains


class ScreenLeveler:
    """The leveling stage on the GPU, shared by the DMRT and DMT renderers (they write the same
    per-pixel ``Hit`` records and colours, see ``shaders/dmrt_frame.glsl``).

    Parameters
    ----------
    ctx : moderngl.Context
    n_photos : int
    min_samples, max_gain : see :func:`solve_gains`
    threshold : float, metres: neighbouring pixels further apart in depth are not a seam
    visibility_tol : float, metres: a photo must see the seam point this closely (its depth map)
    """

    def __init__(self, ctx, n_photos: int, min_samples: int = 16, max_gain: float = 2.0,
                 threshold: float = 0.20, visibility_tol: float = 0.05):
        self.ctx, self.n = ctx, int(n_photos)
        self.min_samples, self.max_gain = min_samples, max_gain
        self.threshold, self.visibility_tol = float(threshold), float(visibility_tol)
        self._seams = load_program(ctx, "dmrt_leveling_seams")
        self._apply = load_program(ctx, "dmrt_leveling_apply")
        # the seam pass adds into `pairs` (GPU only), copied into `_pairs_host` for the CPU, as the
        # label histogram does (FrameShading: why)
        self.pairs = ctx.buffer(reserve=16 * self.n * self.n)
        self._pairs_host = ctx.buffer(reserve=16 * self.n * self.n)
        self.gains_buffer = ctx.buffer(reserve=16 * self.n)
        self.gains = np.ones((self.n, 3), np.float32)

    @property
    def nbytes(self) -> int:
        return 2 * self.pairs.size + self.gains_buffer.size

    def run(self, timer, hits, colors, photos, images, depthmaps, cam_uniforms: dict, counts) -> float:
        """Level the frame's colours in place.

        Parameters
        ----------
        timer : dmrt.gl.GpuTimer, the passes are timed as ``leveling``
        hits, colors : moderngl.Buffer, the frame's ``Hit`` records and packed RGBA8 colours
        photos : moderngl.Buffer, the ``Photo`` records (``dmrt.runtime.renderer.photo_params``)
        images : dmrt.runtime.texturing.ImageCache
        depthmaps : moderngl.TextureArray, the photos' depth maps (as ``photos`` describes them)
        cam_uniforms : dict, ``u_R, u_t, u_K, u_size`` of the frame
        counts : (n_photos,) int, pixels per label in the frame

        Returns
        -------
        float, CPU ms of reading the seam sums back and solving (:attr:`gains` holds the result).
        """
        import time

        import moderngl

        barrier = moderngl.SHADER_STORAGE_BARRIER_BIT | moderngl.COMMAND_BARRIER_BIT
        w, h = cam_uniforms["u_size"]
        n, ctx = self.n, self.ctx
        with timer.section("leveling"):
            fill_u32(ctx, self.pairs, 0, 4 * n * n)
            ctx.memory_barrier(barrier)
            hits.bind_to_storage_buffer(abi.B_HITS)
            photos.bind_to_storage_buffer(abi.B_PHOTOS)
            images.slots.bind_to_storage_buffer(abi.B_SLOTS)
            self.pairs.bind_to_storage_buffer(abi.B_PAIRS)
            depthmaps.use(0)
            images.low.use(1)
            images.high.use(2)
            # colours below 2/255 or above 250/255 are clipped or noise, not exposure
            set_uniforms(self._seams, u_photos=n, u_threshold=self.threshold, u_visibility_tol=self.visibility_tol,
                         u_min_value=2 / 255, u_max_value=250 / 255, u_depthmaps=0, u_low=1, u_high=2,
                         u_low_dims=images.low_dims, u_high_dims=(images.high.width, images.high.height),
                         **cam_uniforms)
            self._seams.run(-(-w // 8), -(-h // 8))
            ctx.memory_barrier(barrier | moderngl.BUFFER_UPDATE_BARRIER_BIT)
            ctx.copy_buffer(self._pairs_host, self.pairs)
        t0 = time.perf_counter()
        pairs = np.frombuffer(self._pairs_host.read(), np.int32).reshape(n, n, 4)
        self.gains = solve_gains(pairs, counts, min_samples=self.min_samples, max_gain=self.max_gain)
        self.gains_buffer.write(np.concatenate([self.gains, np.ones((n, 1), np.float32)], axis=1).tobytes())
        cpu_ms = (time.perf_counter() - t0) * 1e3
        with timer.section("leveling"):
            hits.bind_to_storage_buffer(abi.B_HITS)
            colors.bind_to_storage_buffer(abi.B_COLORS)
            self.gains_buffer.bind_to_storage_buffer(abi.B_GAINS)
            set_uniforms(self._apply, u_count=w * h)
            self._apply.run(max(1, min(-(-w * h // 64), 65535)))
            ctx.memory_barrier(moderngl.BUFFER_UPDATE_BARRIER_BIT)
        return cpu_ms

    def release(self) -> None:
        self.pairs.release()
        self._pairs_host.release()
        self.gains_buffer.release()
