#!/usr/bin/env bash
# Depth maps of the `paper-full` scene (683M points, 192 photos) on every GPU of one machine
# (bench/bench_depth_gpus.py), for a rented machine whose commands are time-limited: the scene
# generated, phases 1-2 once, phase 3 timed in-process / Dask on 1 GPU / Dask on all GPUs, with
# nvidia-smi sampled every second (results/gpu_samples.csv: which GPUs each way kept busy).
#
#   setsid nohup bench/depth_gpus_run.sh /tmp/dg [BENCH OPTION ...] >/dev/null 2>&1 </dev/null &
#   bench/poll_run.sh /tmp/dg 540            # from the next commands, back to back
#
# PRESET=tiny (any synthetic preset) tries the script on a small scene. The result is
# OUT_DIR/results/depth-gpus.json (in results.tgz with the log and the samples).
# The environment (EGL vendor file, PYTHONPATH with the wheels, DMRT_COMMIT for a tree without git
# history) is the caller's: see ../shared/GPU.md.
set -u
out=${1:?usage: bench/depth_gpus_run.sh OUT_DIR [BENCH OPTION ...]}
shift
mkdir -p "$out/results"
rm -f "$out/done.txt"  # a record left by an earlier run on a warm machine would end bench/poll_run.sh at once
nvidia-smi --query-gpu=timestamp,index,memory.used,utilization.gpu,clocks.sm --format=csv,noheader -l 1 \
    >"$out/results/gpu_samples.csv" 2>&1 &
sampler=$!
step() {  # NAME COMMAND...: the command's output to the log, its status and seconds to done.txt
    local name=$1 t0
    shift
    t0=$(date +%s)
    echo "== $name $(date +%s)" >>"$out/log.txt"
    "$@" >>"$out/log.txt" 2>&1
    echo "$name rc=$? $(( $(date +%s) - t0 )) s" >>"$out/done.txt"
}
step synth python3 -m dmrt.app.cli scene synth --preset "${PRESET:-paper-full}" --write-normals --quiet --out "$out/scene"
step bench python3 -m bench.bench_depth_gpus "$out/scene" --out "$out/results/depth-gpus.json" \
    --memory-limit-mb 64000 --resident-mb 40000 --work "$out/work" "$@"
kill "$sampler" 2>/dev/null
tar czf "$out/results.tgz" -C "$out" results log.txt
echo finished >>"$out/done.txt"
