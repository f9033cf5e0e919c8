#!/usr/bin/env bash
# The GPU check in one call (see benchmarks/gpu_check.py): run from anywhere in the repository
# on a machine with an NVIDIA GPU, e.g. through the device tool:
#   run(command="bash benchmarks/gpu_check.sh", carry=[".whl"], timeout_s=540)
# Wheels the machine lacks travel in .whl/ (ignored by git: echo /.whl/ >> .git/info/exclude);
# split ones are reassembled by the script. The full log lands in $OUT (or --out DIR); the short
# table is printed last. Without a GPU (or with --no-gpu) it checks its own plumbing.
set -uo pipefail
cd "$(dirname "$0")/.." || exit 2
OUT="${OUT:-benchmarks/results/gpu_check}"
mkdir -p "$OUT"
export OUT PYTHONUNBUFFERED=1
PYTHON="${PYTHON:-python3}"
# 8 minutes at most; the script itself stops starting checks after its --budget-s (450 s).
timeout 480 "$PYTHON" -m benchmarks.gpu_check --out "$OUT" "$@" 2>&1 | tee "$OUT/console.log"
exit "${PIPESTATUS[0]}"
