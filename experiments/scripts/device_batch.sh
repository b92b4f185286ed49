#!/usr/bin/env bash
# Several training runs side by side on one GPU machine, over chained calls of the `device` tool.
#
#   device_batch.sh start JOBS SECONDS REPORT   launch every job of the file JOBS (each stopped by SIGTERM after
#                                               SECONDS, as `timeout -s TERM` would, unless `extend` moves that
#                                               limit; in its own session so that it outlives the call), then
#                                               report REPORT seconds after this start began (a relaunch's
#                                               wait included) or when all have ended; refused
#                                               while jobs of an earlier start still run (FORCE=1 overrides);
#                                               a job of JOBS launched before (a run cut by its timeout, to be
#                                               resumed) first waits for its earlier process to end (a process
#                                               killed from outside counts as ended); a training
#                                               job whose earlier launch of the same line exited 0 (its run
#                                               reached its steps) is not launched again (RERUN=1 relaunches it)
#                                               ONLY=NAME[,NAME...] launches only those lines of JOBS (a relaunch
#                                               of some lines of a larger plan needs no file of its own)
#   device_batch.sh wait REPORT                 report again after REPORT seconds or when all have ended
#   device_batch.sh extend SECONDS [NAME...]    move the SIGTERM limit of the running jobs (or of those NAMEd) by
#                                               SECONDS (negative: sooner), e.g. when a run trains slower than its
#                                               limit assumed; the report gives each running job's time left
#   device_batch.sh after NAME GPU COMMAND...   once the job NAME of the running batch has ended (its exit status
#                                               is in runs/batch/NAME.rc; "gone" where its process was killed
#                                               from outside), run COMMAND on GPU in the background
#                                               (own session; output in runs/batch/after-NAME.log): a benchmark
#                                               on a GPU that a finished job left idle; returns at once
#   device_batch.sh check JOBS                  before spending device time, here on the CPU: `lint` the file,
#                                               then validate every line (train --check; studies --dry-run);
#                                               exit 1 if any fails ($PYTHON picks the interpreter, default python3)
#   device_batch.sh lint JOBS...                the files' shape alone, in well under a second each (no dry run):
#                                               every job line "<name> --..." or "<name> experiment ...", no job
#                                               name twice in a file; exit 1 naming each bad line. `start` lints
#                                               its file first and launches nothing from a bad one
#
# JOBS: one line per run, "<name> <trainer arguments>" (lines starting with # are skipped); each becomes
#   python3 -m lnnmpc.train.cli train <arguments> --out runs/batch/<name> --compile-cache runs/jaxcache
# A line "<name> experiment <study arguments>" runs a study instead (python3 -m lnnmpc.experiments.run <arguments>
# --runs-dir runs/batch/experiments --out runs/batch/studies): its runs, then its evaluations and tables.
# A run stopped by its timeout saves a checkpoint after its running chunk (SIGTERM), so what it measured is kept;
# a study stopped so then evaluates and aggregates its newest checkpoints (--no-train, under EVAL_SECONDS, default
# 300 more seconds), so a study line yields its table's cells (at the step reached) even when cut short.
# Each report prints every run's progress line (and, for a job that has ended, its exit status and its wall seconds
# from launch to exit, kept in runs/batch/NAME.seconds) and packs the run folders without checkpoints, the logs and
# nvidia-smi's view into $OUT/results.tar.gz (the device tool returns at most 8 files), the runs' policy.npz files
# (their parameters, for `eval` and `video` back here) into $OUT/policies.tar (policies-2.tar ... when one is full)
# and itself into $OUT/report.txt.
# All are also packed every SNAPSHOT_EVERY seconds (default 60) while the report waits: a call stopped at its
# limit kills the command with its pipeline (a `| tail` returns nothing) but still returns what is under $OUT.
# Keep REPORT some 30 s under the call's limit (the install before it takes ~10 s).
# On a machine of several GPUs each job gets one GPU (CUDA_VISIBLE_DEVICES): "<name>@<k>" pins a line to GPU k
# (k mod the machine's count, so a two-GPU file still runs on one GPU), the other lines are dealt out round robin
# (the i-th line on GPU i mod count). "<name>@all" gives one job every GPU (e.g. `train --devices 4`, the seeds
# sharded over them); such a job must be the only line of its file. Independent runs gain the most from more
# GPUs, since one run's step is latency-bound. The jobs on one GPU share it through CUDA MPS when the machine has it (MPS=0 turns that off);
# each process takes MEM_FRACTION (default 0.9 / the number of jobs on its GPU) of its GPU's memory.
set -u
BATCH=runs/batch
SCRIPTS=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
action=${1:?start, wait, extend, after, check or lint}
shift
case ${POLICY_TARS:-3} in  # report.txt, results.tar.gz and the policies' tars: at most 8 files come back
    [1-6]) ;;
    *) echo "POLICY_TARS=${POLICY_TARS} must be 1 to 6 (the device tool returns at most 8 files)" >&2; exit 2 ;;
