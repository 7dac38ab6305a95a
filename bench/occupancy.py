"""Benchmark: how many warps of each compute program of the frame an SM holds at once, measured.

    python -m bench.occupancy --bundle BUNDLE --out RESULTS_DIR [--size 3840x2160]
    python -m bench.occupancy --bundle B --out R --variant dmrt_tiles_raster:TOP=8,BATCH=256

A renderer with the default configuration renders one frame at ``--size``, which loads the
programs the frame uses with the defines it uses (:func:`dmrt.gl.shaders.recording_programs`).
Each compute program is then compiled once more as a probe: its ``main`` renamed and called only
under a uniform that is never set, so that the driver gives the program the registers and shared
memory it gives the shipping one, and a new ``main`` in which the first invocation of each warp
adds 1 to its SM's counter (``gl_SMIDNV``), spins ~50 us, and subtracts 1 again. Every SM fills
up to the limit that registers and shared memory set before the first workgroups leave, so the
largest count seen is the program's resident warps per SM (H200: 64 at most). GL gives no other view of it: NVIDIA's
program binary holds the assembly before register allocation, and no profiler reaches GL compute
programs here. ``--variant PROGRAM:KEY=VALUE,...`` adds the program built with other defines.

Resident warps decide how much latency a pass can hide; they explained the steps in the tile
raster's batch and kept-hits sweeps (reports/frame-h200, session 21). Without
``GL_NV_shader_thread_group`` (Mesa) every warp counts on one counter: the figure is then only a
check that each probe compiles and runs. One JSON ``occupancy-<size>.json``.
"""

from __future__ import annotations

import argparse
import json
import re

import numpy as np

PROBE_BINDING = 63  # a storage binding no program of the frame uses (dmrt/gl/abi.py stays below it)

PROBE_HEAD = """#extension GL_NV_shader_thread_group : enable
"""

PROBE_MAIN = """
layout(std430, binding = PROBE_BINDING) buffer ProbeBuffer {
    uint probe_peak;        // the most warps seen at once on one SM
    uint probe_group;       // invocations a workgroup
    uint probe_sink;        // keeps the spin from being optimised away
    uint probe_live[];      // warps now running, per SM
};
uniform int u_probe_never;  // never set: the shipping main is compiled, never run
void main() {
    bool lead = (gl_LocalInvocationIndex & 31u) == 0u;
#ifdef GL_NV_shader_thread_group
    uint sm = gl_SMIDNV;
#else
    uint sm = 0u;
#endif
    if (lead) atomicMax(probe_peak, atomicAdd(probe_live[sm], 1u) + 1u);
    if (gl_LocalInvocationIndex == 0u) probe_group = gl_WorkGroupSize.x * gl_WorkGroupSize.y * gl_WorkGroupSize.z;
    uint x = gl_LocalInvocationIndex;
    for (int i = 0; i < PROBE_SPIN; ++i) x = x * 1664525u + 1013904223u;
    if (x == 7u) probe_sink = x;
    if (lead) atomicAdd(probe_live[sm], ~0u);
    if (u_probe_never != 0) probe_main();
}
"""

_MAIN = re.compile(r"\bvoid\s+main\s*\(\s*\)")


def probe_source(source: str, spin: int) -> str:
    """The probe of a compute program: ``source`` (a complete stage source, ``#version`` first) with
    its ``main`` renamed ``probe_main`` and :data:`PROBE_MAIN` appended."""
    version, _, body = source.partition("\n")
    body, n = _MAIN.subn("void probe_main()", body)
    if n == 0:
        raise ValueError("no 'void main()' in the program")
    defines = f"#define PROBE_BINDING {PROBE_BINDING}\n#define PROBE_SPIN {int(spin)}\n"
    return version + "\n" + PROBE_HEAD + defines + body + PROBE_MAIN


