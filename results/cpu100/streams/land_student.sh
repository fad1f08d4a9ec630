#!/usr/bin/env bash
# Lands a finished student of the 100-robot run before it is committed: re-saves its model without the
# optimiser state (bit-identical weights and actions, tools/slim_models.py), then checks it against
# the teachers on the 100 training robots -- both through the same `divmorph evaluate` (same robots,
# seed, episodes and env settings) -- into checks/<name>/ (README with the paired shares, returns.csv).
# The evaluation stage repeats this with 3 episodes per robot and the novel robots.
#   bash results/cpu100/streams/land_student.sh student              # the DivMorph student
#   bash results/cpu100/streams/land_student.sh students/distilled   # the dense MetaMorph⚗ student
#   bash results/cpu100/streams/land_student.sh hyperdistill/student # HyperDistill
set -euo pipefail
folder=${1:?usage: land_student.sh student|students/<name>|hyperdistill/student}
RUN=results/cpu100
case $folder in
  student) label=student ;;
  students/*) label=student-${folder#students/} ;;
  hyperdistill/student) label=hyperdistill ;;
  *) echo "unknown student folder $folder" >&2; exit 2 ;;
esac
check=$RUN/checks/$label
[ -f "$RUN/$folder/done.json" ] || { echo "$RUN/$folder has not finished (no done.json)" >&2; exit 1; }
python tools/slim_models.py --write "$RUN/$folder"
tmp=$(mktemp -d)
start=$(date +%s)
divmorph evaluate --run "$RUN" --model teacher --model teacher-untrained --model "$label" --split train --episodes 1 \
  --task FT --task VT --task Incline --task Obstacle --task Patrol --into "$tmp" --no-progress
seconds=$(( $(date +%s) - start ))
mkdir -p "$check"
cp "$tmp/returns.csv" "$check/"
rm -rf "$tmp"
python - "$check" "$label" "$seconds" "$folder" <<'PY'
import csv, platform, sys, time
from pathlib import Path
import torch
from divmorph.pipeline.config import load_profile
from divmorph.pipeline.report import returns_table, student_shares
check, label, seconds, folder = Path(sys.argv[1]), sys.argv[2], sys.argv[3], sys.argv[4]
rows = list(csv.DictReader(open(check / "returns.csv")))
table, _ = returns_table(rows)
text = [
    f"# Check of `{label}` against the teachers: training robots only",
    "",
    "Deterministic return on each of the 100 training robots (1 episode per robot, seed 0), the student and its "
    "teachers through the same `divmorph evaluate`; the evaluation stage repeats it with 3 episodes and the novel robots.",
    "",
    "```bash",
    f"bash results/cpu100/streams/land_student.sh {folder}",
    "```",
    "",
    *student_shares(load_profile("cpu100"), rows)[2:],
    "",
    *table,
    "",
    f"Written {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} on {platform.machine()} (2 cores), torch "
    f"{torch.__version__}, 1 thread; the evaluation took {seconds} s. Per-robot returns: `returns.csv`.",
]
(check / "README.md").write_text("\n".join(text) + "\n")
print("\n".join(text))
PY
echo "landed $label: $check"
