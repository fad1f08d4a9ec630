#!/usr/bin/env bash
# Stream a of the cpu run after the teachers (one core): the DivMorph student, its transfer arm,
# the deployment student, and the scratch arm on Exploration. Resumable: rerun to continue.
set -euo pipefail
D="divmorph"; O="--profile cpu --out results/cpu --no-progress"
$D distill $O --students divmorph --force
$D transfer $O --arms divmorph
$D distill $O --students deploy-g1k1
$D transfer $O --arms scratch --task Exploration