esac

# A line of a jobs file that is no job line: a comment or a blank line (an extended regex; job_lines and lint_jobs
# both skip what it matches)
NOT_A_JOB='^[[:space:]]*(#|$)'

job_lines() {  # JOBS: the job lines of a jobs file (no comments, no blank lines)
    grep -v -E "$NOT_A_JOB" "$1"
}

# Exit 1, each problem on stderr as FILE:LINE, when a job line of JOBS is no "<name> <arguments>" line (a name of
# letters, digits, '.', '_' or '-', with an optional "@<gpu>"; arguments beginning with "--" or "experiment ": a
# line of prose that lost its '#' fails here) or repeats a job name of the file (two processes would train in one
# run folder).
lint_jobs() {  # JOBS
    [ -r "$1" ] || { echo "$1: no such jobs file" >&2; return 1; }
    awk -v file="$1" -v skip="$NOT_A_JOB" '
        $0 ~ skip { next }
        {
            name = $1; sub(/@.*/, "", name)
            args = $0; sub(/^[[:space:]]*[^[:space:]]+[[:space:]]*/, "", args)
            if (name !~ /^[A-Za-z0-9][A-Za-z0-9._-]*$/) {
                printf "%s:%d: job name %s: give letters, digits, . _ or - (and @<gpu>)\n", file, NR, $1; bad = 1
            } else if (args !~ /^(--|experiment )/) {
                printf "%s:%d: %s: a job line is <name> --<trainer arguments> or <name> experiment <study" \
                    " arguments> (a comment starts with #)\n", file, NR, substr($0, 1, 60); bad = 1
            }
            if (name in seen) {
                printf "%s:%d: job name %s again (line %d): each job of a file needs its own name\n", file, NR,
                    name, seen[name]; bad = 1
            } else {
                seen[name] = NR
            }
        }
        END { exit bad }' "$1" >&2
}

# The lines of JOBS whose job names (without "@<gpu>") are in NAMES (comma-separated), written to a new temporary
# file whose path is printed; exit 1 naming each name JOBS lacks and the names it has.
select_jobs() {  # JOBS NAMES
    local names have wanted missing="" selected
    names=$(job_lines "$1" | awk '{sub(/@.*/, "", $1); print $1}')
    wanted=$(echo "$2" | tr ',' '\n' | sed '/^$/d')
    for name in $wanted; do
        echo "$names" | grep -qxF "$name" || missing="$missing $name"
    done
    if [ -n "$missing" ] || [ -z "$wanted" ]; then
        have=$(echo "$names" | tr '\n' ' ')
        echo "ONLY names no job of $1:${missing:- (none given)}; its jobs: ${have% }" >&2
        return 1
    fi
    selected=$(mktemp)
    job_lines "$1" | awk -v keep=",$2," '{ name = $1; sub(/@.*/, "", name); if (index(keep, "," name ",")) print }' \
        >"$selected"
    echo "$selected"
}

