#!/usr/bin/env bash
# The deployment-oriented student (one tailor per gate, issue 11's deploy-g1k1) of the cpu run.
# Resumable: rerun to continue. Then: divmorph export / evaluate --redo evaluate / report --run results/cpu
set -euo pipefail
divmorph distill --profile cpu --out results/cpu --no-progress --students deploy-g1k1
