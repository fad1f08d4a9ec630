#!/usr/bin/env bash
# Stream b of the cpu run after the teachers (one core): the dense MetaMorph student, the scratch and
# closest arms (closest also on Exploration), and the distilled arm. Resumable: rerun to continue.
set -euo pipefail
D="divmorph"; O="--profile cpu --out results/cpu --no-progress"
$D distill $O --students distilled
$D transfer $O --arms scratch,closest --task Escape --task PointNav
$D transfer $O --arms closest --task Exploration
$D transfer $O --arms distilled
# (run after this script, on the same core, to balance the streams)
$D transfer $O --arms scratch --task Exploration
