#!/bin/bash
# One chunk of a long world-model training: resume from the last checkpoint (if any), train for MAX_MINUTES,
# hand the new checkpoint back as parts small enough for a job's outputs. Run it again until it exits 0.
#
#   STORE=/tmp/data/trajectories.zarr CKPT_IN=.carry/ckpt CKPT_OUT=$OUT MAX_MINUTES=7.5 \
#     scripts/gpu/train_chunk.sh --params params/gpu.yaml [--set train.batch_size=8 ...]
#
# CKPT_IN  a folder holding ckpt.tar.xz.part-* from the previous chunk (absent or empty: start afresh)
# CKPT_OUT where this chunk writes ckpt.tar.xz.part-* (parts of PART_BYTES, default 15 MiB) and train.log
# WORK     the model folder on this machine (default /tmp/wc_train/model; the run lives in WORK.partial)
# Exit status: 0 = training complete (the parts hold the finished model folder), 75 = stopped by MAX_MINUTES with a
# complete checkpoint (run the next chunk), anything else = failed. The same script serves a cluster job array with
# a wall-time limit: each job resumes where the last one stopped, with the same result as one uninterrupted run.
set -uo pipefail
cd "$(dirname "$0")/../.."
: "${STORE:?set STORE to the trajectory store}" "${CKPT_OUT:?set CKPT_OUT}"
WORK=${WORK:-/tmp/wc_train/model}
PART_BYTES=${PART_BYTES:-15728640}
mkdir -p "$CKPT_OUT" "$(dirname "$WORK")"
if [ -n "${CKPT_IN:-}" ] && ls "$CKPT_IN"/ckpt.tar.xz.part-* >/dev/null 2>&1; then
  rm -rf "$WORK.partial"
  cat "$CKPT_IN"/ckpt.tar.xz.part-* | xz -dc | tar x -C "$(dirname "$WORK")" || { echo "chunk: unreadable checkpoint parts in $CKPT_IN" >&2; exit 2; }
  echo "chunk: resuming from $(python3 -c "import json;print(json.load(open('$WORK.partial/last.json'))['step'])" 2>/dev/null || echo '?')"
fi
python3 -m stages.train --store "$STORE" --out "$WORK" --report "$CKPT_OUT/train.json" --curves "$CKPT_OUT/train_loss.csv" \
  --resume --set "train.max_minutes=${MAX_MINUTES:-7.5}" "$@" 2>&1 | tr '\r' '\n' | grep -v "it/s\]$" > "$CKPT_OUT/train.log"
rc=${PIPESTATUS[0]}
tail -5 "$CKPT_OUT/train.log"
case $rc in
  0) src="$WORK" ;;
  75) src="$WORK.partial" ;;
  *) echo "chunk: training failed (exit $rc)" >&2; exit "$rc" ;;
esac
rm -f "$CKPT_OUT"/ckpt.tar.xz.part-*
tar cf - -C "$(dirname "$src")" "$(basename "$src")" | xz -1 -T0 | split -b "$PART_BYTES" -d - "$CKPT_OUT/ckpt.tar.xz.part-"
ls -la "$CKPT_OUT"
exit "$rc"
