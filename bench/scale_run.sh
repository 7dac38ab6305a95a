#!/usr/bin/env bash
# Table 1 at the paper's Scene 2 size (bench preset `paper-full`: 683M points, 192 photos of
# 1024x684): the scene generated and preprocessed end to end on one GPU machine, with
# /usr/bin/time -v and a sampler of disk, memory and load every 5 s (results/samples.tsv).
# For a rented machine whose commands are time-limited: start it detached, poll done.txt.
# PRESET=paper-full-scan takes the radii from the scanner's grid instead of kNN (issue #40).
#
#   setsid nohup bench/scale_run.sh /tmp/scale >/dev/null 2>&1 </dev/null &
#   cat /tmp/scale/done.txt      # "table1 rc=STATUS SECONDS s", then "finished"
#
# The environment (EGL vendor file, PYTHONPATH with the wheels, DMRT_COMMIT) is the caller's:
# see ../shared/GPU.md.
set -u
out=${1:?usage: bench/scale_run.sh OUT_DIR}
mkdir -p "$out/results"
rm -f "$out/done.txt"  # a record left by an earlier run on a warm machine would end bench/poll_run.sh at once
"$(dirname "$0")/samples.sh" "$out" &  # gpus.csv, df_before.txt, samples.tsv
sampler=$!
t0=$(date +%s)
/usr/bin/time -v -o "$out/results/time_v.txt" python3 -m dmrt.app.cli bench --preset "${PRESET:-paper-full}" \
    --out "$out/results" --work "$out/work" --only table1 >>"$out/log.txt" 2>&1
echo "table1 rc=$? $(( $(date +%s) - t0 )) s" >>"$out/done.txt"
cp "$out"/work/bundle-base/bundle.json "$out/results/bundle.json" 2>/dev/null
kill $sampler
tar czf "$out/results.tgz" -C "$out" results log.txt
echo finished >>"$out/done.txt"
