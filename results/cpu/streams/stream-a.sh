#!/usr/bin/env bash
# Stream a of the cpu run after the teachers (one core): the DivMorph student, then its transfer arm
# and the Exploration runs of scratch and closest. Resumable: rerun to continue.
set -euo pipefail
D="divmorph"; O="--profile cpu --out results/cpu --no-progress"
$D distill $O --students divmorph
$D transfer $O --arms divmorph
$D transfer $O --arms scratch,closest --task Exploration
