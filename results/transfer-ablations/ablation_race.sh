#!/usr/bin/env bash
# The paper's ablations in the 600k transfer race, without the learning-rate confound (issue 67 item 4; the reading:
# results/transfer-recipes/rule.md, the 13:50 addendum).
#
# Each ablated student -- no diversion in the Transformer, none in the decoder, free (not Cayley-orthogonal)
# square factors -- is distilled like the cpu100 DivMorph student (`divmorph distill --students <name>` in a
# branch of results/cpu100: the same teachers, profile, seed and 1M DAgger steps) and races under G's terms (the
# fixed-gate rule at the dense student's rate: learngenes at 1x, rotations frozen, the undiverted part at 1x;
# results/finetune-known-task/finetune_known_task.py, 602,112 steps, 20 training robots x 5 episodes at every
# 200,704 steps): Escape from the low start (told Incline's instruction) first, then bounded-goal PointNav
# (goal_range 10, Patrol's gates), where the DivMorph student itself runs the same terms as their comparator.
# Each race folder's start is then measured: 5 evaluation seeds x 3 episodes, told what its runs are told.
#
# The jobs are a list in order of priority, worked by any number of workers. A worker takes the first job that
# nobody has claimed and that can start -- a student's races wait until it is distilled, a start until its race
# folder's first seed has begun -- and meanwhile takes later jobs rather than leave its core idle; it claims a
# job by creating its folder under CLAIMS (mkdir is atomic), so two workers never run the same job. Every job
# resumes from its last checkpoint or skips what is finished; a job stopped by Ctrl-C or SIGTERM stops its worker, so
# after an interruption start the workers again with a fresh CLAIMS folder. A student whose distillation fails
# (any other exit) is marked ($WORK/FAILED-<name>, cleared when it distils again) and its jobs are skipped with a
# message. One worker per core:
#
#     git worktree add /work/wt-abl 3c9855a    # the commit the race is run with (its distillations began at 41912bd: the same distillation code)
#     for i in 1 2; do CODE=/work/wt-abl WORK=/work/abl-race PY=$PWD/.venv/bin/python nohup bash /work/wt-abl/results/transfer-ablations/ablation_race.sh /work/abl-race/claims-1 >> ablation.log 2>&1 & done
#
# Results: python results/transfer-ablations/collect.py --from $WORK/race, then read.py (README.md says what they show).
#
# Environment: CODE (the checkout whose code runs; default: this one), WORK (where the branches, races and starts
# go; default: runs/ablation-race), PY (default: this checkout's .venv/bin/python), POLL (seconds between looks for
# a job that cannot start yet; default 60).
set -u
CLAIMS=${1:?usage: ablation_race.sh CLAIMS_FOLDER}
REPO=$(cd "$(dirname "$0")/../.." && pwd)
CODE=$(cd "${CODE:-$REPO}" && pwd) || exit 1
WORK=${WORK:-$REPO/runs/ablation-race}
PY=${PY:-$REPO/.venv/bin/python}
POLL=${POLL:-60}
mkdir -p "$CLAIMS" "$WORK/race" || exit 1
# absolute, since the jobs run from $CODE
CLAIMS=$(cd "$CLAIMS" && pwd)
WORK=$(cd "$WORK" && pwd)
export PYTHONPATH=$CODE MUJOCO_GL=${MUJOCO_GL:-egl} HF_HUB_OFFLINE=1 TRANSFORMERS_OFFLINE=1
cd "$CODE" || exit 1

STUDENTS=(no-kdiv-transformer no-kdiv-decoder no-orthogonality)
# the distillations first: the longest jobs, on which the races wait
JOBS=()
for student in "${STUDENTS[@]}"; do JOBS+=("distill $student"); done
for student in "${STUDENTS[@]}"; do
    for seed in 0 1 2; do JOBS+=("race $student Escape $seed"); done
done
for student in divmorph "${STUDENTS[@]}"; do
    for seed in 0 1 2; do JOBS+=("race $student PointNav $seed"); done
done
for task in Escape PointNav; do
    for student in "${STUDENTS[@]}"; do JOBS+=("starts $student $task"); done
done
JOBS+=("starts divmorph PointNav")

# distill STUDENT: DAgger into the ablated student, in its own branch of results/cpu100
distill() {
    if [ ! -f "$WORK/ablate-$1/run.json" ]; then
        "$PY" -m divmorph.cli branch --from results/cpu100 --out "$WORK/ablate-$1" || {
            local status=$?
            stopped $status || touch "$WORK/FAILED-$1"
            return $status
        }
    fi
    rm -f "$WORK/FAILED-$1"
    "$PY" -m divmorph.cli distill --run "$WORK/ablate-$1" --no-progress --students "$1" || {
        local status=$?
        stopped $status || touch "$WORK/FAILED-$1"
        return $status
    }
}

# stopped STATUS: the job was stopped by Ctrl-C or SIGTERM (the race is being stopped), not failed
stopped() {
    [ "$1" = 130 ] || [ "$1" = 143 ]
}

# the run a student's transfers start from: the DivMorph student's own, or the ablated student's branch
source_run() {
    if [ "$1" = divmorph ]; then echo "$CODE/results/cpu100"; else echo "$WORK/ablate-$1"; fi
}

distilled() {
    [ "$1" = divmorph ] || [ -f "$WORK/ablate-$1/students/$1/done.json" ]
}

failed() {
    [ "$1" != divmorph ] && [ -f "$WORK/FAILED-$1" ] && ! distilled "$1"
}

# ready JOB...: the job can start now (a distillation always can; a race once its student is distilled, or has
# failed, which it reports; a start once its race folder's first seed has begun: it says what the runs are told)
ready() {
    case $1 in
        distill) return 0 ;;
        race) distilled "$2" || failed "$2" ;;
        starts) failed "$2" || [ -f "$WORK/race/$3-$2/transfer/$3/$2/seed-0/source.json" ] ;;
    esac
}

# terms TASK: the race's settings on the task (one array element per argument: the instruction has spaces)
terms() {
    TERMS=(--task "$1" --steps 602112 --eval-every 200704 --set transfer.eval_episodes=5
        --set transfer.learngene_lr_scale=1 --set transfer.rotation_lr_scale=0)
    case $1 in
        Escape) TERMS+=(--set transfer.task_gates=instruction
            --set "transfer.instructions.Escape=Walk forward as fast as possible up a ten degree incline.") ;;
        PointNav) TERMS+=(--set goal_range=10 --set transfer.task_gates=closest) ;;
    esac
}

# race STUDENT TASK SEED: one run, in a branch shared by the student's three seeds on the task
race() {
    failed "$1" && { echo "not run: $1 failed to distil"; return 1; }
    terms "$2"
    "$PY" results/finetune-known-task/finetune_known_task.py --source "$(source_run "$1")" "${TERMS[@]}" \
        --arms "$1" --seeds "$3" --out "$WORK/race/$2-$1"
}

# starts STUDENT TASK: the student's many-draw start in its race folder (5 evaluation seeds x 3 episodes)
starts() {
    failed "$1" && { echo "not run: $1 failed to distil"; return 1; }
    terms "$2"
    "$PY" results/finetune-known-task/finetune_known_task.py --source "$(source_run "$1")" "${TERMS[@]}" \
        --arms "$1" --seeds 0 --out "$WORK/race/$2-$1" --baseline-seeds 5 --baseline-only
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
        # a stopped job stops its worker too: a fresh CLAIMS folder resumes the list
        stopped $status && exit $status
        continue 2
    done
    [ $unclaimed = 0 ] && break
    sleep "$POLL"
done
