#!/usr/bin/env bash
# Files the tarball of `final_evals.sh` (final-evals.tar.gz, back from the device) into a results folder here, under
# the names that the results READMEs' `lnnmpc.train.paired` and `line_measures` commands read:
#
#   runs/batch/mjx-<n>ep-NAME.csv   -> FOLDER/analysis/mjx-<n>ep-SHORT-STEP.csv
#   runs/batch/eval-NAME.log        -> FOLDER/analysis/logs/mjx-<n>ep-SHORT.log
#   runs/batch/dm_control-NAME.csv  -> FOLDER/analysis/dm_control-gpu-SHORT-STEP.csv
#   runs/batch/dm_control-NAME.log  -> FOLDER/analysis/logs/dm_control-gpu-SHORT.log
#
#   file_final_evals.sh TARBALL FOLDER [PREFIX]
#
# SHORT is NAME less PREFIX (default "acrobot-recipe-"; a NAME without it stays whole), STEP the env_step of the CSV's
# rows (the checkpoint evaluated; a CSV whose rows name no step or several is refused). dm_control's files are
# marked "-gpu": final_evals.sh plays them on the device, not bit for bit this CPU's (RESULTS.md [112]), so they pair
# with other device files. Nothing is overwritten unless FORCE=1, and every name is checked before any file is
# copied, so a refusal files nothing. Prints each file it filed (a CSV with its episodes' count and mean return);
# exit 1 on a refusal, 2 on bad arguments.
set -u
tarball=${1:-}
folder=${2:-}
prefix=${3-acrobot-recipe-}
if [ -z "$tarball" ] || [ -z "$folder" ] || [ $# -gt 3 ]; then
    echo "usage: file_final_evals.sh TARBALL FOLDER [PREFIX]" >&2
    exit 2
fi
[ -f "$tarball" ] || { echo "$tarball: no such file (final_evals.sh packs \$OUT/final-evals.tar.gz)" >&2; exit 2; }
[ -d "$folder" ] || { echo "$folder: no such folder (the results folder the runs were filed in)" >&2; exit 2; }
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
tar -xzf "$tarball" -C "$tmp" || { echo "$tarball: not a tar.gz archive" >&2; exit 2; }
batch=$tmp/runs/batch
[ -d "$batch" ] || { echo "$tarball holds no runs/batch/ folder: not a final_evals.sh tarball" >&2; exit 2; }

csv_step() {  # CSV: its rows' one env_step, or a reason on stderr and status 1
    local steps
    if [ "$(head -n 1 "$1" | cut -d, -f1)" != env_step ]; then
        echo "$(basename "$1"): its first column is not env_step (not a cli eval CSV)" >&2
        return 1
    fi
    steps=$(awk -F, 'NR > 1 { print $1 }' "$1" | sort -u)
    if [ -z "$steps" ] || [ "$(printf '%s\n' "$steps" | wc -l)" -ne 1 ]; then
        echo "$(basename "$1"): its rows name $(printf '%s' "$steps" | wc -w) env steps, not one" >&2
        return 1
    fi
    echo "$steps"
}
short() {  # NAME less the prefix
    if [ -n "$prefix" ] && [[ $1 == "$prefix"* ]]; then echo "${1#"$prefix"}"; else echo "$1"; fi
}

sources=()
targets=()
declare -A paired_log  # the logs already filed beside their CSV
bad=0
shopt -s nullglob
for file in "$batch"/mjx-*ep-*.csv "$batch"/dm_control-*.csv; do
    base=$(basename "$file" .csv)
    case $base in
        mjx-*) kind=${base%%ep-*}ep; name=${base#"$kind"-}; label=$kind ;;
        *) kind=dm_control; name=${base#dm_control-}; label=dm_control-gpu ;;
    esac
    step=$(csv_step "$file") || { bad=1; continue; }
    sources+=("$file")
    targets+=("$folder/analysis/$label-$(short "$name")-$step.csv")
    log=$batch/dm_control-$name.log
    [ "$kind" = dm_control ] || log=$batch/eval-$name.log
    if [ -f "$log" ]; then
        sources+=("$log")
        targets+=("$folder/analysis/logs/$label-$(short "$name").log")
        paired_log[$log]=1
    fi
done
for log in "$batch"/eval-*.log "$batch"/dm_control-*.log; do  # an evaluation that failed left its log, no CSV
    [ -z "${paired_log[$log]:-}" ] || continue
    base=$(basename "$log" .log)
    case $base in
        eval-*) label=mjx-failed; name=${base#eval-} ;;
        *) label=dm_control-gpu-failed; name=${base#dm_control-} ;;
    esac
    sources+=("$log")
    targets+=("$folder/analysis/logs/$label-$(short "$name").log")
done
if [ ${#sources[@]} = 0 ]; then
    echo "$tarball holds no evaluation's CSV or log" >&2
    exit 1
fi
for k in "${!targets[@]}"; do
    if [ -e "${targets[k]}" ] && [ -z "${FORCE:-}" ]; then
        echo "${targets[k]} exists (FORCE=1 replaces it)" >&2
        bad=1
    fi
done
if [ $bad = 1 ]; then
    echo "nothing filed" >&2
    exit 1
fi
mkdir -p "$folder/analysis/logs"
for k in "${!sources[@]}"; do
    cp "${sources[k]}" "${targets[k]}.tmp.$$" && mv -f "${targets[k]}.tmp.$$" "${targets[k]}" || exit 1
    case ${targets[k]} in
        *.csv) echo "filed ${targets[k]} ($(awk -F, 'NR == 1 { for (i = 1; i <= NF; i++) if ($i == "return") c = i }
                    NR > 1 { n++; s += $c } END { printf "%d episodes, mean return %.1f", n, s / n }' "${targets[k]}"))" ;;
        *) echo "filed ${targets[k]}" ;;
    esac
done
