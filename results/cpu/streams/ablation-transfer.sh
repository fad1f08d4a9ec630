#!/usr/bin/env bash
# Transfer of one ablation arm of the cpu run (3 novel tasks x 2 seeds x 60k steps, as every arm),
# once its student is distilled (streams/ablations.sh). Resumable: rerun to continue.
#   bash results/cpu/streams/ablation-transfer.sh no-kdiv-transformer
set -euo pipefail
until [ -f "results/cpu/students/$1/done.json" ]; do sleep 30; done
divmorph transfer --run results/cpu --no-progress --arms "$1"
