#!/usr/bin/env bash
# Wait for a detached GPU-machine run (bench/frame_run.sh, bench/paper_run.sh) from the next
# command: until OUT_DIR/done.txt says `finished` or SECONDS have passed, then print its steps and
# the log's tail, and copy OUT_DIR/results.tgz into $OUT (the device tool's return folder) if set.
#
#   bench/poll_run.sh /tmp/frame 540
#
# Exit status 3 at once when OUT_DIR does not exist: the command runs on a fresh machine
# (the one with the run was given back between the commands) and waiting would only spend time.
set -u
dir=${1:?usage: bench/poll_run.sh OUT_DIR [SECONDS]}
if [ ! -d "$dir" ]; then
    echo "poll_run: no run in $dir on this machine (a fresh machine: start the run again)" >&2
    exit 3
fi
end=$(( $(date +%s) + ${2:-540} ))
while [ "$(date +%s)" -lt "$end" ] && ! grep -q '^finished' "$dir/done.txt" 2>/dev/null; do sleep 10; done
cat "$dir/done.txt" 2>/dev/null
tail -n 20 "$dir/log.txt" 2>/dev/null | cut -c1-400
if [ -n "${OUT:-}" ] && [ -f "$dir/results.tgz" ]; then cp "$dir/results.tgz" "$OUT/"; fi
