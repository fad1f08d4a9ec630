#!/usr/bin/env bash
# The HyperDistill baseline on the cpu run's own MetaMorph teachers (profile section `hyperdistill`),
# then the whole evaluation again (it depends on that section) and the report. Rerun to continue.
set -euo pipefail
D="divmorph"; O="--run results/cpu --no-progress"
$D hyperdistill $O --profile cpu --redo evaluate > results/cpu/logs/hyperdistill.out 2>&1
$D evaluate $O > results/cpu/logs/evaluate-hyperdistill.out 2>&1
$D report $O > results/cpu/logs/report-hyperdistill.out 2>&1
