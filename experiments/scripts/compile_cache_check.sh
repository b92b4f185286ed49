#!/usr/bin/env bash
# Does XLA's persistent compile cache, written on one GPU machine and carried to a fresh one, spare the fresh
# machine's compilation? Runs on the device machine:
#
#   compile_cache_check.sh ARCHIVE_GLOB SECONDS JOBS
#
# ARCHIVE_GLOB: the parts (split -b, in name order) of a .tgz of runs/jaxcache made on the first machine; they are
#   concatenated and unpacked at the repository root (an empty glob runs without a cache: the baseline).
#   runs/jaxcache and runs/cachecheck are emptied first (run it on the device machine, not where a cache is kept).
# JOBS: "<name> <trainer arguments>" lines (device_batch.sh's format; # comments skipped), all launched side by side,
#   each with --out runs/cachecheck/<name> --compile-cache runs/jaxcache, stopped after SECONDS (SIGTERM, then
#   SIGKILL 20 s later: only compile.csv is wanted, whose rows are written as each program is ready).
# Writes to $OUT: <name>-compile.csv (each program's lowering / compilation / ready seconds), <name>.log (tail), and
# cache.txt (the GPU, the cache's entries before and after). $PYTHON picks the interpreter (default python3).
set -u
glob=${1:?ARCHIVE_GLOB}; seconds=${2:?SECONDS}; jobs=${3:?JOBS}
out=${OUT:?OUT: where the results go}
cache_size() {  # "<entries>, <KiB> KiB" of runs/jaxcache (0 where absent)
    local kib
    kib=$(du -sk runs/jaxcache 2>/dev/null | cut -f1)
    echo "$(find runs/jaxcache -type f 2>/dev/null | wc -l), ${kib:-0} KiB"
}
rm -rf runs/cachecheck runs/jaxcache && mkdir -p runs/cachecheck
# shellcheck disable=SC2086
parts=$(ls $glob 2>/dev/null | sort)
if [ -n "$parts" ]; then
    # shellcheck disable=SC2086
    cat $parts | tar xz
fi
{
    nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
    echo "cache entries before: $(cache_size)"
} > "$out/cache.txt"
lines=$(grep -v -E '^\s*(#|$)' "$jobs")
n=$(printf '%s\n' "$lines" | wc -l)
fraction=$(awk -v n="$n" 'BEGIN { printf "%.3g", 0.9 / n }')
while read -r name args; do
    # shellcheck disable=SC2086
    XLA_PYTHON_CLIENT_MEM_FRACTION=$fraction timeout -s TERM -k 20 "$seconds" "${PYTHON:-python3}" -m lnnmpc.train.cli train \
        $args --out "runs/cachecheck/$name" --compile-cache runs/jaxcache > "runs/cachecheck/$name.log" 2>&1 &
done <<< "$lines"
wait
while read -r name _; do
    cp "runs/cachecheck/$name/compile.csv" "$out/$name-compile.csv" 2>/dev/null || echo "$name: no compile.csv" >> "$out/cache.txt"
    tr '\r' '\n' < "runs/cachecheck/$name.log" | tail -20 > "$out/$name.log"
done <<< "$lines"
echo "cache entries after: $(cache_size)" >> "$out/cache.txt"
cat "$out/cache.txt"
for f in "$out"/*-compile.csv; do echo "== $f"; cat "$f"; done
