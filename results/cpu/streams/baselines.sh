#!/usr/bin/env bash
# The baselines' transfer arms on the cpu run (same 3 novel tasks, 2 seeds, 60k steps as the other arms),
# two streams, one per core:
#   stream grl:       GRL's evolution (grl defaults: 8 agents x 3 generations x 50k PPO steps on the
#                     training tasks), then the grl arm
#   stream modumorph: the modumorph arm (ModuMorph from scratch)
# Resumable: rerun to continue. Then: divmorph evaluate / report --run results/cpu
set -euo pipefail
D="divmorph"; O="--run results/cpu --no-progress"
case "${1:-}" in
  grl) $D grl $O && $D transfer $O --arms grl ;;
  modumorph) $D transfer $O --arms modumorph ;;
  *) echo "usage: $0 grl|modumorph" >&2; exit 2 ;;
esac
