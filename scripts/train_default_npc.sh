#!/usr/bin/env bash
# Reproduce the shipped TrafficBots NPC (policies/trafficbots/weights/trafficbots_small.*).
# CPU only, one torch thread; see docs/MODEL_CARD.md for data, held-out sets and results.
set -euo pipefail
W=${TBSIM_WOMD_DIR:-../shared/data/womd}
OUT=${1:-runs}

# Training data: 400 generated scenes (seeds 0-399, intersection/merge alternating, generator as
# of commit 6a07f31) and the real WOMD scenes that are NOT held out. Held out, never preprocessed:
# 637f20cafde22ff8 (motion_data_one_scenario) and db4edc9bd0c9d18c (gpudrive ..._4.json).
tbsim preprocess generated:intersection,merge:0-399 \
  "$W/waymo-open-dataset/womd_scenario_input.tfrecord" \
  "$W/gpudrive/tfrecord-00000-of-01000_222.json" \
  "$W/gpudrive/tfrecord-00000-of-01000_325.json" \
  --out "$OUT/cache_v1" --workers 2 --shard-size 64

tbsim train --data "$OUT/cache_v1" --out "$OUT/small_v1" --model small --steps 700 \
  --batch-size 2 --lr 5e-4 --rollout-steps 51 --threads 1 --workers 0 \
  --ckpt-every 25 --log-every 5 --seed 2023

python scripts/evaluate_default_npc.py --checkpoint "$OUT/small_v1/last" --out docs/model_card
