"""Screen-space leveling (paper Section 5.2.3, last step): balance the colours of regions of a frame
textured by different photographs.

The seams of the frame tell how the photos differ: ``shaders/dmrt_leveling_seams.glsl`` looks at
every pair of neighbouring pixels that lie on one surface but carry different labels ``a < b``,
samples both photos at the same surface point and sums ``log(colour in a) - log(colour in b)``
per channel. Exposure and white balance differences are per-photo factors, so they show up as
constant log offsets ``d_ab``; the leveling solves for one log gain ``x_j`` per photo and channel

    minimise   sum_(a,b) w_ab (d_ab + x_a - x_b)^2  +  reg * sum_a deg_a x_a^2

(``w_ab`` = seam samples of the pair, ``deg_a`` = seam samples of photo ``a``: the small second
term fixes the free common offset and keeps a photo without seams at gain 1), then shifts the
gains so that the frame's mean brightness (pixel-weighted over the leveled photos) is unchanged.
``shaders/dmrt_leveling_solve.glsl`` solves it on the GPU, in one workgroup (Jacobi-preconditioned
conjugate gradients; the shader says why that converges in a bounded number of iterations), from
the seam sums and this frame's label histogram, both on the GPU: nothing is read back and the CPU
never waits for the frame (the read-back and a numpy solve took 4.6-5.3 ms a frame on an H200).
``shaders/dmrt_leveling_apply.glsl`` multiplies every pixel by its photo's gain. :func:`solve_gains`
is the plain-numpy twin of the solve (float64, a direct solve), the truth the tests compare the
shader with; no frame runs it.

One gain per photo is the leveling function of Lempitsky and Ivanov's seam leveling with infinite
smoothness inside each region: it removes the global exposure and white-balance steps between
photos (what a tripod camera with auto-exposure produces) without the blur of a per-pixel
correction field, and is solved per frame from what is on screen ("online").
"""

from __future__ import annotations

import numpy as np

from dmrt.gl import abi
from dmrt.gl.kernels import fill_u32, groups
from dmrt.gl.shaders import load_program, set_uniforms

LOG_SCALE = 1024.0  # fixed point of the seam sums: shaders/dmrt_leveling_seams.glsl
REGULARIZATION = 0.01  # reg of the problem above
# the GPU solve (shaders/dmrt_leveling_solve.glsl says why these suffice): a channel stops at
# |residual| <= TOLERANCE |rhs|, after at most min(used photos + 16, MAX_ITERATIONS) iterations
TOLERANCE = 1e-6
MAX_ITERATIONS = 256
# the solve's one workgroup: on an H200 (probe, 192 photos, 30 of them on screen) 0.065 ms with 256
# invocations, 0.15 ms with 128, 0.07 with 512 (whose reductions leave less shared memory for p)
SOLVE_THREADS = 256
GL_SHARED_BYTES = 32768  # shared memory GL guarantees a compute workgroup (llvmpipe has exactly this)


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


