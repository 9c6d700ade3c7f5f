#!/usr/bin/env bash
# The GPU recipe: fine-tune the shipped TrafficBots weights on every real training scene for as
# long as a lent GPU allows (12 minutes of wall time on one H100 or H200), keeping the weights
# that do best on the real validation scenes.
#
#   bash scripts/train_gpu.sh prepare [DATA_DIR]        # on the CPU, once, beforehand
#   bash scripts/train_gpu.sh train OUT [MINUTES]       # on the GPU (default 9 minutes)
#   bash scripts/train_gpu.sh batch                     # the batch size train would use
#
# prepare: token caches of the train (172 scenes) and validation (57) splits of
#   docs/model_card/real_splits.json (tbsim preprocess), gzip-packed into gpu_data/ (about 35 MB,
#   git-ignored): small enough to travel with the working tree (the device tool's carry, or any
#   copy). Nothing on the GPU machine needs the WOMD files.
# train: unpacks gpu_data/ to a temporary folder and runs `tbsim train` from the shipped
#   weights or $INIT (--init, fresh AdamW): batch $BATCH (default: 128 on a GPU of at least
#   $BIG_GPU_MIB of memory, an H200; else 64, which fits an H100) of full 91-step
#   closed-loop rollouts with back-propagation through the unicycle, float16 autocast with a
#   grad scaler (AMP), lr 1e-4 after a 20-step warm-up, EMA of the weights (decay 0.99), the
#   validation loss (policies/trafficbots/validate.py) of the starting weights and then every
#   $VAL_EVERY steps (default 25) and at the end; the lowest is kept as OUT/best.safetensors + .json (the
#   shipped weights themselves when nothing beats them), its step and scores in
#   OUT/best_step.json. The run stops after MINUTES of training, checkpoints included, and
#   resumes from OUT when started again (OUT/last, OUT/optimizer). Scalars: OUT/metrics.jsonl.
# Afterwards, on the CPU: score OUT/best on the validation scenes against the shipped weights
#   (WOSAC metrics, paired over scenes) before shipping anything, e.g.
#   tbsim evaluate --policy trafficbots --checkpoint OUT/best \
#     --data $(python scripts/split_files.py validation) --json val_new.json
#
# Measured on one H200 (torch 2.11, CUDA 13): batch 64 takes 36 GB of GPU memory and runs
#   15.4 scene samples/s (about 4.2 s a step, 18x the 2-core CPU's 0.85); batch 128 runs 27.0
#   (4.7 s a step): the 91 sequential small steps of a rollout are launch-bound (13-34% GPU
#   utilisation at batch 64), so a larger batch is nearly free. Four segments, each resumed
#   from the last: 143 steps of batch 64 (10 minutes), then 146 of batch 128 (11.6 minutes):
#   27,840 scene samples, validation loss 6.447 -> 5.239, still falling.
# Running it on the device machine (nothing installed there but torch and the usual stack):
#   carry gpu_data and wheels of pettingzoo, gymnasium, farama-notifications, crc32c, shapely
#   and protobuf (pip download ... --python-version 3.12), pip install them --target a folder
#   on PYTHONPATH with the checkout, and call the CLI as `python3 -m tbsim_env.cli`.
# Environment: INIT (weights to start from; the shipped ones), DEVICE (auto), BATCH (see above),
# VAL_EVERY (25), WORKERS (4), TRAIN_SOURCES and VAL_SOURCES (the splits' files; anything
# `tbsim preprocess` takes, e.g. generated:merge:0-3, for a test), GPU_DATA (gpu_data).
set -euo pipefail
cd "$(dirname "$0")/.."
STAGE=${1:?usage: train_gpu.sh prepare [DATA_DIR] | train OUT [MINUTES] | batch}
GPU_DATA=${GPU_DATA:-gpu_data}
WEIGHTS=policies/trafficbots/weights/trafficbots_small
BIG_GPU_MIB=120000

batch() {  # $BATCH, else 128 on a GPU with at least BIG_GPU_MIB MiB of memory, else 64
  if [[ -n ${BATCH:-} ]]; then echo "$BATCH"; return; fi
  local mib
  mib=$(nvidia-smi --query-gpu=memory.total --format=csv,noheader,nounits 2>/dev/null | head -1) ||
    mib=0  # no NVIDIA GPU
  if [[ ${mib:-0} =~ ^[0-9]+$ ]] && ((mib >= BIG_GPU_MIB)); then echo 128; else echo 64; fi
}

pack() {  # pack CACHE_DIR DEST_DIR: the manifest as is, each shard gzip-compressed
  mkdir -p "$2"
  cp "$1/manifest.json" "$2/"
  for f in "$1"/*.safetensors; do gzip -c -4 "$f" >"$2/$(basename "$f").gz"; done
}

unpack() {  # unpack PACKED_DIR DEST_DIR
  mkdir -p "$2"
  cp "$1/manifest.json" "$2/"
  for f in "$1"/*.safetensors.gz; do gunzip -c "$f" >"$2/$(basename "$f" .gz)"; done
}

case $STAGE in
prepare)
  if [[ -n ${2:-} ]]; then export TBSIM_WOMD_DIR=$2; fi
  tmp=$(mktemp -d)
  trap 'rm -rf "$tmp"' EXIT
  # shellcheck disable=SC2046
  tbsim preprocess ${TRAIN_SOURCES:-$(python scripts/split_files.py train)} \
    --out "$tmp/train" --workers "${WORKERS:-2}"
  # shellcheck disable=SC2046
  tbsim preprocess ${VAL_SOURCES:-$(python scripts/split_files.py validation)} \
    --out "$tmp/validation" --workers "${WORKERS:-2}"
  rm -rf "$GPU_DATA"
  pack "$tmp/train" "$GPU_DATA/train"
  pack "$tmp/validation" "$GPU_DATA/validation"
  du -sh "$GPU_DATA"
  ;;
train)
  OUT=${2:?usage: train_gpu.sh train OUT [MINUTES]}
  MINUTES=${3:-9}
  tmp=$(mktemp -d)
  trap 'rm -rf "$tmp"' EXIT
  unpack "$GPU_DATA/train" "$tmp/train"
  unpack "$GPU_DATA/validation" "$tmp/validation"
  budget=$(python -c "print(round(float('$MINUTES') * 60, 1))")
  tbsim train --data "$tmp/train" --val-data "$tmp/validation" --out "$OUT" \
    --init "${INIT:-$WEIGHTS}" --model small --steps 100000 --batch-size "$(batch)" --lr 1e-4 \
    --warmup-steps 20 --ema-decay 0.99 --teacher-forcing-start 0 --teacher-forcing-end 0 \
    --workers "${WORKERS:-4}" --cache-shards 0 --device "${DEVICE:-auto}" --amp \
    --time-budget-s "$budget" --val-every "${VAL_EVERY:-25}" --ckpt-every 25 --log-every 5
  cat "$OUT/best_step.json"
  echo
  ;;
batch)
  batch
  ;;
*)
  echo "unknown stage $STAGE: prepare, train or batch" >&2
  exit 2
  ;;
esac
