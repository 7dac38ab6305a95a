#!/usr/bin/env bash
# Long tile lists split over workgroups (RenderConfig.tile_split, issue #39), for a rented GPU
# machine: start it detached and poll it with bench/poll_run.sh OUT_DIR.
#
#   setsid nohup bench/split_run.sh /tmp/split >/dev/null 2>&1 </dev/null &
#
# A small `many` scene (3M points, 1280 photos of 256x171: the block's rooms and streets, the same
# views along it) generated and preprocessed on every core, then walked through by bench.bench_render
# over its first 120 photos, 5 layers, 1280x720 and 3840x2160, with every list walked by its own tile's
# workgroup (--tile-split 0) and with long ones split (the default), in one run. Its frames that look
# along the block pile distant discs into a few tiles (tile_lists_per_frame.longest: thousands of
# discs), the case the split is for (reports/many-photos); then the same at 1280x720 with every timed
# section fenced (results/fenced/). Steps append "NAME rc=STATUS SECONDS s" to OUT_DIR/done.txt;
# results (preprocess-many.json, render-bundle-walk120.json, fenced/render-bundle-walk120.json) in
# OUT_DIR/results.tgz. The environment (EGL vendor file, PYTHONPATH with the wheels, DMRT_COMMIT) is
# the caller's: see ../shared/GPU.md.
set -u
out=${1:?usage: bench/split_run.sh OUT_DIR}
mkdir -p "$out/results"
rm -f "$out/done.txt"
pack() { tar czf "$out/results.tgz.tmp" -C "$out" results log.txt && mv "$out/results.tgz.tmp" "$out/results.tgz"; }
t0=$(date +%s)
python3 -m bench.bench_preprocess --preset many --points 3000000 --photos 1280 --photo-size 256 171 --write-normals \
    --workers "$(nproc)" --keep --work "$out/work" --out "$out/results" 2>&1 | tr '\r' '\n' | grep -v '/s]' >>"$out/log.txt"
echo "preprocess rc=${PIPESTATUS[0]} $(( $(date +%s) - t0 )) s" >>"$out/done.txt"
pack
t0=$(date +%s)
python3 -m bench.bench_render --bundle "$out/work/bundle" --out "$out/results" --layers 5 --methods tiles \
    --sizes 1280x720 3840x2160 --frames 30 --no-leveling --photo-choice view --map-cache-mb 0 --walk-photos 120 \
    --tile-split 0 "$(python3 -c 'from dmrt.runtime.tiles import SPLIT_MIN; print(SPLIT_MIN)')" \
    2>&1 | tr '\r' '\n' | grep -v 'frame/s' >>"$out/log.txt"
echo "render rc=${PIPESTATUS[0]} $(( $(date +%s) - t0 )) s" >>"$out/done.txt"
pack
# the same at 1280x720 with every timed section fenced (glFinish around each): which pass a split
# frame's time goes to (unfenced, a section that waits for the pass before it is charged with it)
t0=$(date +%s)
mkdir -p "$out/results/fenced"
python3 -m bench.bench_render --bundle "$out/work/bundle" --out "$out/results/fenced" --layers 5 --methods tiles \
    --sizes 1280x720 --frames 30 --no-leveling --photo-choice view --map-cache-mb 0 --walk-photos 120 --fenced \
    --tile-split 0 "$(python3 -c 'from dmrt.runtime.tiles import SPLIT_MIN; print(SPLIT_MIN)')" \
    2>&1 | tr '\r' '\n' | grep -v 'frame/s' >>"$out/log.txt"
echo "render fenced rc=${PIPESTATUS[0]} $(( $(date +%s) - t0 )) s" >>"$out/done.txt"
pack
echo finished >>"$out/done.txt"
