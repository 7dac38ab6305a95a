#!/usr/bin/env bash
# The view-dependent photo choice's frame cost on the `paper` preset, for a rented GPU machine:
# start it detached and poll it with bench/poll_run.sh OUT_DIR (see bench/frame_run.sh).
#
#   setsid nohup bench/choice_run.sh /tmp/choice >/dev/null 2>&1 </dev/null &
#
# Steps: the paper scene (32M points with the scan's normals, 192 photos 1024x684) generated and
# preprocessed (bench.bench_render --preset), then the default 5-layer frame with the fixed labels
# and with RenderConfig(photo_choice="view") in the same run, sustained walkthroughs at 1280x720 and
# 3840x2160. The environment (EGL vendor file, PYTHONPATH with the wheels, DMRT_COMMIT) is the
# caller's: see ../shared/GPU.md.
set -u
out=${1:?usage: bench/choice_run.sh OUT_DIR}
mkdir -p "$out/results"
rm -f "$out/done.txt"
nvidia-smi --query-gpu=name,clocks.sm,clocks.max.sm,memory.total --format=csv >"$out/results/gpus.csv" 2>&1
t0=$(date +%s)
python3 -m bench.bench_render --preset paper --write-normals --work "$out/work" --out "$out/results" --layers 5 \
    --methods tiles --sizes ${SIZES:-1280x720 3840x2160} --frames 30 --no-leveling --photo-choice labels view \
    2>&1 | tr '\r' '\n' | grep -v 'frame/s' >>"$out/log.txt"
echo "render rc=${PIPESTATUS[0]} $(( $(date +%s) - t0 )) s" >>"$out/done.txt"
tar czf "$out/results.tgz" -C "$out" results log.txt
echo finished >>"$out/done.txt"
