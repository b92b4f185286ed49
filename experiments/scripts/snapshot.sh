#!/usr/bin/env bash
# The code a device batch runs, frozen at a commit: HEAD's src/ and benchmarks/ unpacked into DIR (default
# runs/gpu-head, git-ignored) with the commit's hash in DIR/SNAPSHOT_COMMIT, which a run's config.json then
# records as its code (`lnnmpc.train.provenance.git_state`; without SNAPSHOT_COMMIT a package under an ignored
# folder records none, since the enclosing checkout's HEAD says nothing of it). Uncommitted changes to src/ or
# benchmarks/ are refused: they would not be in the snapshot (FORCE=1 snapshots HEAD anyway).
#
#   experiments/scripts/snapshot.sh [DIR]
#
# Then carry DIR on the device tool's `start` call and put DIR/src first on PYTHONPATH.
set -eu
dir=${1:-runs/gpu-head}
if [ -z "${FORCE:-}" ] && ! git diff --quiet HEAD -- src benchmarks; then
    echo "src/ or benchmarks/ differ from HEAD: commit them first (FORCE=1 snapshots HEAD without them)" >&2
    exit 1
fi
rm -rf "$dir"
mkdir -p "$dir"
git archive HEAD src benchmarks | tar -x -C "$dir"
git rev-parse HEAD >"$dir/SNAPSHOT_COMMIT"
echo "$dir: $(cat "$dir/SNAPSHOT_COMMIT") ($(du -sh "$dir" | cut -f1))"
