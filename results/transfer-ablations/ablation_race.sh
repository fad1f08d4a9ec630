#!/usr/bin/env bash
# The paper's ablations in the 600k transfer race, without the learning-rate confound (issue 67 item 4; the reading:
# results/transfer-recipes/rule.md, the 13:50 addendum and the terms of 2026-12-06 16:50).
#
# Four students are distilled alike, each in its own branch of results/cpu100 that reuses only the teachers
# (`divmorph distill --students <name> --set distill.n_timesteps=400000`: the same teachers, profile and seed, 400k
# DAgger steps): the DivMorph student, the comparator, and its three ablations -- no diversion in the Transformer,
# none in the decoder, free (not Cayley-orthogonal) square factors. Each races under G's terms (the fixed-gate rule
# at the dense student's rate: learngenes at 1x, rotations frozen, the undiverted part at 1x;
# results/finetune-known-task/finetune_known_task.py, 602,112 steps, 20 training robots x 5 episodes at every
# 200,704 steps): Escape from the low start (told Incline's instruction) first, then bounded-goal PointNav
# (goal_range 10, Patrol's gates). Each race folder's start is then measured: 5 evaluation seeds x 3 episodes,
# told what its runs are told.
#
# What outlives the machine: a finished student (its model, statistics and logs) is copied into KEPT_STUDENTS, and a
# finished run's or start's small files (done.json, source.json, its evaluations and a table of its updates, packed
# by tools/pack_transfer_runs.py; baseline.json) into KEEP, a tracked folder, as the job ends; a later session's job finds them there and restores
# the student or skips the run. A distillation cannot resume across machines (its aggregated dataset is ~1 GB), so
# it must finish within one. The four students (3.4 MB) would take the tracked files over their 24 MiB limit: they
# live in commit 63b877b, not in the tree (README.md: how to take them out of it).
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
#     git worktree add /work/wt-abl <commit>    # the commit the race is run with (README.md names it)
#     mkdir -p /work/abl-students && git archive 63b877b results/transfer-ablations/kept/students | tar -x --strip-components=4 -C /work/abl-students
#     for i in 1 2; do CODE=/work/wt-abl WORK=/work/abl-race KEEP=$PWD/results/transfer-ablations/kept KEPT_STUDENTS=/work/abl-students PY=$PWD/.venv/bin/python nohup bash /work/wt-abl/results/transfer-ablations/ablation_race.sh /work/abl-race/claims-1 >> ablation.log 2>&1 & done
#
# Results: python results/transfer-ablations/collect.py --from results/transfer-ablations/kept/race, then read.py
# (README.md says what they show).
#
# Environment: CODE (the checkout whose code runs; default: this one), WORK (where the branches, races and starts
# go; default: runs/ablation-race), KEEP (the tracked folder of finished runs; default: this checkout's
# results/transfer-ablations/kept), KEPT_STUDENTS (the folder of finished students; default: KEEP/students), PY
# (default: this checkout's .venv/bin/python), POLL (seconds between looks for a
# job that cannot start yet; default 60).
set -u
CLAIMS=${1:?usage: ablation_race.sh CLAIMS_FOLDER}
REPO=$(cd "$(dirname "$0")/../.." && pwd)
CODE=$(cd "${CODE:-$REPO}" && pwd) || exit 1
WORK=${WORK:-$REPO/runs/ablation-race}
KEEP=${KEEP:-$REPO/results/transfer-ablations/kept}
PY=${PY:-$REPO/.venv/bin/python}
POLL=${POLL:-60}
mkdir -p "$CLAIMS" "$WORK/race" "$KEEP" || exit 1
# absolute, since the jobs run from $CODE
CLAIMS=$(cd "$CLAIMS" && pwd)
WORK=$(cd "$WORK" && pwd)
KEEP=$(cd "$KEEP" && pwd)
KEPT_STUDENTS=${KEPT_STUDENTS:-$KEEP/students}
mkdir -p "$KEPT_STUDENTS" && KEPT_STUDENTS=$(cd "$KEPT_STUDENTS" && pwd) || exit 1
DISTILL_STEPS=400000
export PYTHONPATH=$CODE MUJOCO_GL=${MUJOCO_GL:-egl} HF_HUB_OFFLINE=1 TRANSFORMERS_OFFLINE=1
cd "$CODE" || exit 1

STUDENTS=(no-kdiv-transformer no-kdiv-decoder no-orthogonality divmorph)
# the distillations first: the longest jobs, on which the races wait
JOBS=()
for student in "${STUDENTS[@]}"; do JOBS+=("distill $student"); done
for student in "${STUDENTS[@]}"; do
    for seed in 0 1 2; do JOBS+=("race $student Escape $seed"); done
done
for student in "${STUDENTS[@]}"; do
    for seed in 0 1 2; do JOBS+=("race $student PointNav $seed"); done
done
for task in Escape PointNav; do
    for student in "${STUDENTS[@]}"; do JOBS+=("starts $student $task"); done
done

# the student's folder in its branch (the DivMorph student's is the run's `student`)
student_dir() {
    if [ "$1" = divmorph ]; then echo "$WORK/distill-$1/student"; else echo "$WORK/distill-$1/students/$1"; fi
}

