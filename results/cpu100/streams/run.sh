#!/usr/bin/env bash
# The 100-robot run (issue 27, profile `cpu100`), stage after stage, as a job queue that any number of
# workers share -- one per core:
#   PATH=$PWD/.venv/bin:$PATH nohup bash results/cpu100/streams/run.sh > results/cpu100/stream-1.log 2>&1 &
#   PATH=$PWD/.venv/bin:$PATH nohup bash results/cpu100/streams/run.sh > results/cpu100/stream-2.log 2>&1 &
# A worker takes the next job nobody holds; a stage's jobs all finish before any worker starts the next
# stage's. Resumable: rerun after a stop -- finished runs are skipped, an unfinished one resumes from its
# checkpoint (a job whose worker died is taken again). Each job is a divmorph command on the run folder.
set -euo pipefail
RUN=results/cpu100
QUEUE="$RUN/streams/queue"
P="--profile cpu100 --out $RUN --no-progress"
mkdir -p "$QUEUE"

STAGES=(teachers students transfer finish merge report control)
# longest first, so that the two workers end a stage together
jobs_teachers=("teachers $P --task Obstacle" "teachers $P --task VT" "teachers $P --task Incline" "teachers $P --task Patrol"
               "teachers $P --task FT" "grl $P")
jobs_students=("distill $P --students divmorph" "distill $P --students distilled")
# The deployment student (width 64, ~3 h) and HyperDistill open the transfer stage, which needs neither
# (export and evaluation do): their cores would otherwise wait idle at the students' barrier.
jobs_transfer=("distill $P --students deploy-g1k1" "hyperdistill $P")
for task in PointNav Exploration Escape; do jobs_transfer+=("transfer $P --task $task --seeds 0"); done
# Seeds 1 and 2 (added after seed 0 took ~13-34 min a run): the four arms the transfer claims compare
# (DivMorph, scratch, MetaMorph->, MetaMorph-distilled), PointNav and Escape first; Exploration last
# (at seed 0 no arm learnt it within 500k steps). ModuMorph and GRL stay at seed 0 (the slowest arms).
# The first two keep the queue indices they had (transfer-5: PointNav seed 1, started with all arms).
A4="--arms divmorph,scratch,closest,distilled"
for seed in 1 2; do for task in PointNav Escape; do jobs_transfer+=("transfer $P --task $task --seeds $seed $A4"); done; done
for seed in 1 2; do jobs_transfer+=("transfer $P --task Exploration --seeds $seed $A4"); done
# the evaluation in two shares (one per worker), merged and finished by the plain evaluate before the report
jobs_finish=("evaluate $P --part 1/2" "evaluate $P --part 2/2" "export $P")
# one worker merges the shares (and evaluates what a lost share left); then one writes the report
jobs_merge=("evaluate $P")
jobs_report=("report --run $RUN --no-progress")
# a control after the report: scratch on each novel task for 4x the race's budget (seed 0), in a run
# folder of its own, to show where scratch gets (at 500k steps it learns little) and to turn the
# race's lower bounds on the speed-up over scratch into numbers where it gets there
# (evaluation curves every 200k steps rather than 50k: at 50k they would cost more steps than training)
C="--profile cpu100 --out results/cpu100-scratch-long --no-progress --arms scratch --seeds 0 --set transfer.n_timesteps=2000000 --set transfer.eval_every=200000"
jobs_control=("transfer $C --task PointNav" "transfer $C --task Exploration" "transfer $C --task Escape")
# ModuMorph and GRL at seeds 1 and 2 (added while the control ran, for the issue's >= 3 seeds of every
# arm), in the control stage so that a core the control leaves idle takes them: PointNav and Escape
# first, Exploration (where no arm learnt at seed 0) last. Afterwards a plain `evaluate` and `report`
# on the run take the new runs in.
for seed in 1 2; do for task in PointNav Escape; do for arm in modumorph grl; do
  jobs_control+=("transfer $P --task $task --seeds $seed --arms $arm")
done; done; done
# (slowest first: the two workers end together)
jobs_control+=("transfer $P --task Exploration --seeds 1 --arms modumorph" "transfer $P --task Exploration --seeds 1 --arms grl"
               "transfer $P --task Exploration --seeds 2 --arms grl" "transfer $P --task Exploration --seeds 2 --arms modumorph")

alive() { [ -f "$1/pid" ] && kill -0 "$(cat "$1/pid")" 2> /dev/null; }

claim() {  # take job folder $1 if nobody holds it (or its holder died without finishing)
  if mkdir "$1" 2> /dev/null; then echo $$ > "$1/pid"; return 0; fi
  # a dead holder's job: one worker wins it (the folder is named after the dead holder, made once)
  if [ ! -f "$1/done" ] && [ -f "$1/pid" ] && ! alive "$1" && mkdir "$1/after-$(cat "$1/pid" 2> /dev/null)" 2> /dev/null; then echo $$ > "$1/pid"; return 0; fi
  return 1
}

for stage in "${STAGES[@]}"; do
  declare -n list="jobs_$stage"
  for i in "${!list[@]}"; do
    job="$QUEUE/$stage-$i"
    [ -f "$job/done" ] && continue
    claim "$job" || continue
    echo "[$(date -u +%H:%M:%S)] $stage $i: divmorph ${list[$i]}"
    # shellcheck disable=SC2086
    divmorph ${list[$i]}
    touch "$job/done"
  done
  # the stage's barrier: wait for the other workers' jobs of this stage
  for i in "${!list[@]}"; do
    until [ -f "$QUEUE/$stage-$i/done" ]; do
      if [ -f "$QUEUE/$stage-$i/pid" ] && ! alive "$QUEUE/$stage-$i" && [ ! -f "$QUEUE/$stage-$i/done" ]; then
        echo "a worker of $stage $i died; rerun this script to take it over" >&2; exit 1
      fi
      sleep 30
    done
  done
done
