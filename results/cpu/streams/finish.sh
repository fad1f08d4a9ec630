#!/usr/bin/env bash
# After both streams: deploy (export), evaluate (two processes, one per core), then report and renders.
# Each step skips what is done; rerun to continue.
set -euo pipefail
D="divmorph"; O="--run results/cpu --no-progress"
while pgrep -f "divmorph export" > /dev/null; do sleep 5; done  # an export started early on an idle core
$D export $O > results/cpu/logs/export.out 2>&1 &
sleep 15  # one run.json update at a time
$D evaluate $O > results/cpu/logs/evaluate.out 2>&1
wait
$D report $O > results/cpu/logs/report.out 2>&1
bash results/cpu/streams/render.sh