# distill STUDENT: DAgger into the student, in its own branch of results/cpu100 (teachers only); a student kept by
# an earlier session is restored instead, and a new one kept
distill() {
    local branch=$WORK/distill-$1 kept=$KEPT_STUDENTS/$1 status
    if [ ! -f "$branch/run.json" ]; then
        "$PY" -m divmorph.cli branch --from results/cpu100 --out "$branch" --stages teachers || {
            status=$?
            stopped $status || touch "$WORK/FAILED-$1"
            return $status
        }
    fi
    rm -f "$WORK/FAILED-$1"
    if [ -f "$kept/student/done.json" ] && ! distilled "$1"; then
        echo "restoring $1 from $kept"
        cp "$kept/run.json" "$kept/robot_sets.json" "$branch/" && mkdir -p "$(student_dir "$1")" &&
            cp -r "$kept/student/." "$(student_dir "$1")/"
        return
    fi
    "$PY" -m divmorph.cli distill --run "$branch" --no-progress --students "$1" --set distill.n_timesteps=$DISTILL_STEPS || {
        status=$?
        stopped $status || touch "$WORK/FAILED-$1"
        return $status
    }
    [ -f "$kept/student/done.json" ] || keep_student "$1"
}

# keep_student STUDENT: its model, statistics, done marker and logs (packed by tools/pack_logs.py), and its branch's
# settings, into KEPT_STUDENTS
keep_student() {
    local from stage=$KEPT_STUDENTS/.staging-$1
    from=$(student_dir "$1")
    rm -rf "$stage" && mkdir -p "$stage/student" || return
    cp "$WORK/distill-$1/run.json" "$WORK/distill-$1/robot_sets.json" "$stage/" || return
    cp -r "$from/model.zip" "$from/vecnormalize.pkl" "$from/done.json" "$from/logs" "$stage/student/" || return
    "$PY" tools/pack_logs.py --write "$stage/student" || return
    rm -rf "${KEPT_STUDENTS:?}/$1" && mv "$stage" "$KEPT_STUDENTS/$1"
}

# keep_run TASK STUDENT: the race folder's finished runs, packed into KEEP as tools/pack_transfer_runs.py packs a
# race (each run's evaluations, returns to 0.01, and done/source json; its updates' training return, KL, clip
# fraction and explained variance in KEEP/race/training-TASK-STUDENT.csv.gz; models and full logs stay behind).
# One packer at a time: two workers finishing seeds of one student would both rewrite its training table.
keep_run() {
    flock "$WORK/pack.lock" "$PY" tools/pack_transfer_runs.py "$KEEP/race" "$WORK/race/$1-$2=$1-$2"
}

# stopped STATUS: the job was stopped by Ctrl-C or SIGTERM (the race is being stopped), not failed
stopped() {
    [ "$1" = 130 ] || [ "$1" = 143 ]
}

# the run a student's transfers start from: its branch
source_run() {
    echo "$WORK/distill-$1"
}

distilled() {
    [ -f "$(student_dir "$1")/done.json" ]
}

failed() {
    [ -f "$WORK/FAILED-$1" ] && ! distilled "$1"
}

# begun TASK STUDENT: the race folder's first seed has begun, here or in an earlier session (kept)
begun() {
    local seed=transfer/$1/$2/seed-0/source.json
    [ -f "$WORK/race/$1-$2/$seed" ] || [ -f "$KEEP/race/$1-$2/$seed" ]
}

# ready JOB...: the job can start now (a distillation always can; a race once its student is distilled, or has
# failed, which it reports; a start once its race folder's first seed has begun: it says what the runs are told)
ready() {
    case $1 in
        distill) return 0 ;;
        race) distilled "$2" || failed "$2" ;;
        starts) failed "$2" || begun "$3" "$2" ;;
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

# race STUDENT TASK SEED: one run, in a branch shared by the student's three seeds on the task (skipped when kept)
race() {
    failed "$1" && { echo "not run: $1 failed to distil"; return 1; }
    [ -f "$KEEP/race/$2-$1/transfer/$2/$1/seed-$3/done.json" ] && { echo "kept: $2 $1 seed $3"; return 0; }
    terms "$2"
    "$PY" results/finetune-known-task/finetune_known_task.py --source "$(source_run "$1")" "${TERMS[@]}" \
        --arms "$1" --seeds "$3" --out "$WORK/race/$2-$1" || return
    keep_run "$2" "$1"
}

# starts STUDENT TASK: the student's many-draw start in its race folder (5 evaluation seeds x 3 episodes; skipped
# when kept)
starts() {
    failed "$1" && { echo "not run: $1 failed to distil"; return 1; }
    [ -f "$KEEP/race/$2-$1/baseline.json" ] && { echo "kept: the start of $1 on $2"; return 0; }
    local race=$WORK/race/$2-$1 seed=transfer/$2/$1/seed-0/source.json
    # a race folder whose runs ran in an earlier session: branched again, told what they were told (source.json)
    if [ ! -f "$race/$seed" ]; then
        [ -f "$race/run.json" ] || "$PY" -m divmorph.cli branch --from "$(source_run "$1")" --out "$race" --stages teachers,distill || return
        mkdir -p "$(dirname "$race/$seed")" && cp "$KEEP/race/$2-$1/$seed" "$race/$seed" || return
    fi
    terms "$2"
    "$PY" results/finetune-known-task/finetune_known_task.py --source "$(source_run "$1")" "${TERMS[@]}" \
        --arms "$1" --seeds 0 --out "$race" --baseline-seeds 5 --baseline-only || return
    mkdir -p "$KEEP/race/$2-$1" && cp "$race/baseline.json" "$KEEP/race/$2-$1/baseline.json.staging" &&
        mv "$KEEP/race/$2-$1/baseline.json.staging" "$KEEP/race/$2-$1/baseline.json"
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
