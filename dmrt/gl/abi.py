"""The GPU/Python ABI: every number that Python and the GLSL programs must agree on, in one place.

:func:`dmrt.gl.shaders.load_program` puts each entry of :data:`DEFINES` at the top of every program
as ``#define NAME value``, so a shader writes ``layout(std430, binding = B_HITS)`` and compares with
``EMPTY_BITS``, and Python binds ``abi.B_HITS`` and reads ``abi.HIT_DTYPE``. The record layouts
(``HIT_DTYPE`` <-> ``struct Hit`` in ``shaders/dmrt_frame.glsl``, ``PHOTO_FLOATS`` <-> ``struct
Photo`` in ``shaders/dmrt_photos.glsl``) are checked on both sides by ``tests/test_abi.py``.

Storage-buffer binding points are unique per buffer role across every program (GL guarantees 8
binding points only, but every driver the suite runs on has >= 80: NVIDIA 96, Mesa llvmpipe 80),
so a buffer bound for one pass is never silently read as another's by the next.
"""

from __future__ import annotations

import numpy as np

# -- storage-buffer binding points --------------------------------------------------------------
# DMRT frame
B_PROXIES = 0       # (n, PROXY_FLOATS) float32 proxy discs (dmrt_splat_common.glsl)
B_LAYER_DEPTH = 1   # k x h x w uint: float bits of each label layer's camera z
B_LAYER_LABEL = 2   # k x h x w int: each label layer's label
B_LARGE = 3         # dispatch-indirect command + list of discs splatted by a whole workgroup
B_HITS = 4          # h x w Hit records
B_PHOTOS = 5        # n_photos Photo records
B_COUNTS = 6        # n_photos uint: the label histogram
B_COLORS = 7        # h x w packed RGBA8
B_STEP_STATS = 8    # layers x STEP_BINS x 4 uint: iterative-search statistics
B_PAIRS = 9         # n_photos x n_photos x 4 int: leveling seam sums
B_GAINS = 10        # n_photos vec4: leveling gains
B_KBUFFER = 11      # h x w x slots uint: k-buffer fragment lists
B_OVERFLOW = 12     # uint: k-buffer pixels whose list ran out
B_KEY = 13          # h x w uint (or uint64): labeling pass nearest-proxy keys
B_VLABEL = 14       # h x w int: labeling pass labels (portable path)
B_VKEY = 15         # h x w uint64: visibility pass (depth, label) keys (int64 path)
B_SLOTS = 16        # n_photos int: photo -> full-resolution cache layer, -1 = low-res only
# common kernels
B_FILL = 17         # the buffer fill_u32.glsl writes
# depth maps (preprocessing)
B_SPLATS = 18       # (n, SPLAT_FLOATS) float32 P_HD discs
B_DEPTH_BITS = 19   # h x w uint: float bits of camera z
B_DEPTH_LARGE = 20  # count + list of large discs
# DMT
B_DMT_BOXES = 21    # n_maps x 2 vec4 bounding boxes
B_DMT_COMMANDS = 22  # n_maps draw-indirect commands
B_DMT_STATS = 23    # culled maps, triangles drawn
# tile-binned visibility (dmrt/runtime/tiles.py)
B_TILE_ENTRIES = 24  # uint proxy index per disc-tile overlap
B_TILE_COUNTS = 25   # uint per tile: discs binned
B_TILE_OFFSETS = 26  # uint per tile + 1: where each tile's entries start
B_FRAME_STATUS = 27  # FrameStatus record: STATUS_HEADER_WORDS uint, then int wanted[] (dmrt/runtime/status.py)
# photometric adjustment
B_PHOTO_GAINS = 28  # n_photos vec4: each photo's RGB colour gain (bundle.json photo_gains), 1 = unchanged
# raytracing's lists of holes (shaders/dmrt_raytrace.glsl): a dispatch-indirect header (groups x,
# y, z, items), then a pixel index per hole
B_HOLES = 29        # the holes a fill pass walks
B_HOLES_NEXT = 30   # the holes a pass leaves to the next fill pass
# the leveling's gains solve on the GPU (shaders/dmrt_leveling_solve.glsl), its scratch buffers
B_LEVEL_EDGES = 32  # n_photos x n_photos uvec2: row a lists photo a's seam neighbours (index, weight bits)
B_LEVEL_P = 33      # n_photos vec4: the conjugate-gradient search direction, where shared memory is too small
B_NORMALS = 34      # h x w x 3 float: unit world normals, written only for a frame that is read back
B_TILE_MASKS = 35   # h x w x 2 uvec4: which of its tile's first 256 discs hit each pixel (tiles raster -> labeling)
# view-dependent photo choice (dmrt/runtime/view_choice.py)
B_VIEW_SCORES = 36      # n_photos uint: each photo's score against the frame's sample points
B_VIEW_CANDIDATES = 37  # STATUS_HEADER_WORDS uint (word 1: count), then int: the photos each pixel tests
B_VIEW_BLEND = 38       # h x w ivec4: the 2nd-4th photo of a pixel's blend (-1 = none), the 4 weights packed
B_VIEW_LIST = 42        # int[]: the photos the scores test, with a partial map cache (else every photo)
# the depth-map cache (dmrt/runtime/maps.py), where a texture array cannot hold every photo
B_MAP_SLOTS = 39        # n_photos int: photo -> slot of the depth-map and low-resolution arrays, -1 = not resident
B_MAP_MISSING = 40      # 1 + n_photos uint: [0] any map missing this frame, [1 + j] photo j's: 1 missing, 2 read
# the photo choice's compacted list (dmrt/runtime/ranking.py): uint length, uint spare, then
# (count, photo) uvec2 per photo with a non-zero count
B_PHOTO_LIST = 41
# the synthetic scenes' OpenGL photographer (bench/scenes/glphoto.py): the photographed mesh's faces
B_SYNTH_FACES = 43
# the exact grid kNN (dmrt/preprocess/gpu_knn.py, shaders/knn_grid.glsl)
B_KNN_POINTS = 44     # n x (float x, y, z; uint index): positions sorted by cell, the caller's index
B_KNN_COLUMNS = 45    # nx * ny + 1 uint: each (x, y) column's first cell
B_KNN_CELLS = 46      # cells + 1 uvec2: a cell's z index and first point
B_KNN_INDICES = 47    # n x k uint: the neighbours found, nearest first
B_KNN_DISTANCES = 48  # n x k float: their distances, metres
# the tiles path's long lists split over workgroups (dmrt/runtime/tiles.py, shaders/dmrt_tiles_split.glsl):
# uint words: two dispatch-indirect headers (slices x, 1, 1, slices reserved; split tiles x, 1, 1,
# discs reserved: the scan reads x, the tiles the plan split), a uvec4 per slice (tile, its first
# slice, its slices, this slice), a uvec4 per split tile (tile, first slice, slices, unused), per tile
# its first disc or EMPTY_BITS, its discs and those not yet scattered, per slice and pixel of a tile
# its partial result (2 words), then the split tiles' discs (uvec2 each, as Entries)
B_TILE_SPLIT = 49