# "NAME@K" -> "NAME K", "NAME@all" -> "NAME all"; a plain NAME -> "NAME" (no GPU asked for); exit 1 for a GPU
# that is no number
split_name() {  # NAME[@K|@all]
    case $1 in
    *@*)
        local gpu=${1##*@}
        [[ $gpu =~ ^([0-9]+|all)$ ]] || { echo "bad GPU '$gpu' in job name '$1': give <name>@<number> or"\
            "<name>@all" >&2; return 1; }
        echo "${1%@*} $gpu" ;;
    *) echo "$1" ;;
    esac
}

# The GPU of every job line of JOBS, one per line ("NAME GPU"): pinned lines on their GPU mod COUNT, the others
# round robin by their position among all lines.
place_jobs() {  # JOBS COUNT
    local index=0 name gpu args
    while read -r name args; do
        read -r name gpu < <(split_name "$name") || return 1
        if [ "$gpu" = all ]; then
            echo "$name all"
        else
            echo "$name $(((${gpu:-$index}) % $2))"
        fi
        index=$((index + 1))
    done < <(job_lines "$1")
}

# Exit 1 (with the reason) when a "@all" job shares its file with other jobs: it would share every GPU with them.
all_alone() {  # JOBS
    local names
    names=$(job_lines "$1" | awk '{print $1}')
    if echo "$names" | grep -q '@all$' && [ "$(echo "$names" | wc -l)" -gt 1 ]; then
        echo "a <name>@all job uses every GPU: give it a jobs file of its own" >&2
        return 1
    fi
}

# The command of one job line "NAME ARGS", its outputs under DIR: a study for "experiment ..." lines (STUDY_EXTRA
# appended), else a training run (TRAIN_EXTRA appended). `start` and `check` both build their commands here.
job_command() {  # NAME ARGS DIR TRAIN_EXTRA STUDY_EXTRA
    local name=$1 args=$2 dir=$3
    if [ "${args%% *}" = experiment ]; then
        echo "${PYTHON:-python3} -m lnnmpc.experiments.run ${args#experiment } --runs-dir $dir/experiments" \
            "--out $dir/studies $5"
    else
        echo "${PYTHON:-python3} -m lnnmpc.train.cli train $args --out $dir/$name $4"
    fi
}

# The names of the jobs that `start` launched on this machine (its commands.txt), one per line.
batch_jobs() {
    grep -o '^[^ ]* (GPU' "$BATCH/commands.txt" 2>/dev/null | cut -d' ' -f1
}

# The jobs of earlier starts on this machine that have not ended (no NAME.rc yet), space-separated: a second
# `start` in the same hold (another jobs file once the first has ended) adds its runs beside the first's.
still_running() {
    batch_jobs | while read -r name; do
        settle_gone "$name" || printf '%s ' "$name"
    done
}

# Exit 0 when job NAME has ended: its NAME.rc is there, or its launch's wrapper process (NAME.pid) is gone without
# writing one (killed from outside: a `pkill`, the kernel's OOM killer), in which case NAME.rc gets "gone", so that
# neither a relaunch nor a second start waits for a process that no longer exists.
settle_gone() {  # NAME
    local pid
    [ -f "$BATCH/$1.rc" ] && return 0
    pid=$(cat "$BATCH/$1.pid" 2>/dev/null) && [ -n "$pid" ] || return 1
    if kill -0 "$pid" 2>/dev/null; then  # alive, unless a zombie that nothing reaps
        [ "$(ps -o stat= -p "$pid" 2>/dev/null | tr -d ' ' | cut -c1)" = Z ] || return 1
    fi
    [ -f "$BATCH/$1.rc" ] || echo gone >"$BATCH/$1.rc"
}

