#!/usr/bin/env bash
# The same `benchmarks/train_throughput.py` measurement with two code snapshots, one after the other: the
# snapshot's own script and package each time (runs/gpu-<version>/benchmarks and runs/gpu-<version>/src, made
# by `experiments/scripts/snapshot.sh runs/gpu-<version>` or `git archive <commit> src benchmarks`). Writes
# $OUT/{device}-NAME-<version>.json per version; the device tool's wheels stay first on PYTHONPATH ($SITE).
#
#   experiments/scripts/throughput_ab.sh NAME [train_throughput.py arguments]      (VERSIONS="old head")
set -eu
if [ $# -lt 1 ]; then
    echo "usage: $0 NAME [train_throughput.py arguments]" >&2
    exit 2
fi
name=$1
shift
for version in ${VERSIONS:-old head}; do
    dir=runs/gpu-$version
    if [ ! -f "$dir/benchmarks/train_throughput.py" ]; then
        echo "$dir holds no snapshot (benchmarks/train_throughput.py missing)" >&2
        exit 1
    fi
    echo "== $version: $(cat "$dir/SNAPSHOT_COMMIT" 2>/dev/null || echo 'commit unknown')"
    PYTHONPATH="${SITE:-/tmp/site}:$PWD/$dir/src" python3 "$dir/benchmarks/train_throughput.py" "$@" \
        --out "${OUT:-.}/{device}-$name-$version.json"
done
