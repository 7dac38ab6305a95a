#!/usr/bin/env bash
# Table 1 at the paper's Scene 2 size (bench preset `paper-full`: 683M points, 192 photos of
# 1024x684): bench/scene3_run.sh with PRESET=paper-full by default (the disk checked first, the
# scene generated and preprocessed end to end on one GPU machine, /usr/bin/time -v and a sampler of
# disk, memory and load every 5 s, JSON results packed into OUT_DIR/results.tgz).
# PRESET=paper-full-scan takes the radii from the scanner's grid instead of kNN (issue #40).
#
#   setsid nohup bench/scale_run.sh /tmp/scale >/dev/null 2>&1 </dev/null &
#   bench/poll_run.sh /tmp/scale 540   # "disk rc=0", "table1 rc=STATUS SECONDS s", then "finished"
#
# The environment (EGL vendor file, PYTHONPATH with the wheels, DMRT_COMMIT) is the caller's:
# see ../shared/GPU.md.
PRESET=${PRESET:-paper-full} exec "$(dirname "$0")/scene3_run.sh" "$@"
