#!/usr/bin/env bash
# Preprocessing at thousands of photos (issue #39): the `many` preset (2 x 64 rooms, 10,240 photos
# of 1024x684, 32M points with the scan's normals) generated and preprocessed on one GPU machine
# by bench.bench_preprocess, with /usr/bin/time -v and a sampler of disk, memory and load every 5 s
# (results/samples.tsv). The scene and the bundle stay in WORK for the runtime benchmarks
# (python3 -m bench.bench_render --bundle WORK/bundle ...). For a rented machine whose commands are
# time-limited: start it detached, then poll it from the next commands.
#
#   setsid nohup bench/many_run.sh /tmp/many >/dev/null 2>&1 </dev/null &
#   bench/poll_run.sh /tmp/many 540       # "preprocess rc=STATUS SECONDS s", then "finished"
#
# Extra arguments go to bench.bench_preprocess (e.g. --photo-size 512 342: a quarter of the
# generation's time). Results: OUT_DIR/results/preprocess-many.json (seconds, CPU seconds and peak
# memory per phase, counts.photos, the depth maps' splats and culled fraction), bundle.json,
# time_v.txt, samples.tsv; packed into OUT_DIR/results.tgz. The environment (EGL vendor file,
# PYTHONPATH with the wheels, DMRT_COMMIT) is the caller's: see ../shared/GPU.md.
set -u
out=${1:?usage: bench/many_run.sh OUT_DIR [bench.bench_preprocess ARGS ...]}
shift
work=${WORK:-$out/work}
mkdir -p "$out/results"
rm -f "$out/done.txt"  # a record left by an earlier run on a warm machine would end bench/poll_run.sh at once
"$(dirname "$0")/samples.sh" "$out" &  # gpus.csv, df_before.txt, samples.tsv
sampler=$!
t0=$(date +%s)
/usr/bin/time -v -o "$out/results/time_v.txt" python3 -m bench.bench_preprocess --preset many --write-normals \
    --workers "$(nproc)" --memory-limit-mb 16000 --keep --work "$work" --out "$out/results" "$@" >>"$out/log.txt" 2>&1
echo "preprocess rc=$? $(( $(date +%s) - t0 )) s" >>"$out/done.txt"
cp "$work/bundle/bundle.json" "$out/results/bundle.json" 2>/dev/null
df -h "$out" >"$out/results/df_after.txt" 2>&1
kill $sampler
tar czf "$out/results.tgz" -C "$out" results log.txt
echo finished >>"$out/done.txt"
