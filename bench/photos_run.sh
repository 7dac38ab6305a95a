#!/usr/bin/env bash
# The frame with thousands of photos (issue #39), for a rented GPU machine: start it detached and
# poll it with bench/poll_run.sh OUT_DIR.
#
#   setsid nohup bench/photos_run.sh /tmp/photos >/dev/null 2>&1 </dev/null &
#
# Steps, each appending "NAME rc=STATUS SECONDS s" to OUT_DIR/done.txt:
# 1. paper: the `paper` preset (192 photos) generated, preprocessed and walked through
#    (bench.bench_render, 5 layers, the default view choice, 1280x720 and 3840x2160), with every
#    depth map resident (--map-cache-mb 0) and with 185 of its 192 in a cache (520 MiB: the cache's
#    shader path on the same scene; PAPER_CACHE_MB="0" skips the second, measured once already);
# 2. many: the `many` preset (10,240 photos) generated and preprocessed by bench/many_run.sh
#    (phases, memory, disk), then walked through the same way (2048 of its maps resident): over the
#    first 960 photos along the block (about 12 rooms: the paper preset's walking speed), with a
#    1 GiB and a 3 GiB photo cache and the CPU profiled (render-bundle-walk960.json), then over all
#    10,240 (the whole block in 30 frames: every frame needs new maps; render-bundle.json).
#    MANY_WALKS (default "960 0") picks those walks: "960" skips the whole block (~4 minutes).
# The environment (EGL vendor file, PYTHONPATH with the wheels, DMRT_COMMIT) is the caller's: see
# ../shared/GPU.md. Results: OUT_DIR/results.tgz (render-paper.json, render-bundle.json,
# many/preprocess-many.json ...), repacked after each step.
set -u
out=${1:?usage: bench/photos_run.sh OUT_DIR}
mkdir -p "$out/results"
rm -f "$out/done.txt"
pack() { tar czf "$out/results.tgz.tmp" -C "$out" results log.txt && mv "$out/results.tgz.tmp" "$out/results.tgz"; }
render=(--layers 5 --methods tiles --sizes 1280x720 3840x2160 --frames 30 --no-leveling --photo-choice view)
t0=$(date +%s)
python3 -m bench.bench_render --preset paper --write-normals --work "$out/paper" --out "$out/results" \
    "${render[@]}" --map-cache-mb ${PAPER_CACHE_MB:-0 520} 2>&1 | tr '\r' '\n' | grep -v 'frame/s' >>"$out/log.txt"
echo "paper rc=${PIPESTATUS[0]} $(( $(date +%s) - t0 )) s" >>"$out/done.txt"
pack
rm -rf "$out/paper"  # the disk holds one scene at a time (many: ~40 GB)
t0=$(date +%s)
bench/many_run.sh "$out/many" >>"$out/log.txt" 2>&1
echo "many preprocess rc=$? $(( $(date +%s) - t0 )) s" >>"$out/done.txt"
mkdir -p "$out/results/many" && tar xzf "$out/many/results.tgz" -C "$out/results/many" 2>/dev/null
pack
# the paper's walking speed (12 of its 128 rooms) with the default photo cache (1 GiB: 383 photos, fewer
# than the walk wants) and one that holds the walk's 960 (3 GiB), the CPU profiled; then the whole
# block in 30 frames
for walk in ${MANY_WALKS:-960 0}; do
    extra=(); [ $walk = 960 ] && extra=(--cache-mb 1024 3072 --cpu-profile)
    t0=$(date +%s)
    python3 -m bench.bench_render --bundle "$out/many/work/bundle" --out "$out/results" "${render[@]}" --map-cache-mb 0 \
        --walk-photos $walk "${extra[@]}" 2>&1 | tr '\r' '\n' | grep -v 'frame/s' >>"$out/log.txt"
    echo "many render walk=$walk rc=${PIPESTATUS[0]} $(( $(date +%s) - t0 )) s" >>"$out/done.txt"
    pack
done
echo finished >>"$out/done.txt"
