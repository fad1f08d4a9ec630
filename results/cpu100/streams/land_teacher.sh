#!/usr/bin/env bash
# Lands a finished teacher of the 100-robot run before it is committed: re-saves its model without the
# optimiser state (bit-identical weights and actions, tools/slim_models.py), then checks it on the
# 100 training robots against the same policy untrained (results/cpu100-calibration/teacher_calibration.py) into
# checks/teacher-<task>/ (the figure stays out; its numbers are curves.csv).
#   bash results/cpu100/streams/land_teacher.sh VT
set -euo pipefail
task=${1:?usage: land_teacher.sh TASK}
RUN=results/cpu100
check=$RUN/checks/teacher-$task
[ -f "$RUN/teachers/$task/done.json" ] || { echo "$RUN/teachers/$task has not finished (no done.json)" >&2; exit 1; }
python tools/slim_models.py --write "$RUN/teachers/$task"
tmp=$(mktemp -d)
python results/cpu100-calibration/teacher_calibration.py --runs "$RUN" --task "$task" --out "$tmp"
mkdir -p "$check"
grep -v '\.png' "$tmp/README.md" | sed "s|$tmp|$check|g" > "$check/README.md"
cp "$tmp/returns.csv" "$tmp/curves.csv" "$check/"
rm -rf "$tmp"
echo "landed $task: $check"
