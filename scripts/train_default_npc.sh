#!/usr/bin/env bash
# Reproduce the shipped TrafficBots NPC (policies/trafficbots/weights/trafficbots_small.*).
# See docs/MODEL_CARD.md for data, held-out sets and results.
#
# Four stages:
#   1. CPU (2 cores, 1 torch thread): steps 1-700, batch 2, 4 s closed-loop rollouts (51 steps),
#      on 400 generated scenes (intersection/merge) plus the 3 real training scenes.
#   2. One H100 GPU: steps 701-1030, batch 32, full 91-step rollouts, on 480 generated scenes of
#      all four layouts plus the 3 real training scenes drawn 24 times as often. The shipped
#      weights come from three resumed segments of it (to steps 820, 960 and 1030, with --seed
#      2024, 2025 and 2026); `--steps 1100 --stop-at 1030` keeps their learning-rate schedule.
#      The command below runs it in one go with one seed, so its batches differ.
#   3. CPU (2 cores, 1 torch thread): a fine-tune of the stage-2 weights (`--init`, fresh AdamW,
#      lr 2e-4, batch 4, full 91-step rollouts, no teacher forcing) on generated scenes whose
#      roads run 60 m past the observed area and whose urban layouts have cyclists and crossing
#      pedestrians. Steps 1-70 draw from seeds 480-1119 (640 scenes) and the real scenes x40;
#      steps 71-250 also from seeds 1120-1759 (640 scenes) drawn twice as often, and the real
#      scenes x70; steps 251-400 resume (weights and AdamW state) with seeds 1120-1759 drawn
#      three times as often, the real scenes x90, seed 2029. For the shipped weights, seeds
#      480-1119 came from the generator of commit 424e315, without cyclists or crossing
#      pedestrians; this generator gives them both.
#   Stage 3's result is the mean of its step-250 and step-400 weights (`tbsim average`).
#   4. CPU (1 torch thread on 2 shared cores, ~95 min): a fine-tune of stage 3's result on the
#      76 real training scenes of docs/model_card/real_splits.json (x3: 42% of the draws) and
#      320 calibrated generated scenes of five layouts (seeds 2000-2319, permissive left turns
#      included); batch 4, full 91-step rollouts, no teacher forcing, lr 1e-4 with a 20-step
#      warm-up, 5e-5 after step 1000, EMA of the weights (decay 0.98). The shipped weights are
#      the EMA at step 1200, chosen among the EMAs of steps 175-1300 on the 27 real validation
#      scenes (16 rollouts each); the held-out scenes took no part in any choice.
#   5. One H200 GPU (scripts/train_gpu.sh, four segments, each resumed from the last: 7 and
#      3 minutes at batch 64, steps 1-143; 7 and 4.6 minutes at batch 128, steps 144-289): a
#      fine-tune of stage 4's result on the 172 real training scenes of real_splits.json
#      alone; full 91-step rollouts, AMP, lr 1e-4 with a 20-step warm-up, EMA (decay 0.99).
#      The shipped weights are the EMA at step 289, the lowest validation loss (57 real
#      validation scenes); paired WOSAC scores on the validation scenes confirmed them.
#
#   bash scripts/train_default_npc.sh [OUT_DIR] [STAGE]     # STAGE: all (default), 1, 2, 3, 4 or 5
set -euo pipefail
W=${TBSIM_WOMD_DIR:-../shared/data/womd}
OUT=${1:-runs}
STAGE=${2:-all}
REAL=(
  "$W/waymo-open-dataset/womd_scenario_input.tfrecord"
  "$W/gpudrive/tfrecord-00000-of-01000_222.json"
  "$W/gpudrive/tfrecord-00000-of-01000_325.json"
)
# Held out, never preprocessed for training: 637f20cafde22ff8 (motion_data_one_scenario) and
# db4edc9bd0c9d18c (gpudrive ..._4.json); generated seeds 10000-10007.
HELD_OUT=(637f20cafde22ff8 db4edc9bd0c9d18c)

if [[ $STAGE == all || $STAGE == 1 ]]; then
  tbsim preprocess generated:intersection,merge:0-399 "${REAL[@]}" \
    --out "$OUT/cache_v1" --workers 2 --shard-size 64 --exclude "${HELD_OUT[@]}"
  tbsim train --data "$OUT/cache_v1" --out "$OUT/small_v1" --model small --steps 700 \
    --batch-size 2 --lr 5e-4 --rollout-steps 51 --threads 1 --workers 0 \
    --ckpt-every 25 --log-every 5 --seed 2023
fi

if [[ $STAGE == all || $STAGE == 2 ]]; then
  tbsim preprocess generated:intersection,merge,stop_intersection,t_junction:0-479 \
    --out "$OUT/cache_gen_v2" --workers 16 --shard-size 64
  tbsim preprocess "${REAL[@]}" --out "$OUT/cache_real" --workers 1 --exclude "${HELD_OUT[@]}"
  mkdir -p "$OUT/small_v2"
  # Resume from stage 1: weights and AdamW state (step 700).
  cp "$OUT"/small_v1/{last.safetensors,last.json,optimizer.safetensors,optimizer.json} \
    "$OUT/small_v2/"
  tbsim train --data "$OUT/cache_gen_v2,$OUT/cache_real*24" --out "$OUT/small_v2" \
    --model small --steps 1100 --stop-at 1030 --batch-size 32 --lr 5e-4 --no-amp --workers 3 \
    --cache-shards 0 --log-every 5 --ckpt-every 10 --seed 2024
