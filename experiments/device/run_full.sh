#!/usr/bin/env bash
# `jaxinertia reproduce --full` on the lent GPU machine, under the folds' timeline (issue 30,
# item 4): the run this project's GPU numbers come from (docs/benchmarks.md).
#
# Here, once:   make device-bundle          (.device/: the wheels the device image lacks, for
#                                            its Python 3.12, and a copy of the lbipe folder)
# Then one `run` of the device tool, carry [".device"]:
#   bash experiments/device/run_full.sh NAME [REPRODUCE ARGS...]    (e.g. --draws 1)
# Cold by default (JAXINERTIA_CACHE_DIR=off unless set); SCALE= (empty) runs the quick scale,
# as a check of the script on a CPU. Back in $OUT/NAME.tgz: the run's
# report, tables.json and model configs (no .npz, no .png), the timeline, its stage sums
# (experiments/timeline_stages.py) and the log with `time`'s line.
set -euo pipefail
name=${1:?usage: experiments/device/run_full.sh NAME [REPRODUCE ARGS...]}
shift
: "${OUT:?OUT: the output folder of the device tool}"
here=$(pwd)
site=/tmp/jaxinertia-site
rm -rf "$site"
pip install -q --no-index --no-deps --target "$site" .device/wheels/*.whl
pip install -q --no-deps --no-build-isolation --target "$site" .
export PYTHONPATH="$site" JAXINERTIA_CACHE_DIR="${JAXINERTIA_CACHE_DIR:-off}"
work=/tmp/jaxinertia-runs/$name
mkdir -p "$work"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv > "$work/device.txt" 2>&1 || true
{ time python experiments/fold_timeline.py --timeline "$work/timeline.txt" -- \
    ${SCALE---full} --out "$work/run" --lbipe-dir .device/lbipe "$@" ; } > "$work/log.txt" 2>&1 \
  || echo "reproduce failed: $?" >> "$work/log.txt"
python experiments/timeline_stages.py "$work/timeline.txt" > "$work/stages.txt" 2>&1 || true
tail -3 "$work/log.txt"
cat "$work/stages.txt"
cd /tmp/jaxinertia-runs && tar czf "$OUT/$name.tgz" --exclude='*.npz' --exclude='*.png' "$name"
cd "$here"
