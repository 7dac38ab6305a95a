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
#    first 960 photos along the block (about 12 rooms: the paper preset's walking speed), with the
#    default photo cache (sized from the GPU's memory; session 29 compared 1 and 3 GiB) and the CPU
#    profiled (render-bundle-walk960.json), then over all
#    10,240 (the whole block in 30 frames: every frame needs new maps; render-bundle.json).
#    MANY_WALKS (default "960 0") picks those walks: "960" skips the whole block (~4 minutes).
# 3. with SCENES="paper-many" (default "many"; "many paper-many" runs both, ~37 minutes): the paper
#    preset's geometry with 10,240 photos (PAPER_MANY_PHOTOS) made by the OpenGL photographer and
#    preprocessed as many_run.sh does, then walked along the paper step's key cameras
#    (--keys paper-keys.json): the same views with 53x the photos, so the ratio of the two frames
#    is the photo count's alone (many's also holds its longer block's).
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
    --save-keys "$out/results/paper-keys.json" "${render[@]}" --map-cache-mb ${PAPER_CACHE_MB:-0 520} 2>&1 | tr '\r' '\n' | grep -v 'frame/s' >>"$out/log.txt"
echo "paper rc=${PIPESTATUS[0]} $(( $(date +%s) - t0 )) s" >>"$out/done.txt"
pack
rm -rf "$out/paper"  # the disk holds one scene at a time (many: ~40 GB)
for scene in ${SCENES:-many}; do
case $scene in
paper-many)
    t0=$(date +%s)
    bench/many_run.sh "$out/paper-many" --preset paper --photos "${PAPER_MANY_PHOTOS:-10240}" --photographer auto \
        >>"$out/log.txt" 2>&1
    echo "paper-many preprocess rc=$? $(( $(date +%s) - t0 )) s" >>"$out/done.txt"
    mkdir -p "$out/results/paper-many" && tar xzf "$out/paper-many/results.tgz" -C "$out/results/paper-many" 2>/dev/null
    pack
    t0=$(date +%s)
    python3 -m bench.bench_render --bundle "$out/paper-many/work/bundle" --out "$out/results" "${render[@]}" \
        --map-cache-mb 0 --keys "$out/results/paper-keys.json" 2>&1 | tr '\r' '\n' | grep -v 'frame/s' >>"$out/log.txt"
    echo "paper-many render rc=${PIPESTATUS[0]} $(( $(date +%s) - t0 )) s" >>"$out/done.txt"
    pack
    rm -rf "$out/paper-many/work"
    ;;
many)
t0=$(date +%s)
bench/many_run.sh "$out/many" >>"$out/log.txt" 2>&1
echo "many preprocess rc=$? $(( $(date +%s) - t0 )) s" >>"$out/done.txt"
mkdir -p "$out/results/many" && tar xzf "$out/many/results.tgz" -C "$out/results/many" 2>/dev/null
pack
# the paper's walking speed (12 of its 128 rooms), the CPU profiled; then the whole block in 30 frames
for walk in ${MANY_WALKS:-960 0}; do
    extra=(); [ $walk = 960 ] && extra=(--cpu-profile)
    t0=$(date +%s)
    python3 -m bench.bench_render --bundle "$out/many/work/bundle" --out "$out/results" "${render[@]}" --map-cache-mb 0 \
        --walk-photos $walk "${extra[@]}" 2>&1 | tr '\r' '\n' | grep -v 'frame/s' >>"$out/log.txt"
    echo "many render walk=$walk rc=${PIPESTATUS[0]} $(( $(date +%s) - t0 )) s" >>"$out/done.txt"
    pack
done
rm -rf "$out/many/work"
;;
esac
done
echo finished >>"$out/done.txt"
