#!/usr/bin/env bash
# Source trees of revisions for bench/ab_run.sh: DIR/NAME holds dmrt/, shaders/, bench/ and
# pyproject.toml of REV (git archive; COMMIT holds its short hash). Edit a tree afterwards to try a
# change that is not committed.
#
#   bench/ab_trees.sh .ab HEAD~1:base HEAD:new
set -eu
dir=${1:?usage: bench/ab_trees.sh DIR REV:NAME...}
shift
for spec in "$@"; do
    rev=${spec%%:*} name=${spec#*:}
    [ "$rev" != "$spec" ] && [ -n "$name" ] || { echo "ab_trees: $spec: expected REV:NAME" >&2; exit 2; }
    git rev-parse --verify --quiet "$rev^{commit}" >/dev/null || { echo "ab_trees: $rev: no such revision" >&2; exit 2; }
    rm -rf "${dir:?}/$name" && mkdir -p "$dir/$name"
    git archive "$rev" dmrt shaders bench pyproject.toml | tar x -C "$dir/$name"
    git rev-parse --short "$rev" >"$dir/$name/COMMIT"
    echo "$dir/$name: $(cat "$dir/$name/COMMIT")"
done
