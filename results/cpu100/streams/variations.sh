#!/usr/bin/env bash
# Zero-shot on variations of the training robots (issue 43 item 5), as MetaMorph reports it: one
# kinematic and one dynamic variant of each of the 100 official training robots (seed 0), and the
# run's FT and Patrol teacher, DivMorph student and HyperDistill student on them, 3 deterministic
# episodes per robot. A variation set is made again by the same command (the same bytes); the
# rows go to results/cpu100/variations/<kind>/returns.csv (split "ood": the variation set).
#   PATH=$PWD/.venv/bin:$PATH bash results/cpu100/streams/variations.sh [jobs]
set -euo pipefail
RUN=results/cpu100
for kind in kinematic dynamic; do
  unimal-morphologies mutate unimals100-train --kind "$kind" --seed 0 --quiet
done
CACHE=${UNIMAL_DATA:-${XDG_CACHE_HOME:-$HOME/.cache}/unimal_envs}
evaluate() {  # kind task
  divmorph evaluate --run "$RUN" --no-progress --set "ood_set=$CACHE/variations/unimals100-train-$1-s0" \
    --model teacher --model student --model hyperdistill --task "$2" --split ood --episodes 3 \
    --into "$RUN/variations/$1-$2"
}
evaluate kinematic FT & evaluate dynamic FT & wait
evaluate kinematic Patrol & evaluate dynamic Patrol & wait
