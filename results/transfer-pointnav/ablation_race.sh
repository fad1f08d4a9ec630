#!/usr/bin/env bash
# The paper's ablations in the 600k transfer race (issue 42; results/transfer-pointnav/race-600k-rule.md,
# the 16:49 addendum and the last one).
#
# Each ablated student -- no diversion in the Transformer, none in the decoder, free (not Cayley-orthogonal)
# square factors -- is distilled like the cpu100 DivMorph student (`divmorph distill --students <name>` in a
# branch of results/cpu100: the same teachers, profile, seed and 1M DAgger steps), its many-draw starts are
# measured (results/novel-task-gates/novel_task_gates.py), and it races on the DivMorph arm's terms (results/finetune-known-task/finetune_known_task.py:
# the closest training task's gates, the race's rates, 602,112 steps, 20 training robots x 5 episodes at every
# 200,704 steps), PointNav's nine runs first, then Escape's, then Exploration's.
#
# The jobs are a list in order of priority, worked by any number of workers. A worker takes the first job that
# nobody has claimed and that can start -- a student's starts and races wait until it is distilled, and meanwhile
# the worker takes later jobs rather than leave its core idle -- and claims it by creating its folder under CLAIMS
# (mkdir is atomic), so two workers never run the same job. Every job resumes from its last checkpoint or skips what
# is finished, so after an interruption start the workers again with a fresh CLAIMS folder. A student whose
# distillation fails is marked (ablate-<name>/FAILED, cleared when it distils again) and its jobs are skipped with a
# message. One worker per core:
#
#     git worktree add /work/wt-abl e61a1b2    # the commit the race's students are distilled and raced with
#     for i in 1 2; do CODE=/work/wt-abl WORK=/work nohup bash results/transfer-pointnav/ablation_race.sh /work/claims-1 >> ablation.log 2>&1 & done
#
# Results (per task, when its runs have finished; models are not kept):
#
#     python tools/pack_transfer_runs.py results/transfer-pointnav/runs-600k $WORK/race600/PointNav-no-orthogonality=PointNav-no-orthogonality
#
# Environment: CODE (the checkout whose code runs; default: this one), WORK (where the branches, starts and races
# go; default: runs/ablation-race), PY (default: this checkout's .venv/bin/python), POLL (seconds between looks for
# a student still distilling; default 60).
set -u
CLAIMS=${1:?usage: ablation_race.sh CLAIMS_FOLDER}
REPO=$(cd "$(dirname "$0")/../.." && pwd)
CODE=$(cd "${CODE:-$REPO}" && pwd) || exit 1
WORK=${WORK:-$REPO/runs/ablation-race}
PY=${PY:-$REPO/.venv/bin/python}
POLL=${POLL:-60}
mkdir -p "$CLAIMS" "$WORK/race600" || exit 1
# absolute, since the jobs run from $CODE
CLAIMS=$(cd "$CLAIMS" && pwd)
WORK=$(cd "$WORK" && pwd)
export PYTHONPATH=$CODE MUJOCO_GL=${MUJOCO_GL:-egl} HF_HUB_OFFLINE=1 TRANSFORMERS_OFFLINE=1
cd "$CODE" || exit 1

STUDENTS=(no-orthogonality no-kdiv-transformer no-kdiv-decoder)
# the distillations first: the longest jobs, on which everything else waits
JOBS=()
for student in "${STUDENTS[@]}"; do JOBS+=("distill $student"); done
for student in "${STUDENTS[@]}"; do JOBS+=("starts $student"); done
for task in PointNav Escape Exploration; do
    for student in "${STUDENTS[@]}"; do
        for seed in 0 1 2; do JOBS+=("race $student $task $seed"); done
    done
done

# distill STUDENT: DAgger into the ablated student, in its own branch of results/cpu100
distill() {
    [ -f "$WORK/ablate-$1/run.json" ] || "$PY" -m divmorph.cli branch --from results/cpu100 --out "$WORK/ablate-$1" || return
    rm -f "$WORK/ablate-$1/FAILED"
    "$PY" -m divmorph.cli distill --run "$WORK/ablate-$1" --no-progress --students "$1" || {
        local status=$?
        touch "$WORK/ablate-$1/FAILED"
        return $status
    }
}

distilled() {
    [ -f "$WORK/ablate-$1/students/$1/done.json" ]
}

failed() {
    [ -f "$WORK/ablate-$1/FAILED" ] && ! distilled "$1"
}

# ready JOB...: the job can start now (a distillation always can; the others once their student is distilled,
# or has failed, which they report)
ready() {
    [ "$1" = distill ] || distilled "$2" || failed "$2"
}

# starts STUDENT: its mean return over many draws, told each novel task's instruction and the closest task's
starts() {
    failed "$1" && { echo "not run: $1 failed to distil"; return 1; }
    [ -f "$WORK/starts-$1/finished" ] && return 0
    "$PY" results/novel-task-gates/novel_task_gates.py --run "$WORK/ablate-$1" --out "$WORK/starts-$1" --students "$1" --eval-seeds 0 1 2 3 4 &&
        touch "$WORK/starts-$1/finished"
}

# race STUDENT TASK SEED: one run of the race, in a branch shared by the student's three seeds on the task
race() {
    failed "$1" && { echo "not run: $1 failed to distil"; return 1; }
    local out=$WORK/race600/$2-$1
    # the seeds' workers would otherwise race to create the same branch
    (
        flock 9 || exit 1
        [ -f "$out/run.json" ] || "$PY" -c "import sys; from pathlib import Path; from divmorph.pipeline.branch import branch; \
branch(Path(sys.argv[1]), Path(sys.argv[2]), ('teachers', 'distill'), command='python results/finetune-known-task/finetune_known_task.py')" \
            "$WORK/ablate-$1" "$out"
    ) 9> "$WORK/race600/.branch-lock" || return
    "$PY" results/finetune-known-task/finetune_known_task.py --source "$WORK/ablate-$1" --task "$2" --steps 602112 --eval-every 200704 \
        --set transfer.eval_episodes=5 --set transfer.task_gates=closest --arms "$1" --seeds "$3" --out "$out"
}

# Scan the list from the top after every job, so a job that becomes ready goes before lower-priority ones.
while :; do
    unclaimed=0
    for i in "${!JOBS[@]}"; do
        [ -d "$CLAIMS/$i" ] && continue
        unclaimed=1
        # shellcheck disable=SC2086  # a job is words without spaces or patterns: split on purpose
        ready ${JOBS[$i]} && mkdir "$CLAIMS/$i" 2> /dev/null || continue
        echo "[$(date -u '+%F %T')] worker $$ starts job $i: ${JOBS[$i]}"
        ${JOBS[$i]}
        status=$?
        echo "[$(date -u '+%F %T')] worker $$ ends job $i (exit $status): ${JOBS[$i]}"
        continue 2
    done
    [ $unclaimed = 0 ] && break
    sleep "$POLL"
done