fi

if [[ $STAGE == all || $STAGE == 3 ]]; then
  # This generator gives seeds 480-1119 cyclists and crossing pedestrians too (the shipped
  # run's came from commit 424e315, without them), so both caches below hold those.
  tbsim preprocess generated:intersection,merge,stop_intersection,t_junction:480-1119 \
    --out "$OUT/cache_gen_v3" --workers 2 --shard-size 64
  tbsim preprocess generated:intersection,merge,stop_intersection,t_junction:1120-1759 \
    --out "$OUT/cache_gen_v4" --workers 2 --shard-size 64
  tbsim preprocess "${REAL[@]}" --out "$OUT/cache_real" --workers 1 --exclude "${HELD_OUT[@]}"
  tbsim train --data "$OUT/cache_gen_v3,$OUT/cache_real*40" --out "$OUT/small_v3" \
    --model small --steps 400 --stop-at 70 --batch-size 4 --lr 2e-4 --teacher-forcing-start 0 \
    --teacher-forcing-end 0 --threads 1 --workers 0 --no-amp --log-every 5 --ckpt-every 10 \
    --seed 2027 --init "$OUT/small_v2/last"
  tbsim train --data "$OUT/cache_gen_v4*2,$OUT/cache_gen_v3,$OUT/cache_real*70" \
    --out "$OUT/small_v3" --model small --steps 400 --stop-at 250 --batch-size 4 --lr 2e-4 \
    --teacher-forcing-start 0 --teacher-forcing-end 0 --threads 1 --workers 0 --no-amp \
    --log-every 5 --ckpt-every 10 --seed 2028
  for f in safetensors json; do cp "$OUT/small_v3/last.$f" "$OUT/small_v3/step250.$f"; done
  tbsim train --data "$OUT/cache_gen_v4*3,$OUT/cache_gen_v3,$OUT/cache_real*90" \
    --out "$OUT/small_v3" --model small --steps 400 --batch-size 4 --lr 2e-4 \
    --teacher-forcing-start 0 --teacher-forcing-end 0 --threads 1 --workers 0 --no-amp \
    --log-every 5 --ckpt-every 10 --seed 2029
  tbsim average "$OUT/small_v3/step250" "$OUT/small_v3/last" --out "$OUT/small_v3/shipped"
fi

if [[ $STAGE == all || $STAGE == 4 ]]; then
  # The 76 real training scenes of docs/model_card/real_splits.json (their validation and
  # held-out scenes never enter a cache) and 320 calibrated generated scenes of five layouts.
  python - "$W" > "$OUT/real_train.txt" <<'PY'
import json, sys
splits = json.load(open("docs/model_card/real_splits.json"))
print("\n".join(f"{sys.argv[1]}/{e['file']}" for e in splits["train"]))
PY
  EXCLUDE=$(python -c "import json; s = json.load(open('docs/model_card/real_splits.json')); \
print(' '.join(e['scenario_id'] for k in ('validation', 'held_out') for e in s[k]))")
  # shellcheck disable=SC2046
  tbsim preprocess $(cat "$OUT/real_train.txt") --out "$OUT/cache_real76" --workers 1 \
    --shard-size 32 --exclude $EXCLUDE
  tbsim preprocess \
    generated:intersection,merge,stop_intersection,t_junction,permissive_intersection:2000-2319 \
    --out "$OUT/cache_gen_cal" --workers 1 --shard-size 64
  FT=(--data "$OUT/cache_gen_cal,$OUT/cache_real76*3" --out "$OUT/small_v4" --model small
      --batch-size 4 --warmup-steps 20 --ema-decay 0.98 --teacher-forcing-start 0
      --teacher-forcing-end 0 --threads 1 --workers 0 --no-amp --log-every 5 --ckpt-every 25
      --init "$OUT/small_v3/shipped")
  # Resumable segments as run: steps 1-300, then 100 at a time (each segment reseeds; the lr
  # is constant after the warm-up), lr 1e-4 to step 1000, 5e-5 to step 1200.
  tbsim train "${FT[@]}" --lr 1e-4 --steps 300 --seed 2030
  for stop in $(seq 400 100 1200); do
    lr=1e-4; [[ $stop -gt 1000 ]] && lr=5e-5
    tbsim train "${FT[@]}" --lr $lr --steps 2000 --stop-at "$stop" --seed $((2030 + stop))
  done
  # Shipped: the EMA (decay 0.98) at step 1200, chosen on the 27 real validation scenes.
  for f in safetensors json; do cp "$OUT/small_v4/ema.$f" "$OUT/small_v4/shipped.$f"; done
fi

if [[ $STAGE == all || $STAGE == 5 ]]; then
  # On the GPU machine (see scripts/train_gpu.sh for what to carry there); gpu_data/ made on
  # the CPU beforehand. Each segment resumes the last from the run folder.
  bash scripts/train_gpu.sh prepare "$W"
  for seg in 64:7 64:3 128:7 128:4.6; do
    INIT="$OUT/small_v4/shipped" BATCH=${seg%%:*} bash scripts/train_gpu.sh train "$OUT/small_v5" "${seg##*:}"
  done
  for f in safetensors json; do cp "$OUT/small_v5/best.$f" "$OUT/small_v5/shipped.$f"; done
fi

python scripts/evaluate_default_npc.py --checkpoint "$OUT/small_v5/shipped" --samples 64 \
  --out docs/model_card
