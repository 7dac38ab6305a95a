"""The GPU/Python ABI (dmrt/gl/abi.py) is what the shaders see: the Hit and Photo records have the
same layout on both sides, the injected #defines have Python's values, and no shader keeps a binding
number or sentinel of its own."""

import re

import numpy as np
import pytest

from dmrt.gl import abi, load_program
from dmrt.gl.shaders import SHADER_DIR, stage_sources

pytestmark = pytest.mark.gpu

# A compute shader that fills hits[i] field by field with values derived from i, and reports the
# ABI's defines as the shader sees them. It includes the real record declarations.
PROBE = """
#if defined COMPUTE_SHADER
layout(local_size_x = 1) in;
#include "dmrt_frame.glsl"
#include "dmrt_photos.glsl"
layout(std430, binding = B_FILL) buffer Out { uint o[]; };
void main() {
    int i = int(gl_GlobalInvocationID.x);
    hits[i].depth = 1.5 + float(i);
    hits[i].label = 10 + i;
    hits[i].final_label = -1 - i;
    hits[i].layer_iters = layer_iters(i == 0 ? -1 : 20 + i, 300000 + i);
    if (i == 0) {
        o[0] = uint(B_HITS); o[1] = uint(B_PHOTOS); o[2] = EMPTY_BITS; o[3] = uint(EMPTY_LABEL);
        o[4] = uint(STEP_BINS); o[5] = uint(STAT_LAYERS); o[6] = floatBitsToUint(EMPTY_Z);
        o[7] = floatBitsToUint(photos[1].full.y); o[8] = floatBitsToUint(photos[1].k.z);
        o[9] = uint(photos.length());
    }
}
#endif
"""


@pytest.fixture
def probe(ctx, tmp_path, monkeypatch):
    import dmrt.gl.shaders as shader_mod

    (tmp_path / "abi_probe.glsl").write_text(PROBE)
    for inc in ("dmrt_frame.glsl", "splat_depth_common.glsl", "dmrt_photos.glsl"):
        (tmp_path / inc).write_text((SHADER_DIR / inc).read_text())
    monkeypatch.setattr(shader_mod, "SHADER_DIR", tmp_path)
    return load_program(ctx, "abi_probe")


def test_hit_and_photo_records_match(ctx, probe):
    n = 3
    hits = ctx.buffer(reserve=abi.HIT_DTYPE.itemsize * n)
    rows = np.arange(2 * abi.PHOTO_FLOATS, dtype=np.float32).reshape(2, abi.PHOTO_FLOATS)
    photos = ctx.buffer(rows.tobytes())
    out = ctx.buffer(reserve=4 * 16)
    hits.bind_to_storage_buffer(abi.B_HITS)
    photos.bind_to_storage_buffer(abi.B_PHOTOS)
    out.bind_to_storage_buffer(abi.B_FILL)
    probe.run(n)
    got = np.frombuffer(hits.read(), abi.HIT_DTYPE)
    i = np.arange(n)
    np.testing.assert_array_equal(got["depth"], 1.5 + i)
    np.testing.assert_array_equal(got["label"], 10 + i)
    np.testing.assert_array_equal(got["final_label"], -1 - i)
    layer, iters = abi.hit_layer_iters(got)
    np.testing.assert_array_equal(layer, np.where(i == 0, -1, 20 + i))
    np.testing.assert_array_equal(iters, 300000 + i)
    o = np.frombuffer(out.read(), np.uint32)
    assert list(o[:6]) == [abi.B_HITS, abi.B_PHOTOS, abi.EMPTY_BITS, abi.EMPTY_LABEL, abi.STEP_BINS, abi.STAT_LAYERS]
    assert o[6:7].view(np.float32)[0] == np.float32(abi.EMPTY_Z)
    # Photo row 1: 'full' is the 6th vec4 (floats 20..23), 'k' the 4th (12..15)
    assert o[7:9].view(np.float32).tolist() == [rows[1, 21], rows[1, 14]]
    assert o[9] == 2  # 2 rows of PHOTO_FLOATS floats are exactly 2 records
    for b in (hits, photos, out):
        b.release()


def test_shaders_take_bindings_and_sentinels_from_the_abi():
    literal = re.compile(r"binding\s*=\s*\d|0x[fF]{8}u?\b|0x7[fF]{7}\b|\bconst\s+\w+\s+EMPTY_")
    offenders = [f"{p.name}:{n}: {line.strip()}" for p in sorted(SHADER_DIR.glob("*.glsl"))
                 for n, line in enumerate(p.read_text().splitlines(), 1)
                 if literal.search(line.split("//")[0])]
    assert offenders == []
    src = stage_sources("fill_u32")["COMPUTE_SHADER"]
    for name, value in abi.BINDINGS.items():
        assert f"#define {name} {value}\n" in src
    assert len(set(abi.BINDINGS.values())) == len(abi.BINDINGS), "binding points must be unique per role"


def test_runtime_reads_gpu_buffers_through_staging():
    """A buffer that the CPU reads back directly moves to host memory on NVIDIA's driver, and every
    pass that uses it afterwards slows down (dmrt.gl.kernels.Staging; met in sessions 8 and 28, and
    found by reading in the viewer's depth_at). DMRT's runtime and the DMT baseline read their buffers through a
    Staging copy: the only direct reads are of records in persistently mapped memory, made for
    reading (dmrt.gl.mapped: the status records, DMT's draw statistics)."""
    from pathlib import Path

    import baselines.dmt
    import dmrt.runtime

    direct = re.compile(r"[\w\])]\.read\(")
    allowed = re.compile(r"(staging|self\.status|self\.record\(back\)|self\._records\[[^\]]*\]|self\._stats_host|self)"
                         r"\.read\(")
    sources = [p for m in (dmrt.runtime, baselines.dmt) for p in sorted(Path(m.__file__).parent.glob("*.py"))]
    offenders = [f"{p.name}:{n}: {line.strip()}" for p in sources
                 for n, line in enumerate(p.read_text().splitlines(), 1)
                 if direct.search(line.split("#")[0]) and not allowed.search(line.split("#")[0])]
    assert offenders == []
