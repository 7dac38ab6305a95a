#!/usr/bin/env bash
# The `paper` preset end to end, one experiment per process, for a rented GPU machine whose
# commands are time-limited: start it detached and collect OUT_DIR/results.tgz while it runs
# (repacked after every experiment, so a cut-off run still leaves every finished result).
#
#   setsid nohup bench/paper_run.sh /tmp/paper >/dev/null 2>&1 </dev/null &
#   cat /tmp/paper/done.txt                  # one line per experiment: name, exit status, seconds
#   bench/poll_run.sh /tmp/paper 540         # from the next commands, back to back
#   dmrt report RESULTS --out reports/latest # after unpacking results.tgz here
#
# The environment (EGL vendor file, PYTHONPATH with the wheels, DMRT_COMMIT for a tree without git
# history) is the caller's: see ../shared/GPU.md.
set -u
out=${1:?usage: bench/paper_run.sh OUT_DIR [EXPERIMENT ...]}
shift
experiments=("$@")
[ ${#experiments[@]} -gt 0 ] || read -ra experiments <<<"$(python3 -m bench.experiments)"  # every experiment, in run order
mkdir -p "$out"
rm -f "$out/done.txt"  # a record left by an earlier run on a warm machine would end bench/poll_run.sh at once
for e in "${experiments[@]}"; do
    t0=$(date +%s)
    python3 -m dmrt.app.cli bench --preset paper --out "$out/results" --work "$out/work" --only "$e" >>"$out/log.txt" 2>&1
    rc=$?
    echo "$e rc=$rc $(( $(date +%s) - t0 )) s" >>"$out/done.txt"
    tar czf "$out/results.tgz.tmp" -C "$out" results && mv "$out/results.tgz.tmp" "$out/results.tgz"
done
echo finished >>"$out/done.txt"
