#!/usr/bin/env bash
# Table 1 at the paper's Scene 3 size (bench preset `paper-scene3`: 1,092M points, 161 photos of
# 1024x684): the scene generated and preprocessed end to end on one GPU machine (16 cores, 128 GB,
# a 64 GB disk), with /usr/bin/time -v and a sampler of disk, memory and load every 5 s. The disk
# estimate (bench/scenes/disk.py, docs/scene3.md) is checked first: a disk that cannot hold the
# run's peak ends it at once ("disk rc=2" in done.txt, the reason in log.txt). For a rented machine
# whose commands are time-limited: start it detached, poll done.txt.
#
#   setsid nohup bench/scene3_run.sh /tmp/scene3 >/dev/null 2>&1 </dev/null &
#   bench/poll_run.sh /tmp/scene3 540    # "disk rc=0", "table1 rc=STATUS SECONDS s", then "finished"
#
# PRESET (default paper-scene3) picks another bench preset: PRESET=paper-scene3-mini runs the same
# layout at 1/2000 of the points on a CPU (Mesa) in about a minute. Results, packed into
# OUT_DIR/results.tgz, JSON only: <machine>/<commit>-<preset>/table1.json (counts.points,
# preprocess_total_s, seconds, CPU seconds and peak memory per phase), bundle.json, and disk.json
# (the estimate beside the disk the sampler saw used above the start: measured_peak_bytes). The
# environment (EGL vendor file, PYTHONPATH with the wheels, DMRT_COMMIT) is the caller's: see
# ../shared/GPU.md.
set -u
out=${1:?usage: bench/scene3_run.sh OUT_DIR}
preset=${PRESET:-paper-scene3}
here=$(dirname "$0")
mkdir -p "$out/results"
rm -f "$out/done.txt"  # a record left by an earlier run on a warm machine would end bench/poll_run.sh at once
"$here/samples.sh" "$out" &  # gpus.csv, df_before.txt, samples.tsv
sampler=$!
python3 -m bench.workspace "$preset" "$out/work" --dry-run --json "$out/results/disk.json" >>"$out/log.txt" 2>&1
rc=$?
echo "disk rc=$rc" >>"$out/done.txt"
if [ $rc -eq 0 ]; then
    t0=$(date +%s)
    /usr/bin/time -v -o "$out/results/time_v.txt" python3 -m dmrt.app.cli bench --preset "$preset" \
        --out "$out/results" --work "$out/work" --only table1 >>"$out/log.txt" 2>&1
    echo "table1 rc=$? $(( $(date +%s) - t0 )) s" >>"$out/done.txt"
    cp "$out"/work/bundle-base/bundle.json "$out/results/bundle.json" 2>/dev/null
fi
kill $sampler
# the disk used above the start at its sampled peak, beside the estimate
python3 - "$out/results" <<'EOF' >>"$out/log.txt" 2>&1
import json, sys
from pathlib import Path

res = Path(sys.argv[1])
rows = [line.split("\t") for line in (res / "samples.tsv").read_text().splitlines()[1:] if line.count("\t") == 3]
used = [int(r[1]) * 2 ** 20 for r in rows if r[1].isdigit()]  # df -B1M: MiB
disk = json.loads((res / "disk.json").read_text()) if (res / "disk.json").is_file() else {}
disk["measured_peak_bytes"] = max(used) - used[0] if used else None
disk["sample_seconds"] = 5
(res / "disk.json").write_text(json.dumps(disk, indent=1))
EOF
(cd "$out" && find results \( -name '*.json' -o -name '*.txt' -o -name '*.tsv' \) -print0 | tar czf results.tgz --null -T -)
echo finished >>"$out/done.txt"
