"""bench/occupancy.py: each compute program of a frame, built as the frame builds it, runs as a
probe (on Mesa the count is GPU-wide: it shows the probe compiles and counts, not an occupancy)."""

import pytest

from bench.occupancy import frame_programs, parse_variant, probe_source, resident_warps


def test_probe_source_renames_main():
    src = "#version 430\nlayout(local_size_x = 64) in;\nvoid main() { }\n"
    out = probe_source(src, spin=5)
    assert out.startswith("#version 430\n#extension GL_NV_shader_thread_group : enable\n")
    assert "void probe_main() { }" in out and out.count("void main()") == 1
    with pytest.raises(ValueError, match="main"):
        probe_source("#version 430\nvoid helper() { }\n", spin=5)


def test_parse_variant():
    assert parse_variant("dmrt_tiles_raster:TOP=8,BATCH=256") == ("dmrt_tiles_raster", {"TOP": 8, "BATCH": 256})
    with pytest.raises(ValueError):
        parse_variant("dmrt_tiles_raster")
    with pytest.raises(ValueError):
        parse_variant("dmrt_tiles_raster:TOP")


def test_every_frame_program_probes(ctx, tiny_bundle):
    from dmrt.io.bundle import read_bundle

    programs = frame_programs(read_bundle(tiny_bundle), (96, 64))
    names = {name for name, _ in programs}
    # the default frame's hot passes (tile lists, raster, labeling, search) are among them
    assert {"dmrt_tiles_bin", "dmrt_tiles_raster", "dmrt_tiles_labeling", "dmrt_raytrace"} <= names
    raster = next(d for n, d in programs if n == "dmrt_tiles_raster")
    assert raster["TOP"] == 12 and raster["BATCH"] == 288
    for name, defines in programs:
        row = resident_warps(ctx, name, defines, spin=4, groups=3)
        # at least one warp ran (the count rose); the workgroup size is the program's own
        assert row["warps_per_sm"] >= 1, name
        assert row["workgroup"] >= 1, name
    assert resident_warps(ctx, "dmrt_tiles_raster", raster, spin=4, groups=2)["workgroup"] == 16 * 16

