#!/usr/bin/env bash
# For the GPU-machine runs (scale_run.sh, many_run.sh): the GPUs and the disk before the run
# (OUT_DIR/results/gpus.csv, df_before.txt), then the disk used, memory used and load every 5 s
# into OUT_DIR/results/samples.tsv until killed:
#
#   bench/samples.sh OUT_DIR & sampler=$!   ...   kill $sampler
set -u
out=${1:?usage: bench/samples.sh OUT_DIR}
mkdir -p "$out/results"
nvidia-smi --query-gpu=name,clocks.sm,clocks.max.sm,memory.total --format=csv >"$out/results/gpus.csv" 2>&1
df -h "$out" >"$out/results/df_before.txt" 2>&1
echo -e "unix_s\tdisk_used_mb\tmem_used_mb\tload_1min" >"$out/results/samples.tsv"
while true; do
    echo -e "$(date +%s)\t$(df -B1M --output=used "$out" | tail -1 | tr -d ' ')\t$(free -m | awk '/Mem:/{print $3}')\t$(cut -d' ' -f1 /proc/loadavg)"
    sleep 5
done >>"$out/results/samples.tsv"
