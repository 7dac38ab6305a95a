#!/usr/bin/env bash
# The default path's per-stage frame times of several source trees on one `paper` bundle, in one run
# on a rented GPU machine: within a run the trees share the machine and its clocks, which makes
# differences of a few per cent visible (between runs they are not: see reports/frame-h200).
#
#   bench/ab_trees.sh .ab HEAD~1:base HEAD:new      # trees of revisions (plus edits of your own)
#   setsid nohup bench/ab_run.sh /tmp/ab .ab/base .ab/new >/dev/null 2>&1 </dev/null &
#   bench/poll_run.sh /tmp/ab 540                  # in the next commands, back to back
#   python -m bench.ab_table OUT/results           # after unpacking results.tgz here
#
# Steps: the bench workspace's main bundle (scene and preprocessing, ~3 minutes on an H100; or
# BUNDLE=path to use one), then for each tree, in order, `bench.bench_render` with the tree's own
# code (5 layers, no leveling, tiles, 1280x720 and 3840x2160; SIZES, FRAMES override; PASSES=1: the
# tile lists timed pass by pass, `--passes`, for trees that have it), its results
# in OUT_DIR/results/<tree name>/ and OUT_DIR/results.tgz repacked after each tree; with SWEEP="T:B:K ..."
# also each tree's tile raster alone per setting and size (`bench.bench_visibility --tile-sweep`, in
# OUT_DIR/results/<tree name>/sweep-<width>/: ~10 s a setting). Trees need
# dmrt/, shaders/ and bench/; reference/ and baselines/ come from this checkout.
# The environment (EGL vendor file, PYTHONPATH with the wheels) is the caller's: ../shared/GPU.md.
set -u
out=${1:?usage: bench/ab_run.sh OUT_DIR TREE_DIR...}
mkdir -p "$out" && out=$(cd "$out" && pwd)  # absolute: the trees run from their own folders
shift
[ $# -gt 0 ] || { echo "ab_run: no tree given" >&2; exit 2; }
for t in "$@"; do
    [ -d "$t/dmrt" ] && [ -d "$t/shaders" ] && [ -d "$t/bench" ] || { echo "ab_run: $t: not a source tree (dmrt/, shaders/, bench/)" >&2; exit 2; }
done
repo=$(cd "$(dirname "$0")/.." && pwd)
mkdir -p "$out/results"
rm -f "$out/done.txt"  # a record left by an earlier run on a warm machine would end bench/poll_run.sh at once
log=$out/log.txt
t0=$(date +%s)
nvidia-smi --query-gpu=name,clocks.sm,clocks.max.sm,memory.total --format=csv >"$out/results/gpus.csv" 2>&1
bundle=${BUNDLE:-$(cd "$repo" && python3 -m bench.workspace paper "$out/work" 2>>"$log" | tail -n 1)}
echo "bundle ${bundle:-none} $(( $(date +%s) - t0 )) s" >>"$out/done.txt"
[ -d "$bundle" ] || { echo "failed: no bundle (see log.txt)" >>"$out/done.txt"; echo finished >>"$out/done.txt"; exit 1; }
for t in "$@"; do
    name=$(basename "$t")
    (cd "$t" && PYTHONPATH="$PWD:$repo:${PYTHONPATH:-}" DMRT_COMMIT=$(cat COMMIT 2>/dev/null || echo "$name") \
        python3 -m bench.bench_render --bundle "$bundle" --out "$out/results/$name" --layers 5 --no-leveling \
        --methods tiles --sizes ${SIZES:-1280x720 3840x2160} --frames ${FRAMES:-30} ${PASSES:+--passes}) >>"$log" 2>&1
    echo "$name rc=$? $(( $(date +%s) - t0 )) s" >>"$out/done.txt"
    for size in ${SWEEP:+${SIZES:-1280x720 3840x2160}}; do
        (cd "$t" && PYTHONPATH="$PWD:$repo:${PYTHONPATH:-}" python3 -m bench.bench_visibility --bundle "$bundle" \
            --out "$out/results/$name/sweep-${size%x*}" --layers 5 --width "${size%x*}" --height "${size#*x}" \
            --no-paths --tile-sweep $SWEEP) >>"$log" 2>&1
        echo "$name sweep $size rc=$? $(( $(date +%s) - t0 )) s" >>"$out/done.txt"
    done
    tar czf "$out/results.tgz.tmp" -C "$out" results && mv "$out/results.tgz.tmp" "$out/results.tgz"
done
echo finished >>"$out/done.txt"
