#!/usr/bin/env bash
# The frame pipeline and the preprocessing on the `paper` preset, for a rented GPU machine whose
# commands are time-limited: start it detached and collect OUT_DIR/results.tgz while it runs.
#
#   setsid nohup bench/frame_run.sh /tmp/frame >/dev/null 2>&1 </dev/null &
#   cat /tmp/frame/done.txt                 # one line per step: name, exit status, seconds
#   bench/poll_run.sh /tmp/frame 540        # in the next commands, back to back (see there)
#
# Steps: the paper scene (32M points with the scan's normals, 192 photos 1024x684); Table 2
# (`dmrt bench --only table2` on that scene: its preprocessing, once, in the bench's work folder,
# whose main bundle every later step uses; `dmrt report` builds reports/latest from
# OUT_DIR/results/bench); the default path's per-stage frame times at 1280x720 and 3840x2160 with 5
# layers (bench.bench_render: GPU-resident walkthroughs, median / p95, sustained, clocks; Table 2
# has the other paths beside it); at 3840x2160 the tile raster's time with other disc batches in shared
# memory, fewer nearest hits kept, warps of pixel rows and 8x8 tiles; the default path with the search's step capped at
# 32 and 16 (time and what the cap changes in the frames), with both list checks and a CPU profile
# of the issuing; the paper's bisection beside the default Illinois refinement; the visibility
# paths' agreement with compute peeling (bench.bench_visibility); with 2+ GPUs, the preprocessing
# again on a 2-worker Dask LocalCluster (one GPU each) for the depth maps' speed-up.
# The environment (EGL vendor file, PYTHONPATH with the wheels, DMRT_COMMIT) is the caller's:
# see ../shared/GPU.md.
set -u
out=${1:?usage: bench/frame_run.sh OUT_DIR}
work=${WORK:-$out/work}
mkdir -p "$out/results" "$work"
rm -f "$out/done.txt"  # a record left by an earlier run on a warm machine would end bench/poll_run.sh at once
step() {  # step NAME COMMAND...: run, log, record, repack
    local name=$1; shift
    local t0=$(date +%s)
    "$@" >>"$out/log.txt" 2>&1
    echo "$name rc=$? $(( $(date +%s) - t0 )) s" >>"$out/done.txt"
    tar czf "$out/results.tgz.tmp" -C "$out" results log.txt && mv "$out/results.tgz.tmp" "$out/results.tgz"
}
nvidia-smi --query-gpu=name,clocks.sm,clocks.max.sm,memory.total --format=csv >"$out/results/gpus.csv" 2>&1
step scene python3 -m dmrt.app.cli scene synth --preset paper --write-normals --out "$work/scene" --force --quiet
step table2 python3 -m dmrt.app.cli bench --preset paper --scene "$work/scene" --work "$work/bench" \
    --out "$out/results/bench" --only table2 --quiet
bundle=$(python3 -m bench.workspace paper "$work/bench" --scene "$work/scene" 2>>"$out/log.txt" | tail -n 1)
[ -d "$bundle" ] || bundle=$work/bench/bundle-L4  # the paper preset's main bundle
echo "bundle $bundle" >>"$out/done.txt"
cp "$bundle/bundle.json" "$out/results/bundle.json"
step render python3 -m bench.bench_render --bundle "$bundle" --out "$out/results" --layers 5 \
    --methods tiles --sizes 1280x720 3840x2160 --frames 30 --no-leveling
step tile_sweep_4k python3 -m bench.bench_visibility --bundle "$bundle" --out "$out/results/tiles-4k" --layers 5 \
    --width 3840 --height 2160 --no-paths --tile-sweep 16:288:12 16:288:12:r 16:384:16 16:512:16 16:256:8 16:192:12 8:256:12
step render_caps python3 -m bench.bench_render --bundle "$bundle" --out "$out/results/caps" --layers 5 \
    --methods tiles --tile-check frame lagged --max-steps 100 32 16 --sizes 1280x720 3840x2160 --frames 30 \
    --no-leveling --cpu-profile
step render_bisection python3 -m bench.bench_render --bundle "$bundle" --out "$out/results/bisection" \
    --layers 5 --methods tiles --refine bisection --sizes 1280x720 3840x2160 --frames 30 --no-leveling
step visibility python3 -m bench.bench_visibility --bundle "$bundle" --out "$out/results" --layers 5 \
    --slots 32 --max-thread-pixels 256
if [ "$(nvidia-smi -L 2>/dev/null | wc -l)" -ge 2 ]; then
    step preprocess_dask2 python3 -m dmrt.app.cli preprocess "$work/scene" --out "$work/bundle2" --force --quiet \
        --dask local:2
    cp "$work/bundle2/bundle.json" "$out/results/bundle_dask2.json" 2>/dev/null
    step repack true
fi
echo finished >>"$out/done.txt"