# Exit 0 when the training job NAME with trainer arguments ARGS need not be launched again: its last launch on this
# machine ran the same line (commands.txt) and exited 0, so its run reached its steps; relaunching it would only
# resume, find nothing to train and exit (~40 s of a GPU, compilation included). Study lines ("experiment ...")
# always relaunch: their exit status is that of the evaluation that follows a cut. RERUN=1 relaunches every job.
finished_before() {  # NAME ARGS
    [ "${RERUN:-0}" != 1 ] && [ "${2%% *}" != experiment ] && [ "$(cat "$BATCH/$1.rc" 2>/dev/null)" = 0 ] || return 1
    local last
    last=$(grep "^$1 (GPU [^)]*): " "$BATCH/commands.txt" 2>/dev/null | tail -1)
    [ "${last#*): }" = "$2" ]
}

# The report: every run's progress line (and, for a job that has ended, its exit status and wall seconds), the
# tracebacks, nvidia-smi's view.
print_report() {
    echo "=== $(date -u +%T) ($(($(date +%s) - $(cat $BATCH/started))) s since start)"
    for log in "$BATCH"/*.log; do
        printf '%-34s %s\n' "$(basename "$log" .log)" "$(tr '\r' '\n' <"$log" | grep '^\[' | tail -1 | cut -c1-130)"
        tr '\r' '\n' <"$log" | grep -v -E '^\s*$|^\[' | tail -1 | cut -c1-150
        local ended=${log%.log}
        settle_gone "$(basename "$ended")" || true
        [ -f "$ended.seconds" ] && echo "ended (exit $(cat "$ended.rc" 2>/dev/null)) $(cat "$ended.seconds") s after its launch"
        [ "$(cat "$ended.rc" 2>/dev/null)" = gone ] && echo "ended: its process is gone without an exit status (killed from outside)"
        [ ! -f "$ended.rc" ] && [ -f "$ended.deadline" ] \
            && echo "running: SIGTERM in $(($(cat "$ended.deadline") - $(date +%s))) s unless extended (device_batch.sh extend)"
        [ -f "$ended.earlier-seconds" ] && echo "earlier launches: $(paste -sd+ "$ended.earlier-seconds") s"
    done
    cat "$BATCH/policies.txt" 2>/dev/null
    grep -l -E "Traceback|Error" "$BATCH"/*.log 2>/dev/null | while read -r bad; do
        echo "--- $bad"; tail -15 "$bad"; done
    nvidia-smi --query-gpu=index,utilization.gpu,memory.used,memory.total --format=csv,noheader 2>/dev/null \
        | tee "$BATCH/nvidia-smi.txt"
}

# The report and the run folders (without checkpoints), the logs and nvidia-smi's view packed into $OUT (report.txt,
# results.tar.gz; each replaced whole), where the device tool fetches them: also after a call cut at its limit.
# The runs' policy.npz files (the newest checkpoint's parameters, some MB per seed) go apart into policies.tar and,
# when it is full, policies-2.tar ... policies-<POLICY_TARS>.tar (default 3), each under POLICY_MIB (default 15: the
# tool returns files of at most 16 MiB, 8 files and 64 MiB in all), the policies written since the latest start
# first; the report names any left out.
# Runs trained with --eval-policies add each evaluation's policy (policies/policy-<step>.npz): packed after every
# run's policy.npz of the same start, newest evaluation first, while they fit.
pack_out() {
    [ -n "${OUT:-}" ] || return 0
    pack_policies >"$BATCH/policies.txt"
    print_report >"$OUT/.report.txt" 2>&1 && mv "$OUT/.report.txt" "$OUT/report.txt"
    tar czf "$OUT/.results.tar.gz" --exclude=checkpoints --exclude=.lock --exclude='*.deadline' --exclude=policy.npz --exclude='policy-*.npz' --exclude=./.parts -C "$BATCH" . \
        && mv "$OUT/.results.tar.gz" "$OUT/results.tar.gz"
}

# $OUT/policies.tar (then policies-2.tar ...): the policy files under $BATCH, those written since the latest start
# first (a machine that ran an earlier start has returned those runs' policies already); in each group every run's
# policy.npz in name order, then the evaluations' policies (each run's newest first); each file goes into the first
# tar it keeps under POLICY_MIB, else it is left out; prints one line per file left out. A tar left empty is removed
# from $OUT.
# A run's policy.npz over POLICY_MIB (TD-MPC2's 5M model: ~20 MB) goes in equal parts, <file>.part-<k>-of-<n>
# (written under $BATCH/.parts), each placed like a file; ingest_batch.sh joins them when all came back.
batch_policies() {  # FIND_TEST...: the policy files under $BATCH (relative) that pass find's tests FIND_TEST...:
    # each run's policy.npz in name order, then the evaluations' policies/policy-<step>.npz, by run, newest first
    (cd "$BATCH" && find . -name policy.npz -not -path '*/checkpoints/*' "$@" | sort \
        && find . -path '*/policies/policy-*.npz' -not -path '*/checkpoints/*' "$@" \
            | awk -F'/policies/policy-' '{ print $1 "\t" ($2 + 0) "\t" $0 }' | sort -t "$(printf '\t')" -k1,1 -k2,2nr \
            | cut -f3)
}

run_policies() {  # every policy file under $BATCH (relative) in pack_policies' order: those written since the latest
    # start first, then the earlier ones; $BATCH/started is there (pack_out's one caller, report_until, runs after a
    # start)
    batch_policies -newer started
    batch_policies ! -newer started
}

policy_parts() {  # FILE BUDGET: FILE (relative to $BATCH) cut into n = ceil(size / BUDGET) equal parts under
    # $BATCH/.parts; prints each part's path relative to $BATCH/.parts
    local file=$1 budget=$2 size n k part
    size=$(stat -c %s "$BATCH/$file")
    n=$(((size + budget - 1) / budget))
    mkdir -p "$BATCH/.parts/$(dirname "$file")"
    split -n "$n" -d -a 3 "$BATCH/$file" "$BATCH/.parts/$file.tmp-"
    for ((k = 1; k <= n; k++)); do
        part=$file.part-$k-of-$n
        mv "$BATCH/.parts/$file.tmp-$(printf %03d $((k - 1)))" "$BATCH/.parts/$part"
        echo "$part"
    done
}

packed_path() {  # ENTRY: where pack_policies' entry lies (a part, <file>.part-<k>-of-<n>, under $BATCH/.parts)
    case $1 in *.part-*-of-*) echo "$BATCH/.parts/$1" ;; *) echo "$BATCH/$1" ;; esac
}

pack_policies() {
    local budget=$((${POLICY_MIB:-15} * 1048576)) tars=${POLICY_TARS:-3} size file i name placed entry
    local -a used=() assigned=() packed=() parts=() entries=() args=()
    for ((i = 0; i < tars; i++)); do used[i]=0; done
    rm -rf "$BATCH/.parts"
    while read -r file; do
        entries=("$file")
        if [ "$(stat -c %s "$BATCH/$file")" -gt "$budget" ] && [ "$(basename "$file")" = policy.npz ]; then
            mapfile -t entries < <(policy_parts "$file" "$budget")
        fi
        for entry in "${entries[@]}"; do
            size=$(stat -c %s "$(packed_path "$entry")")
            placed=
            for ((i = 0; i < tars; i++)); do
                if [ $((used[i] + size)) -le "$budget" ]; then
                    used[i]=$((used[i] + size))
                    assigned+=("$i $entry")
                    placed=1
                    break
                fi
            done
            [ -n "$placed" ] \
                || echo "policy left out (over POLICY_TARS=$tars tars of POLICY_MIB=${POLICY_MIB:-15}): $entry"
        done
    done < <(run_policies)
    for ((i = 0; i < tars; i++)); do
        name=policies.tar
        [ "$i" -eq 0 ] || name=policies-$((i + 1)).tar
        packed=() parts=()
        for entry in "${assigned[@]}"; do
            [ "${entry%% *}" = "$i" ] || continue
            case ${entry#* } in *.part-*-of-*) parts+=("${entry#* }") ;; *) packed+=("${entry#* }") ;; esac
        done
        if [ $((${#packed[@]} + ${#parts[@]})) -eq 0 ]; then
            rm -f "$OUT/$name"
            continue
        fi
        args=(-C "$BATCH" "${packed[@]}")
        [ ${#parts[@]} -eq 0 ] || args+=(-C .parts "${parts[@]}")  # relative to $BATCH, tar's first -C
        tar cf "$OUT/.$name" "${args[@]}" && mv "$OUT/.$name" "$OUT/$name"
    done
}

# Wait until the epoch second DEADLINE or until no run is left, packing $OUT every SNAPSHOT_EVERY seconds (default
# 60) on the way, so that a call stopped at its limit still returns the last pack; then pack and print the report
# (made once: the packed report.txt, or the report itself without OUT).
report_until() {  # DEADLINE
    local packed
    packed=$(date +%s)
    while [ "$(date +%s)" -lt "$1" ] && pgrep -f "lnnmpc[.](train[.]cli train|experiments[.]run)" >/dev/null; do
        sleep 1
        if [ $(($(date +%s) - packed)) -ge "${SNAPSHOT_EVERY:-60}" ]; then
            pack_out
            packed=$(date +%s)
        fi
    done
    if [ -n "${OUT:-}" ]; then
        pack_out
        cat "$OUT/report.txt"
    else
        print_report
    fi
}

case $action in
start)
    jobs=${1:?JOBS file}
    seconds=${2:?SECONDS}
    report=${3:?REPORT}
    [[ $seconds =~ ^[0-9]+$ ]] || { echo "start: SECONDS must be a whole number of seconds, not '$seconds'" >&2; exit 2; }
    lint_jobs "$jobs" || exit 2
    if [ -n "${ONLY:-}" ]; then
        jobs=$(select_jobs "$jobs" "$ONLY") || exit 2
        trap 'rm -f "$jobs"' EXIT
    fi
    deadline=$(($(date +%s) + report))  # counted from here: a relaunch's wait for its earlier process included
    mkdir -p "$BATCH" runs/jaxcache
    date +%s >"$BATCH/started"
    count=$(job_lines "$jobs" | wc -l)
    gpus=$(nvidia-smi -L 2>/dev/null | grep -c '^GPU' || true)
    [ "${gpus:-0}" -ge 1 ] || gpus=1
    all_alone "$jobs" || exit 2
    placement=$(place_jobs "$jobs" "$gpus") || exit 2
    # A job of this file that an earlier start launched is relaunched: its run resumes from its checkpoint, so it
    # waits (RELAUNCH_WAIT seconds at most, default 300) for the earlier process, which after its timeout's SIGTERM
    # still finishes its chunk and writes that checkpoint; two processes must not train in one run folder.
    for name in $(job_lines "$jobs" | awk '{print $1}' | sed 's/@.*//'); do
        batch_jobs | grep -qxF "$name" || continue
        waited=0
        until settle_gone "$name"; do
            if [ "$waited" -ge "${RELAUNCH_WAIT:-300}" ]; then
                echo "$name: its earlier launch still runs after ${RELAUNCH_WAIT:-300} s (no $BATCH/$name.rc):" \
                    "not relaunched" >&2
                exit 2
            fi
            sleep 2
            waited=$((waited + 2))
        done
    done
    running=$(still_running)
    if [ -n "$running" ] && [ "${FORCE:-0}" != 1 ]; then
        echo "jobs of an earlier start still run (no $BATCH/<name>.rc yet): $running; 'wait' for them first," \
            "or FORCE=1 to start beside them" >&2
        exit 2
    fi
    per_gpu=$(echo "$placement" | awk '{print $2}' | sort | uniq -c | sort -rn | awk 'NR == 1 {print $1}')
    echo "$count jobs on $gpus GPU(s), up to $per_gpu per GPU" | tee "$BATCH/gpus.txt"
    if [ "${MPS:-1}" = 1 ] && command -v nvidia-cuda-mps-control >/dev/null; then
        nvidia-cuda-mps-control -d && sleep 1
        if python3 -c "import jax, jax.numpy as jnp; assert float(jnp.ones(4).sum()) == 4.0" 2>/dev/null; then
            echo "CUDA MPS on" | tee "$BATCH/mps.txt"
        else
            echo quit | nvidia-cuda-mps-control
            echo "CUDA MPS failed a JAX check: off" | tee "$BATCH/mps.txt"
        fi
    else
        echo "CUDA MPS not used" | tee "$BATCH/mps.txt"
    fi
    # the jobs that ended at an earlier launch of the same line: reported, not launched, and no GPU's share
    skipped=$(job_lines "$jobs" | while read -r name args; do
        name=${name%@*}
        finished_before "$name" "$args" && echo "$name"
    done)
    launching=$(echo "$placement" | awk 'NR == FNR { skip[$1]; next } !($1 in skip)' <(echo "$skipped") -)
    index=0
    job_lines "$jobs" | while read -r name args; do
        index=$((index + 1))
        read -r name gpu < <(echo "$placement" | sed -n "${index}p")
        if echo "$skipped" | grep -qxF "$name"; then
            echo "$name: ended (exit 0) at an earlier launch of this line: not launched again (RERUN=1 relaunches)"
            continue
        fi
        sharing=$(echo "$launching" | awk -v g="$gpu" '$2 == g' | wc -l)
        export XLA_PYTHON_CLIENT_MEM_FRACTION=${MEM_FRACTION:-$(awk -v n="$sharing" 'BEGIN {print int(900 / n) / 1000}')}
        command=$(job_command "$name" "$args" "$BATCH" "--compile-cache runs/jaxcache" "")
        if [ "${args%% *}" = experiment ]; then  # a study stopped while training still evaluates what it has
            command="bash '$SCRIPTS/run_until.sh' $BATCH/$name.deadline $command; timeout -s TERM ${EVAL_SECONDS:-300} $command --no-train"
        else
            command="bash '$SCRIPTS/run_until.sh' $BATCH/$name.deadline $command"
        fi
        # the job's end (NAME.rc, for `after`) and its wall seconds from launch to exit (NAME.seconds: a speed
        # bar's "including compilation", the process's start and exit included)
        took="echo \"\$(date +%s.%N) \$begun\" | awk '{printf \"%.1f\\n\", \$1 - \$2}' >$BATCH/$name.seconds"
        command="echo \$\$ >$BATCH/$name.pid; begun=\$(date +%s.%N); $command; rc=\$?; $took; echo \$rc >$BATCH/$name.rc"
        if [ -f "$BATCH/$name.rc" ]; then  # relaunched: the earlier launches' wall seconds kept, its log appended
            cat "$BATCH/$name.seconds" >>"$BATCH/$name.earlier-seconds" 2>/dev/null
            rm -f "$BATCH/$name.rc" "$BATCH/$name.seconds" "$BATCH/$name.pid"
        fi
        echo $(($(date +%s) + seconds)) >"$BATCH/$name.deadline"  # the SIGTERM limit, which `extend` moves
        visible=$gpu
        [ "$gpu" = all ] && visible=$(seq -s, 0 $((gpus - 1)))
        CUDA_VISIBLE_DEVICES=$visible setsid nohup bash -c "$command" >>"$BATCH/$name.log" 2>&1 </dev/null &
        echo "$name (GPU $gpu): $args" | tee -a "$BATCH/commands.txt"
    done
    report_until "$deadline"
    ;;
wait)
    [ -f "$BATCH/started" ] || { echo "no batch on this machine ($BATCH/started is missing): the machine that ran"\
        "'start' went back (idle release) and this is a fresh one; its runs and checkpoints are gone" >&2; exit 1; }
    report_until $(($(date +%s) + ${1:?REPORT}))
    ;;
