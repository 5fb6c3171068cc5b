#!/usr/bin/env bash
# The real-pairs benchmark (benchmarks/real_pairs.py) at the dataset's full resolution on one
# CUDA GPU, inside a fixed wall-time budget (a lent GPU is lent for minutes).
#
#   DATA=path/to/dlmd OUT=results-folder bash benchmarks/gpu/real_pairs.sh [budget_s] [max_iters]
#
# 1. times the UDN (float32 and bf16) and FISTA-TV per iteration on the GPU (--time-threads);
# 2. picks the UDN iteration count that fits the budget (at most max_iters, default 3000),
#    assuming the four processes below slow each other down fourfold (measured on an H100:
#    four shared it at no slowdown, twelve at 2.9x); with GROUPS_OF_LEVELS give ITERS=N,
#    which skips 1 and 2;
# 3. runs the four pairs as four processes sharing the GPU, all five erasure levels each (or
#    one process per pair and group of levels, GROUPS_OF_LEVELS="0 0.99;0.5 0.95;0.9"),
#    every case appended to its results file as it ends (a case cut off by the budget is lost,
#    the others are kept);
# 4. makes the table and the figure from all of them, and packs everything but the per-case
#    images into $OUT/results.tgz.
# EXTRA: more options for every run, e.g. EXTRA="--lever fista-input --seeds 2".
# TABLE_EXTRA: more options for the table, e.g. TABLE_EXTRA=--error-analysis (which needs the
# per-case images: they stay on the device, so the analysis is made there).
# DEVICE=cpu DOWNSAMPLE=4 make a dry run of the script on a CPU.
# Needs python3 with torch (CUDA), numpy, scipy, pillow, h5py, tifffile, opencv on the path;
# the project is used from the source tree (PYTHONPATH), not installed.
set -u
BUDGET=${1:-470}
MAX_ITERS=${2:-3000}
DATA=${DATA:-../shared/data/dlmd}
OUT=${OUT:?set OUT to the results folder}
PY=${PY:-python3}
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1 OMP_NUM_THREADS=2
start=$(date +%s)
elapsed() { echo $(( $(date +%s) - start )); }
W=$(mktemp -d)
# through the CLI (`python -m app` is `lenslesscam`): a `timeout` that ends a process runs its
# clean-ups as Ctrl-C would; 1 torch thread per process, as the documented runs had
TABLE="$PY -m app bench real-pairs --data $DATA"
RP="$TABLE --device ${DEVICE:-cuda} --downsample ${DOWNSAMPLE:-1} --threads 1"

nvidia-smi -L 2>/dev/null
$PY -c "import sys, torch, numpy; print('python', sys.version.split()[0], 'torch', \
torch.__version__, 'numpy', numpy.__version__, torch.cuda.is_available() and \
torch.cuda.get_device_name())" || exit 1
if [ -z "${ITERS:-}" ]; then
$RP --time-threads 20 --pairs im65 > "$W/timing.json" || { cat "$W/timing.json"; exit 1; }
cat "$W/timing.json"
ITERS=$($PY - "$W/timing.json" "$BUDGET" "$(elapsed)" "$MAX_ITERS" <<'EOF'
import json, sys
t = json.load(open(sys.argv[1]))["s_per_iteration"]
t = t.get("float32", t.get("1"))  # on a CPU (a dry run): the 1-thread times
s = sorted(t)[len(t) // 2]
budget, used, cap = float(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4])
# per process: what is left after the table (30 s) and FISTA/ADMM (~15 s a case), 5 cases,
# four processes on one GPU at a quarter of its speed each
per_case = (budget - used - 30 - 5 * 15) / 5
iters = int(per_case / (4 * s) // 250 * 250)
print(max(min(cap, 500), min(cap, iters)))
EOF
)
fi
echo "UDN iterations: $ITERS (after $(elapsed) s)"
left=$(( BUDGET - $(elapsed) - 25 ))
# GROUPS_OF_LEVELS: the erasure levels of each process, per pair (default: all five in one process)
IFS=';' read -r -a groups <<< "${GROUPS_OF_LEVELS:-0 0.5 0.9 0.95 0.99}"
for p in im65 im408 im740 im1000; do
  for g in "${!groups[@]}"; do
    # shellcheck disable=SC2086
    timeout "$left" $RP --pairs $p --erasures ${groups[$g]} --udn-iters "$ITERS" ${EXTRA:-} \
      --results "$W/rp-$p-$g.jsonl" > "$W/log-$p-$g.txt" 2>&1 &
  done
done
wait
echo "runs ended after $(elapsed) s"
mkdir -p "$W/all-images"
# one file of all the processes' records; a torn last line of a process cut off by the
# timeout is dropped (cat put it in the middle of the file, which the table refuses)
$PY - "$W" <<'EOF'
import json, sys
from pathlib import Path
from benchmarks._cli import read_jsonl
w = Path(sys.argv[1])
rows = [r for f in sorted(w.glob("rp-*.jsonl")) for r in read_jsonl(f, "--results")]
(w / "all.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
EOF
cp "$W"/rp-*-images/*.npz "$W/all-images/" 2>/dev/null
# shellcheck disable=SC2086
$TABLE --table-only ${TABLE_EXTRA:-} --results "$W/all.jsonl" --figure "$W/real-pairs-gpu.png" \
  --out "$W/real-pairs-gpu.md" > "$W/table.txt" 2>&1
tail -n 4 "$W"/log-*.txt
head -n 60 "$W/table.txt"
tar czf "$OUT/results.tgz" -C "$W" --exclude='*-images' .
echo "done after $(elapsed) s"