def resident_warps(ctx, name: str, defines: dict, spin: int = 30000, groups: int = 4096) -> dict:
    """Run the probe of program ``name`` built with ``defines``: ``warps_per_sm`` (the peak) and
    ``workgroup`` (invocations a workgroup), ``workgroups_per_sm`` when that divides."""
    from dmrt.gl.shaders import stage_sources

    program = ctx.compute_shader(probe_source(stage_sources(name, defines)["COMPUTE_SHADER"], spin))
    buf = ctx.buffer(np.zeros(3 + 4096, np.uint32).tobytes())
    try:
        buf.bind_to_storage_buffer(PROBE_BINDING)
        program.run(groups, 1, 1)
        peak, group = (int(v) for v in np.frombuffer(buf.read(8), np.uint32))
    finally:
        buf.release()
        program.release()
    warps = max(1, -(-group // 32))
    return {"warps_per_sm": peak, "workgroup": group, "workgroups_per_sm": round(peak / warps, 2)}


def frame_programs(bundle, size: tuple[int, int]) -> list[tuple[str, dict]]:
    """The compute programs one default frame at ``size`` uses, with their defines."""
    from dmrt.gl.shaders import recording_programs, stage_sources
    from dmrt.runtime.renderer import RenderConfig, Renderer

    with recording_programs() as programs:
        r = Renderer(bundle, RenderConfig(async_photos=False))
        try:
            r.render(bundle.cameras[0].resized(*size))
        finally:
            r.release()
    seen, out = set(), []
    for name, defines in programs:
        key = (name, tuple(sorted(defines.items())))
        if key not in seen and "COMPUTE_SHADER" in stage_sources(name, defines):
            seen.add(key)
            out.append((name, defines))
    return out


def parse_variant(spec: str) -> tuple[str, dict]:
    """``PROGRAM:KEY=VALUE,...`` -> (program, {KEY: int VALUE})."""
    name, sep, rest = spec.partition(":")
    if not sep or not name:
        raise ValueError(f"{spec!r}: expected PROGRAM:KEY=VALUE,...")
    defines = {}
    for item in filter(None, rest.split(",")):
        key, eq, value = item.partition("=")
        if not eq:
            raise ValueError(f"{spec!r}: {item!r} is not KEY=VALUE")
        defines[key] = int(value)
    return name, defines


def main(argv=None) -> None:
    from bench.bench_render import add_source_args, open_bundle
    from dmrt.gl import get_context, renderer_info

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_source_args(p, "/tmp/dmrt-occupancy")
    p.add_argument("--size", default="3840x2160", help="frame size WxH whose programs are measured")
    p.add_argument("--variant", action="append", default=[], metavar="PROGRAM:KEY=VALUE,...",
                   help="also the program built with these defines changed (repeatable)")
    p.add_argument("--spin", type=int, default=30000, help="iterations each probe warp spins (~50 us on an H200)")
    p.add_argument("--groups", type=int, default=4096, help="workgroups a probe dispatch launches")
    args = p.parse_args(argv)
    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
        variants = [parse_variant(v) for v in args.variant]
    except ValueError as exc:
        p.error(f"--size / --variant: {exc}")
    args.write_normals = False
    ctx = get_context()
    bundle = open_bundle(p, args, {})
    programs = frame_programs(bundle, (w, h))

    def frame_defines(name: str) -> dict:  # the defines of the frame's first build of `name`
        return next((d for n, d in programs if n == name), {})

    rows = []
    for name, defines in programs + [(name, {**frame_defines(name), **changed}) for name, changed in variants]:
        row = {"program": name, "defines": defines, **resident_warps(ctx, name, defines, args.spin, args.groups)}
        rows.append(row)
        shown = ", ".join(f"{k}={v}" for k, v in defines.items())
        print(f"{row['warps_per_sm']:3d} warps/SM  {row['workgroups_per_sm']:6.2f} x {row['workgroup']:4d}  "
              f"{name}  {shown}", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / f"occupancy-{w}x{h}.json"
    path.write_text(json.dumps({"benchmark": "occupancy", "machine": renderer_info(ctx), "frame_size": [w, h],
                                "programs": rows}, indent=1))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
