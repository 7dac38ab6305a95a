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
# 3. SCENES (default "many") lists the scenes after the paper step, in order: "many" (step 2), and
#    PRESET-N (e.g. many-1280, paper-2560): that preset's geometry with N photos, made by the OpenGL
#    photographer and preprocessed as many_run.sh does, then walked along the key cameras of
#    PRESET's own walk in this run (--keys: many's 960-photo walk, or the paper step's; so list it
#    after "many"). The same views with other photo counts: their frames' ratio is the photo
#    count's alone, where many's against paper's also holds the longer block's. many-1280 took
#    3 minutes (session 30: 124 s made and preprocessed, 56 s walked; the whole run with
#    MANY_WALKS=960 20 minutes); photo-dense rooms grow the candidates, labeling and photometric
#    phases (paper-10240 is 850 photos a room).
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
*-*)
    preset=${scene%-*} photos=${scene##*-}
    if [ ! -f "$out/results/$preset-keys.json" ]; then  # before minutes of preprocessing
        echo "$scene: no $preset walk's keys in this run (list $preset first; many: MANY_WALKS with 960) rc=2" >>"$out/done.txt"
        continue
    fi
    t0=$(date +%s)
    bench/many_run.sh "$out/$scene" --preset "$preset" --photos "$photos" --photographer auto >>"$out/log.txt" 2>&1
    echo "$scene preprocess rc=$? $(( $(date +%s) - t0 )) s" >>"$out/done.txt"
    mkdir -p "$out/results/$scene" && tar xzf "$out/$scene/results.tgz" -C "$out/results/$scene" 2>/dev/null
    pack
    t0=$(date +%s)
    python3 -m bench.bench_render --bundle "$out/$scene/work/bundle" --out "$out/results/$scene" "${render[@]}" \
        --map-cache-mb 0 --keys "$out/results/$preset-keys.json" 2>&1 | tr '\r' '\n' | grep -v 'frame/s' >>"$out/log.txt"
    echo "$scene render rc=${PIPESTATUS[0]} $(( $(date +%s) - t0 )) s" >>"$out/done.txt"
    pack
    rm -rf "$out/$scene/work"
    ;;
many)
t0=$(date +%s)
bench/many_run.sh "$out/many" >>"$out/log.txt" 2>&1
echo "many preprocess rc=$? $(( $(date +%s) - t0 )) s" >>"$out/done.txt"
mkdir -p "$out/results/many" && tar xzf "$out/many/results.tgz" -C "$out/results/many" 2>/dev/null
pack
# the paper's walking speed (12 of its 128 rooms), the CPU profiled; then the whole block in 30 frames
for walk in ${MANY_WALKS:-960 0}; do
    extra=(); [ $walk = 960 ] && extra=(--cpu-profile --save-keys "$out/results/many-keys.json")
    t0=$(date +%s)
    python3 -m bench.bench_render --bundle "$out/many/work/bundle" --out "$out/results" "${render[@]}" --map-cache-mb 0 \
        --walk-photos $walk "${extra[@]}" 2>&1 | tr '\r' '\n' | grep -v 'frame/s' >>"$out/log.txt"
    echo "many render walk=$walk rc=${PIPESTATUS[0]} $(( $(date +%s) - t0 )) s" >>"$out/done.txt"
    pack
done
rm -rf "$out/many/work"
;;
*) echo "$scene: unknown scene (many or PRESET-N) rc=2" >>"$out/done.txt" ;;
esac
done
echo finished >>"$out/done.txt"
