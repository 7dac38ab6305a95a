"""The label histogram pass alone (``shaders/dmrt_label_histogram.glsl``) on synthetic ``Hit`` records.

Inside a walkthrough frame the pass's timer section once read far more than the pass's bytes (1.26
ms at 3840x2160 on an H200, where 265 MB of records take ~0.07 ms): the counts buffer, read back
every frame, lived in host memory (see dmrt/runtime/shading.py). This measures the shader alone,
with warm clocks, its counts buffer read once per case: label layouts (blocks of one label, one
label everywhere, random labels, no labels) times column lengths per thread. Each result is checked
against ``numpy.bincount``.

    python -m bench.bench_histogram [--size 3840x2160] [--repeats 30]
"""

from __future__ import annotations

import argparse

import numpy as np


def label_layouts(w: int, h: int, n_photos: int) -> dict[str, np.ndarray]:
    """``{name: (h, w) int labels}``; -1 = no surface."""
    yy, xx = np.mgrid[0:h, 0:w]
    return {"blocky": ((yy // 90) * 7 + (xx // 120) * 3) % n_photos,
            "uniform": np.zeros((h, w), np.int64),
            "random": np.random.default_rng(0).integers(0, n_photos, (h, w)),
            "empty": np.full((h, w), -1)}


def main(argv=None) -> None:
    from dmrt.gl import GpuTimer, abi, get_context, load_program
    from dmrt.gl.kernels import fill_u32, groups
    from dmrt.gl.shaders import set_uniforms

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", default="3840x2160", help="frame WxH")
    p.add_argument("--photos", type=int, default=192, help="labels (histogram bins)")
    p.add_argument("--repeats", type=int, default=30, help="timed dispatches per case (after 300 untimed)")
    args = p.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))

    ctx = get_context()
    timer = GpuTimer(ctx)
    counts = ctx.buffer(reserve=4 * args.photos)
    print(f"{ctx.info['GL_RENDERER']}, {w}x{h}, {args.photos} labels")
    for name, labels in label_layouts(w, h, args.photos).items():
        records = np.zeros(w * h, abi.HIT_DTYPE)
        records["final_label"] = labels.ravel()
        hits = ctx.buffer(records.tobytes())
        truth = np.bincount(labels[labels >= 0].ravel(), minlength=args.photos)
        for column in (16, 64, 256):
            prog = load_program(ctx, "dmrt_label_histogram", {"PIXELS_PER_THREAD": column})
            hits.bind_to_storage_buffer(abi.B_HITS)
            counts.bind_to_storage_buffer(abi.B_COUNTS)
            set_uniforms(prog, u_size=(w, h))
            grid = (groups(w, 64), groups(h, column))
            for _ in range(300):  # the clocks up
                prog.run(*grid)
            ms = []
            for _ in range(args.repeats):
                fill_u32(ctx, counts, 0, args.photos)
                ctx.memory_barrier()
                timer.reset()
                with timer.section("histogram"):
                    prog.run(*grid)
                    ctx.memory_barrier()
                ms.append(timer.ms["histogram"])
            correct = np.array_equal(np.frombuffer(counts.read(), np.uint32), truth)
            print(f"{name:8s} column {column:4d}: median {np.median(ms):.3f} ms, min {np.min(ms):.3f} ms, "
                  f"{records.nbytes / 1e6 / np.median(ms):.0f} GB/s of records, counts {'equal' if correct else 'DIFFER'} "
                  "to numpy", flush=True)
        hits.release()


if __name__ == "__main__":
    main()
