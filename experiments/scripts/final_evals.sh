#!/usr/bin/env bash
# The final policies of finished device-batch runs on the two independent measures that RESULTS.md reads beside the
# trainer's evaluation, all side by side on the device machine, in one call:
#   - MJX_EPISODES (default 20) episodes of `cli eval` on MJX (the GPU), the same starts for every run of a master
#     seed, into runs/batch/mjx-20ep-NAME.csv (mjx-<n>ep-NAME.csv for another n);
#   - DMC_EPISODES (default 10) episodes of `cli eval --backend dm_control` (the machine's CPU steps dm_control's
#     physics, its GPU plans: ~1 min for six acrobot policies side by side, where the 2-core CPU box took 5-30 min
#     each), into runs/batch/dm_control-NAME.csv. It replays byte for byte on another H100, but not the CPU box's
#     returns: same starts, other arithmetic (RESULTS.md [112], six policies: +6.9 ± 6.3 on average over 60
#     episodes, no bias shown; 26 episodes within 1, one 206.7 apart; policies' means -1.8 to +22.4 apart), so pair
#     device files with device files and CPU files with CPU files where both exist.
#
#   final_evals.sh NAME...        each NAME a run folder runs/batch/NAME with its policy.npz (device_batch.sh's runs)
#
# Each evaluation's output goes to runs/batch/eval-NAME.log / dm_control-NAME.log; all CSVs and logs are packed into
# one $OUT/final-evals.tar.gz (the device tool returns at most 8 files; back here, file_final_evals.sh files it into a
# results folder). Exit 1 when an evaluation failed (each one named, with its log's last line); what the others wrote
# is still packed. Every process gets MEM_FRACTION (default 0.9 / the number of processes) of the GPU's memory and
# TIMEOUT seconds (default 300).
# $PYTHON picks the interpreter (default python3); DRY=1 prints the commands and runs nothing.
set -u
BATCH=runs/batch
PYTHON=${PYTHON:-python3}
[ $# -gt 0 ] || { echo "usage: final_evals.sh NAME... (run folders under $BATCH)" >&2; exit 2; }
for var in MJX_EPISODES DMC_EPISODES TIMEOUT; do
    value=${!var:-1}
    [[ $value =~ ^[1-9][0-9]*$ ]] || { echo "$var=$value must be a positive whole number" >&2; exit 2; }
done
missing=0
for name in "$@"; do
    [ -f "$BATCH/$name/policy.npz" ] || { echo "$BATCH/$name/policy.npz: no such file (a finished run of" \
        "device_batch.sh has one)" >&2; missing=1; }
done
[ $missing = 0 ] || exit 1
if [ -z "${DRY:-}" ] && [ -z "${OUT:-}" ]; then
    echo "set OUT, the folder whose files come back (the device tool sets it)" >&2
    exit 2
fi
fraction=${MEM_FRACTION:-$(awk -v n=$(($# * 2)) 'BEGIN { printf "%.2f", 0.9 / n }')}

mjx=${MJX_EPISODES:-20}
pids=()
logs=()
launch() {  # LOG COMMAND...: COMMAND in the background, its output into LOG (DRY=1: printed instead)
    local log=$1
    shift
    if [ -n "${DRY:-}" ]; then
        echo "$* > $log"
        return
    fi
    XLA_PYTHON_CLIENT_MEM_FRACTION=$fraction timeout "${TIMEOUT:-300}" "$@" >"$log" 2>&1 &
    pids+=($!)
    logs+=("$log")
}
for name in "$@"; do
    launch "$BATCH/eval-$name.log" "$PYTHON" -m lnnmpc.train.cli eval "$BATCH/$name" --episodes "$mjx" \
        --out "$BATCH/mjx-${mjx}ep-$name.csv"
    launch "$BATCH/dm_control-$name.log" "$PYTHON" -m lnnmpc.train.cli eval "$BATCH/$name" --backend dm_control \
        --episodes "${DMC_EPISODES:-10}" --out "$BATCH/dm_control-$name.csv"
done
[ -z "${DRY:-}" ] || exit 0
status=0
for k in "${!pids[@]}"; do
    if ! wait "${pids[k]}"; then
        echo "FAILED  ${logs[k]}: $(tr '\r' '\n' <"${logs[k]}" | grep -v '^$' | tail -n 1)" >&2
        status=1
    fi
done
for log in "${logs[@]}"; do
    tr '\r' '\n' <"$log" | grep -E ' return -?[0-9]' | tail -n 1
done
files=()
for name in "$@"; do
    for file in "$BATCH/mjx-${mjx}ep-$name.csv" "$BATCH/eval-$name.log" "$BATCH/dm_control-$name.csv" \
            "$BATCH/dm_control-$name.log"; do
        [ -f "$file" ] && files+=("$file")
    done
done
if [ ${#files[@]} = 0 ]; then
    echo "no evaluation wrote anything: nothing packed" >&2
    exit 1
fi
tar czf "$OUT/final-evals.tar.gz" "${files[@]}"
echo "packed ${#files[@]} file(s) into $OUT/final-evals.tar.gz"
exit $status