extend)
    add=${1:?SECONDS}
    shift
    [[ $add =~ ^-?[0-9]+$ ]] || { echo "extend: SECONDS must be a whole number of seconds (negative: sooner), not"\
        "'$add'" >&2; exit 2; }
    running=$(still_running)
    names=("$@")
    [ ${#names[@]} -gt 0 ] || read -ra names <<<"$running"
    [ ${#names[@]} -gt 0 ] || { echo "extend: no job of this machine's batch is running (each has its" \
        "$BATCH/<name>.rc)" >&2; exit 2; }
    status=0
    for name in "${names[@]}"; do
        if [[ " $running" != *" $name "* ]]; then
            echo "extend: '$name' is no running job (running: ${running:-none})" >&2
            status=2
        elif [ ! -f "$BATCH/$name.deadline" ]; then
            echo "extend: $name has no $BATCH/$name.deadline (launched under \`timeout\`): its limit cannot move" >&2
            status=2
        else
            limit=$(($(cat "$BATCH/$name.deadline") + add))
            echo "$limit" >"$BATCH/$name.deadline.new" && mv "$BATCH/$name.deadline.new" "$BATCH/$name.deadline"
            echo "$name: limit moved by $add s: SIGTERM in $((limit - $(date +%s))) s"
        fi
    done
    exit $status
    ;;
after)
    name=${1:?NAME of a job of the running batch}
    gpu=${2:?GPU}
    shift 2
    [ $# -ge 1 ] || { echo "after: give the command to run once $name has ended" >&2; exit 2; }
    [[ $gpu =~ ^[0-9]+$ ]] || { echo "after: bad GPU '$gpu': give a number" >&2; exit 2; }
    if ! batch_jobs | grep -qxF "$name"; then
        known=$(batch_jobs | tr '\n' ' ')
        echo "after: no job '$name' in $BATCH/commands.txt (jobs: ${known:-none})" >&2
        exit 2
    fi
    command=$(printf '%q ' "$@")
    export BATCH
    export -f settle_gone  # the background wait decides "ended" as start and the report do
    CUDA_VISIBLE_DEVICES=$gpu setsid nohup bash -c "until settle_gone $name; do sleep ${AFTER_POLL:-5}; done; \
        echo \"$name ended (exit \$(cat $BATCH/$name.rc)) at \$(date -u +%T); running on GPU $gpu\"; $command" \
        >"$BATCH/after-$name.log" 2>&1 </dev/null &
    echo "after $name (GPU $gpu): $*" | tee -a "$BATCH/commands.txt"
    ;;
check)
    jobs=${1:?JOBS file}
    scratch=$(mktemp -d)
    failed=0
    lint_jobs "$jobs" || failed=1
    all_alone "$jobs" || failed=1
    while read -r name args; do
        if ! split=$(split_name "$name" 2>&1); then
            echo "FAILED  $name: $split"
            failed=1
            continue
        fi
        read -r name gpu <<<"$split"
        command=$(job_command "$name" "$args" "$scratch" --check --dry-run)
        # An "@all" job's `--devices N` is checked against N host devices: this CPU has one, the GPU machine N
        devices=1
        if [ "${gpu:-}" = all ] && [[ " $args " =~ \ --devices\ ([0-9]+)\  ]]; then
            devices=${BASH_REMATCH[1]}
        fi
        # shellcheck disable=SC2086  # the arguments are meant to split
        if output=$(XLA_FLAGS="${XLA_FLAGS:-} --xla_force_host_platform_device_count=$devices" $command 2>&1 \
            </dev/null); then
            echo "ok      $name"
        else
            echo "FAILED  $name: $(echo "$output" | grep -E '^error|Error' | tail -1)"
            failed=1
        fi
    done < <(job_lines "$jobs")
    rm -rf "$scratch"
    exit $failed
    ;;
lint)
    [ $# -ge 1 ] || { echo "lint: give one or more JOBS files" >&2; exit 2; }
    failed=0
    for jobs in "$@"; do
        lint_jobs "$jobs" || failed=1
    done
    [ "$failed" = 0 ] && echo "ok      $# jobs file(s)"
    exit $failed
    ;;
*)
    echo "unknown action $action (start, wait, extend, after, check or lint)" >&2
    exit 2
    ;;
esac
