#!/usr/bin/env bash
# Run COMMAND until the epoch second written in DEADLINE_FILE, then send it SIGTERM once and exit 124 after it has
# ended, as `timeout -s TERM` does (a training run then saves a checkpoint after its running chunk); otherwise exit
# with COMMAND's status. The file is read again every DEADLINE_POLL seconds (default 1), so that
# `device_batch.sh extend` can move the limit of a run already launched; an unreadable or garbled file keeps the
# last limit read (none read yet: the command is stopped at once, since no limit was ever set).
#
#   run_until.sh DEADLINE_FILE COMMAND...
set -u
deadline_file=${1:?DEADLINE_FILE}
shift
[ $# -ge 1 ] || { echo "run_until.sh: give the command to run" >&2; exit 2; }
"$@" &
pid=$!
deadline=0
termed=0
while kill -0 "$pid" 2>/dev/null; do
    limit=$(cat "$deadline_file" 2>/dev/null)
    [[ $limit =~ ^[0-9]+$ ]] && deadline=$limit
    if [ "$(date +%s)" -ge "$deadline" ]; then
        kill -TERM "$pid" 2>/dev/null && termed=1
        break
    fi
    sleep "${DEADLINE_POLL:-1}"
done
wait "$pid"
rc=$?
[ "$termed" = 1 ] && exit 124
exit $rc
