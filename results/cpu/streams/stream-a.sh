#!/usr/bin/env bash
# Stream a of the cpu run after the teachers (one core): the DivMorph student, then its transfer arm.
# Resumable: rerun to continue.
set -euo pipefail
D="divmorph"; O="--profile cpu --out results/cpu --no-progress"
$D distill $O --students divmorph
$D transfer $O --arms divmorph