# -- sentinels ---------------------------------------------------------------------------------
EMPTY_BITS = 0xFFFFFFFF  # an empty depth (above every positive float's bits: atomicMin keeps the nearest)
EMPTY_LABEL = 0x7FFFFFFF  # an empty label layer entry
EMPTY_Z = float(np.finfo(np.float32).max)  # raster targets' clear value (MIN blending keeps the nearest)

# -- record layouts ----------------------------------------------------------------------------
# FrameStatus (dmrt/runtime/status.py): uint tile_total (the tile list's length), uint n_wanted, uint
# long_tiles (tiles whose list is longer than the split's minimum), a spare word, then int wanted[]
# (photos for the full-resolution cache, most frequent first)
STATUS_HEADER_WORDS = 4
# struct Hit (shaders/dmrt_frame.glsl): one per pixel, written by every DMRT/DMT pass; 16 bytes
HIT_DTYPE = np.dtype([("depth", "<f4"), ("label", "<i4"), ("final_label", "<i4"), ("layer_iters", "<u4")])
MAX_HIT_LAYER = 254  # layer index + 1 fills the low 8 bits of Hit.layer_iters


def hit_layer_iters(hits: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The layer and iteration count packed in ``Hit.layer_iters``.

    Parameters
    ----------
    hits : (...) HIT_DTYPE records

    Returns
    -------
    layer : (...) int32, 0-based index of the layer whose depth map gave the hit, -1 = none
    iters : (...) int32, iterative-search steps over every layer tried
    """
    packed = hits["layer_iters"]
    return (packed & 0xFF).astype(np.int32) - 1, (packed >> 8).astype(np.int32)


PHOTO_FLOATS = 24   # struct Photo (shaders/dmrt_photos.glsl): 6 vec4
PROXY_FLOATS = 8    # proxy disc: position xyz, radius, normal xyz, label bits (dmrt_splat_common.glsl)
SPLAT_FLOATS = 7    # P_HD disc: position xyz, normal xyz, radius (splat_depth_buffers.glsl)

# -- statistics --------------------------------------------------------------------------------
STEP_BINS = 32      # iterative-search step index bins (the last pools later steps)
STAT_LAYERS = 16    # layers the per-workgroup step sums hold in shared memory

BINDINGS = {name: value for name, value in globals().items() if name.startswith("B_")}
DEFINES = {**BINDINGS, "EMPTY_BITS": "0xFFFFFFFFu", "EMPTY_LABEL": "0x7FFFFFFF", "EMPTY_Z": EMPTY_Z,
           "STEP_BINS": STEP_BINS, "STAT_LAYERS": STAT_LAYERS, "PROXY_FLOATS": PROXY_FLOATS,
           "SPLAT_FLOATS": SPLAT_FLOATS, "STATUS_HEADER_WORDS": STATUS_HEADER_WORDS}