def solve_gains(pairs: np.ndarray, pixel_counts: np.ndarray, regularization: float = REGULARIZATION,
                min_samples: int = 16, max_gain: float = 2.0) -> np.ndarray:
    """Per-photo RGB gains that level the seams of a frame (the module docstring's problem): the
    numpy twin of ``shaders/dmrt_leveling_solve.glsl`` (:meth:`ScreenLeveler.solve`).

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
    per-pixel ``Hit`` records and colours, see ``shaders/dmrt_frame.glsl``): seams, gains solve,
    apply, with nothing read back.

    Parameters
    ----------
    ctx : moderngl.Context
    n_photos : int
    min_samples, max_gain, regularization : see :func:`solve_gains`
    threshold : float, metres: neighbouring pixels further apart in depth are not a seam
    visibility_tol : float, metres: a photo must see the seam point this closely (its depth map)
    p_in_shared : bool, optional
        Where the solve keeps its search direction (n_photos x 12 bytes): shared memory, or the
        scratch buffer ``B_LEVEL_P``. Default: shared memory when it fits the 32 KiB that GL
        guarantees a workgroup. Tests force the buffer path.

    Attributes
    ----------
    pairs : moderngl.Buffer, (n, n, 4) int32 seam sums of the last frame (see :func:`pair_offsets`)
    gains_buffer : moderngl.Buffer, (n, 4) float32: RGB gain, 1 per photo, solved for the last frame
    """

    def __init__(self, ctx, n_photos: int, min_samples: int = 16, max_gain: float = 2.0,
                 threshold: float = 0.20, visibility_tol: float = 0.05, regularization: float = REGULARIZATION,
                 p_in_shared: bool | None = None, map_defines: dict | None = None):
        self.ctx, self.n = ctx, int(n_photos)
        self.min_samples, self.max_gain, self.regularization = min_samples, max_gain, float(regularization)
        self.threshold, self.visibility_tol = float(threshold), float(visibility_tol)
        n = self.n
        if p_in_shared is None:
            p_in_shared = 12 * n + 48 * SOLVE_THREADS + 16 <= GL_SHARED_BYTES  # s_p, s_red, s_used
        self._seams = load_program(ctx, "dmrt_leveling_seams", map_defines)
        self._solve = load_program(ctx, "dmrt_leveling_solve", {"N_PHOTOS": n, "THREADS": SOLVE_THREADS,
                                                                "P_SHARED": bool(p_in_shared), "LOG_SCALE": LOG_SCALE})
        self._apply = load_program(ctx, "dmrt_leveling_apply")
        self.pairs = ctx.buffer(reserve=16 * n * n)
        self._edges = ctx.buffer(reserve=8 * n * n)
        self._direction = ctx.buffer(reserve=16 * n)
        self.gains_buffer = ctx.buffer(np.ones((n, 4), np.float32).tobytes())

    @property
    def nbytes(self) -> int:
        return self.pairs.size + self._edges.size + self._direction.size + self.gains_buffer.size

    def solve(self, counts) -> None:
        """Dispatch the gains solve (``shaders/dmrt_leveling_solve.glsl``, the GPU twin of
        :func:`solve_gains`): :attr:`pairs` and ``counts`` in, :attr:`gains_buffer` out. The caller
        puts the memory barriers around it.

        Parameters
        ----------
        counts : moderngl.Buffer, (n_photos,) uint32 pixels per label in the frame (the
            mean-brightness weights), e.g. ``FrameShading``'s label histogram
        """
        self.pairs.bind_to_storage_buffer(abi.B_PAIRS)
        counts.bind_to_storage_buffer(abi.B_COUNTS)
        self.gains_buffer.bind_to_storage_buffer(abi.B_GAINS)
        self._edges.bind_to_storage_buffer(abi.B_LEVEL_EDGES)
        self._direction.bind_to_storage_buffer(abi.B_LEVEL_P)
        set_uniforms(self._solve, u_min_samples=max(1, int(self.min_samples)), u_reg=self.regularization,
                     u_max_gain=float(self.max_gain), u_max_iters=MAX_ITERATIONS, u_tol=TOLERANCE)
        self._solve.run(1)

    def read_gains(self, staging) -> np.ndarray:
        """(n_photos, 3) float32 gains of the last frame, read through ``staging``
        (:class:`dmrt.gl.kernels.Staging`: the gains buffer stays in GPU memory); waits for the GPU,
        read-back frames only."""
        return np.frombuffer(staging.read(self.gains_buffer), np.float32).reshape(self.n, 4)[:, :3].copy()

    def run(self, timer, hits, colors, photos, images, depthmaps, cam_uniforms: dict, counts) -> float:
        """Level the frame's colours in place: seams, solve, apply, all on the GPU.

        Parameters
        ----------
        timer : dmrt.gl.GpuTimer, the passes are timed as ``leveling:seams``, ``leveling:solve``
            and ``leveling:apply`` (together the stage ``leveling``)
        hits, colors : moderngl.Buffer, the frame's ``Hit`` records and packed RGBA8 colours
        photos : moderngl.Buffer, the ``Photo`` records (``dmrt.runtime.renderer.photo_params``)
        images : dmrt.runtime.texturing.ImageCache
        depthmaps : moderngl.TextureArray, the photos' depth maps (as ``photos`` describes them)
        cam_uniforms : dict, ``u_R, u_t, u_K, u_size`` of the frame
        counts : moderngl.Buffer, (n_photos,) uint32 pixels per label in this frame, on the GPU

        Returns
        -------
        float, CPU ms of issuing the passes (nothing waits for the GPU; :meth:`read_gains` reads
        the gains).
        """
        import time

        import moderngl

        t0 = time.perf_counter()
        barrier = moderngl.SHADER_STORAGE_BARRIER_BIT | moderngl.COMMAND_BARRIER_BIT
        w, h = cam_uniforms["u_size"]
        n, ctx = self.n, self.ctx
        with timer.section("leveling:seams"):
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
            ctx.memory_barrier(barrier)
        with timer.section("leveling:solve"):
            self.solve(counts)
            ctx.memory_barrier(barrier)
        with timer.section("leveling:apply"):
            self.apply(hits, colors, w * h)
            ctx.memory_barrier(moderngl.BUFFER_UPDATE_BARRIER_BIT)
        return (time.perf_counter() - t0) * 1e3

    def apply(self, hits, colors, count: int) -> None:
        """Dispatch ``shaders/dmrt_leveling_apply.glsl``: the first ``count`` pixels' colours times
        the gain of their final label (:attr:`gains_buffer`). The caller puts the memory barriers
        around it."""
        hits.bind_to_storage_buffer(abi.B_HITS)
        colors.bind_to_storage_buffer(abi.B_COLORS)
        self.gains_buffer.bind_to_storage_buffer(abi.B_GAINS)
        set_uniforms(self._apply, u_count=int(count))
        self._apply.run(groups(count, 64))

    def release(self) -> None:
        for buf in (self.pairs, self._edges, self._direction, self.gains_buffer):
            buf.release()
