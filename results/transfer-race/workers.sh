#!/usr/bin/env bash
# Start the race's workers, one per core, or start them again after an interruption (a session's end kills them;
# their runs resume from the last checkpoint). The claims of dead workers are cleared first, then the second worker
# starts only once the first holds its job, so the two never run the same one.
#
#   bash results/transfer-race/workers.sh WORKTREE RUNS KEEP [SETTING] [WORKERS] [STUDY]
#   e.g. bash results/transfer-race/workers.sh /work/wt-race /work/race "$PWD/results/transfer-race/S2" S2 2
#
# WORKTREE is a checkout at the race's commit (README.md names it), RUNS the run folders, KEEP where finished runs
# are packed (an absolute path: the workers run in WORKTREE), STUDY `race` (default) or `lowstart-diagnosis`.
# Logs: RUNS/worker-<n>.log.
set -euo pipefail
mkdir -p "$2"
worktree=$(realpath "$1") runs=$(realpath "$2") keep=$3 setting=${4:-S2} workers=${5:-2} study=${6:-race}
python=${PYTHON:-$(command -v python)}

if pgrep -f "race.py --setting $setting --runs $runs" >/dev/null; then
    echo "workers for $runs are still running (pgrep -af race.py); stop them first or leave them be" >&2
    exit 1
fi
# A new machine: the race's source, the official robots and the finished first runs' sources (which the starts
# read) are made or checked here, so that a worker does not stop on them in the background.
if [ ! -f "$runs/source/run.json" ]; then
    (cd "$worktree" && PYTHONPATH="$worktree" "$python" results/transfer-race/make_source.py "$runs/source")
fi
PYTHONPATH="$worktree" "$python" -c "from unimal_envs.morphology.cache import official_set_dir as d; d('unimals100-train'); d('unimals100-test')"
PYTHONPATH="$worktree" "$python" "$(dirname "$(realpath "$0")")/restore_runs.py" "$runs" "$keep"
rm -rf "$runs/claims" && mkdir -p "$runs/claims"
for n in $(seq 1 "$workers"); do
    before=$(find "$runs/claims" -mindepth 1 -maxdepth 1 | wc -l)
    (cd "$worktree" && nohup nice -n 19 env PYTHONPATH="$worktree" MUJOCO_GL="${MUJOCO_GL:-egl}" \
        "$python" results/transfer-race/race.py --setting "$setting" --runs "$runs" --keep "$keep" \
        $([ "$study" = race ] || echo --study "$study") \
        >>"$runs/worker-$n.log" 2>&1 &)
    [ "$n" -lt "$workers" ] || break
    for _ in $(seq 1 120); do  # the worker's claim, before the next worker looks for a free job
        [ "$(find "$runs/claims" -mindepth 1 -maxdepth 1 | wc -l)" -gt "$before" ] && break
        sleep 1
    done
done
sleep 2
echo "claimed: $(ls "$runs/claims" 2>/dev/null | tr '\n' ' ')"
