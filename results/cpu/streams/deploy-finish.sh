#!/usr/bin/env bash
# After deploy.sh: the deploy-g1k1 student's compact actors (exported beside the student's), its
# evaluation (a finished evaluation grows with the new student), then the report. Rerun to continue.
set -euo pipefail
D="divmorph"; O="--run results/cpu --no-progress"
$D export $O > results/cpu/logs/export-deploy.out 2>&1
$D evaluate $O > results/cpu/logs/evaluate-deploy.out 2>&1
$D report $O > results/cpu/logs/report-deploy.out 2>&1
