#!/usr/bin/env bash
# The ablation students of the cpu run (issue 17), one per core:
#   bash results/cpu/streams/ablations.sh no-kdiv-transformer &
#   bash results/cpu/streams/ablations.sh no-kdiv-decoder &
#   bash results/cpu/streams/ablations.sh no-orthogonality      # when a core is free
# Then: divmorph transfer --run results/cpu --arms no-kdiv-transformer,no-kdiv-decoder,no-orthogonality
#       divmorph evaluate --run results/cpu; divmorph report --run results/cpu
set -euo pipefail
divmorph distill --profile cpu --out results/cpu --no-progress --students "$1"
