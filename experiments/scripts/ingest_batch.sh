#!/usr/bin/env bash
# Files a device batch's results here, on the CPU, as soon as a `device_batch.sh` report has come back:
#
#   experiments/scripts/ingest_batch.sh RESULTS_TAR_GZ
#
# A policies.tar beside RESULTS_TAR_GZ (the runs' policy.npz files and any evaluations' policies/, packed apart by
# device_batch.sh), and policies-2.tar ... where one was full, are unpacked over the run folders first, so each filed
# run keeps its trained policy (git ignores policy.npz and policies/policy-*.npz); a policy.npz that came in parts
# (<file>.part-<k>-of-<n>, over POLICY_MIB) is joined when every part came back;
# - every study run folder of the batch (runs/batch/experiments/<task>/<agent>/<condition>, no checkpoints) is
#   copied into experiments/results/study-runs/, the runs-dir the committed study tables are built from (but
#   Figure 5.19's: experiments/results/study-runs-fig5_19-h100/). A newer copy of a run replaces the older one,
#   unless it reached fewer environment steps: a run killed early on the device never overwrites a longer one
#   filed before; FORCE=1 replaces it anyway. The older copy's evaluation files that the new copy lacks are listed
#   as "dropped", since a table may have been built from them;
# - for each of them whose eval.csv logged the effective rank: <run>/analysis/effective_rank.{csv,png}
#   (`lnnmpc.analysis.report --ranks-only`);
# - each study of the batch (its commands.txt) is aggregated again over study-runs/ into
#   experiments/results/studies/<study>.{csv,md}: the whole table, every agent of the study (the line's --agents
#   dropped), measured cells from whatever study-runs/ holds, "not yet run" elsewhere;
# - the batch's plain training runs (runs/batch/<name>/) are listed and copied to $STAGING (default
#   runs/ingested/<name>, git-ignored), to be filed by hand with a README; their tables (`lnnmpc.train.tables`:
#   every evaluation and the speed) are printed for it. A run that an earlier batch of the same warm machine
#   brought back already (the same config.json) keeps the policy files staged then that this batch's
#   policies' tars left out (over device_batch.sh's POLICY_TARS x POLICY_MIB).
# $PYTHON picks the interpreter (default .venv/bin/python). Commit what it wrote right after.
set -eu
tarball=${1:?usage: ingest_batch.sh RESULTS_TAR_GZ}
python=${PYTHON:-.venv/bin/python}
runs=experiments/results/study-runs
staging=${STAGING:-runs/ingested}
tmp=$(mktemp -d)
last_env_step() {  # RUN_DIR: the last env_step its eval.csv logged (0 without evaluations)
    if [ -f "$1/eval.csv" ]; then
        awk -F, 'NR > 1 && $1 + 0 > last { last = $1 + 0 } END { print last + 0 }' "$1/eval.csv"
    else
        echo 0
    fi
}
keep_policies() {  # OLD NEW: OLD's policy files that NEW lacks, moved into NEW when both are one run (same config.json)
    [ -f "$1/config.json" ] && [ -f "$2/config.json" ] && cmp -s "$1/config.json" "$2/config.json" || return 0
    local file rel
    for file in "$1"/policy.npz "$1"/policies/policy-*.npz; do
        rel=${file#"$1"/}
        [ -f "$file" ] && [ ! -f "$2/$rel" ] || continue
        mkdir -p "$(dirname "$2/$rel")"
        mv "$file" "$2/$rel"
        echo "kept     $1/$rel (this run's, filed before; the batch's policies' tars lack it)"
    done
}
trap 'rm -rf "$tmp"' EXIT
tar -xzf "$tarball" -C "$tmp"
for policies in "$(dirname "$tarball")"/policies.tar "$(dirname "$tarball")"/policies-[0-9]*.tar; do
    [ -f "$policies" ] || continue
    tar -xf "$policies" -C "$tmp"
    echo "policies $(tar -tf "$policies" | grep -c '/policy[.]npz$' || true) policy.npz from $policies"
    snapshots=$(tar -tf "$policies" | grep -c '/policies/policy-[0-9]*[.]npz$' || true)
    [ "$snapshots" -eq 0 ] || echo "         $snapshots evaluations' policies (policies/policy-<step>.npz)"
done
while IFS=$'\t' read -r base count; do  # a policy.npz too large for one tar came in parts <file>.part-<k>-of-<n>:
    # joined in order where all n came back, else none of them is filed
    parts=()
    for ((k = 1; k <= count; k++)); do
        [ -f "$base.part-$k-of-$count" ] && parts+=("$base.part-$k-of-$count")
    done
    if [ ${#parts[@]} -eq "$count" ]; then
        cat "${parts[@]}" >"$base"
        echo "joined   ${base#"$tmp"/} from its $count parts"
    else
        echo "missing  ${base#"$tmp"/}: ${#parts[@]} of its $count parts came back (device_batch.sh's report names" \
            "those left out); not filed"
    fi
    rm -f "$base".part-*-of-"$count"
done < <(find "$tmp" -name '*.part-*-of-*' | sed -n 's/[.]part-[0-9]*-of-\([0-9]*\)$/\t\1/p' | sort -u)
mkdir -p "$runs"
if [ -d "$tmp/experiments" ]; then
    for run in "$tmp"/experiments/*/*/*/; do
        rel=${run#"$tmp"/experiments/}
        rel=${rel%/}
        if [ -d "$runs/$rel" ] && [ "${FORCE:-0}" != 1 ]; then
            old=$(last_env_step "$runs/$rel") new=$(last_env_step "$run")
            if [ "$new" -lt "$old" ]; then
                echo "kept     $runs/$rel (filed at $old env steps; the batch's copy reached only $new: FORCE=1 replaces it)"
                continue
            fi
        fi
        for eval_file in "$runs/$rel"/evals/*.csv; do  # the older copy's evaluations that the new one lacks
            [ -f "$eval_file" ] && [ ! -f "$run/evals/$(basename "$eval_file")" ] || continue
            echo "dropped  $eval_file (the replaced copy's; if a committed table was built from it, restore the" \
                "old run from git into a runs-dir of its own, as experiments/results/study-runs-fig5_19-h100)"
        done
        rm -rf "${runs:?}/$rel"
        mkdir -p "$runs/$(dirname "$rel")"
        cp -r "$run" "$runs/$rel"
        echo "run      $runs/$rel"
        if head -1 "$runs/$rel/eval.csv" 2>/dev/null | grep -q effective_rank; then
            "$python" -m lnnmpc.analysis.report "$runs/$rel" --ranks-only 2>&1 | grep -v warp || true
        fi
    done
fi
if [ -f "$tmp/commands.txt" ]; then
    sed -n 's/^[^ ]* ([^)]*): experiment //p' "$tmp/commands.txt" \
        | sed -E 's/ --(agents|tasks|train-obs) [^ ]+//g' | sort -u | while read -r study; do
        # shellcheck disable=SC2086  # the study's arguments, word-split on purpose
        "$python" -m lnnmpc.experiments.run $study --aggregate-only --runs-dir "$runs" \
            --out experiments/results/studies 2>&1 | grep -v warp || true
    done
fi
plain=() names=()
for run in "$tmp"/*/; do
    name=$(basename "$run")
    if [ "$name" != experiments ] && [ "$name" != studies ] && [ -f "$run/config.json" ]; then
        mkdir -p "$staging"
        keep_policies "$staging/$name" "$run"
        rm -rf "${staging:?}/$name"
        cp -r "$run" "$staging/$name"
        echo "plain run (file it by hand): runs/batch/$name, copied to $staging/$name"
        plain+=("$staging/$name") names+=("$name")
    fi
done
if [ ${#plain[@]} -gt 0 ]; then  # what its README will quote: each run's evaluations, all speeds, all commands
    for i in "${!plain[@]}"; do
        echo
        "$python" -m lnnmpc.train.tables "${plain[$i]}" --labels "${names[$i]}" --returns-only \
            || echo "(no table for ${names[$i]})"
    done
    echo
    "$python" -m lnnmpc.train.tables "${plain[@]}" --labels "${names[@]}" --speed-only || echo "(no speed table)"
    echo
    "$python" -m lnnmpc.train.tables "${plain[@]}" --labels "${names[@]}" --commands-only || echo "(no commands)"
fi
