#!/usr/bin/env bash
# Longer MP-GatedGCN-RL (TD3) runs in stages, one seed per call, each stage submitted (docs/reproduction.md).
#
#   bash leaderboard/train_long.sh SEED          e.g.  bash leaderboard/train_long.sh 1
#
# The rows' recipe (leaderboard/train_rows.sh) at 5x and 12x the rows' budget: stage 1 trains
# runs/long/gatedgcn_td3_s<SEED> to 143,360 frames and submits gatedgcn_td3_5x_s<SEED>; stage 2
# resumes the same run to 344,064 frames and submits gatedgcn_td3_12x_s<SEED>. A stage that is
# already done is skipped, so a call cut off by the end of a session continues where it stopped.
# Each stage takes ~1-1.5 h (stage 2 ~1.5-2 h) on one core. The replay buffer is not
# checkpointed: stage 2 starts with an empty buffer (2,000 frames before its first update), and a
# stage killed mid-way and resumed is valid training but no longer the bit-identical run of the
# uninterrupted commands.
set -euo pipefail
cd "$(dirname "$0")/.."
SEED=${1:?usage: bash leaderboard/train_long.sh SEED}
RECIPE="algo=td3 encoder=gatedgcn_fast seed=$SEED train.progress_reward=0.1 algo.exploration_sigma=0.3 \
algo.critic_lookahead=0.25 train.probe_every=28672 eval.episodes=250"
out=runs/long/gatedgcn_td3_s$SEED
mkdir -p runs/long

frames_done() {  # frames in the run's checkpoint, 0 if none
  python -c "import sys, torch; print(torch.load(sys.argv[1], weights_only=True)['frames'])" "$out/checkpoint.pt" \
    2>/dev/null || echo 0
}

stage() {  # FRAMES NAME LABEL
  local frames=$1 name=$2 label=$3 resume=""
  if [ "$(frames_done)" -ge "$frames" ]; then
    echo "$name: $out already has $frames frames"
  else
    [ -f "$out/checkpoint.pt" ] && resume="resume=true"
    # shellcheck disable=SC2086
    OMP_NUM_THREADS=1 RL_WARNINGS=False crowdbench run $RECIPE train.total_frames="$frames" out="$out" $resume \
      >>"$out.log" 2>&1
  fi
  [ -d "leaderboard/submissions/$name" ] && return
  crowdbench submit "$out" --name "$name" --entry "$label" \
    --notes "trained by leaderboard/train_long.sh $SEED: crowdbench run $RECIPE train.total_frames=$frames out=RUN (stage 2: the same with resume=true on the stage-1 run)"
}

stage 143360 "gatedgcn_td3_5x_s$SEED" "MP-GatedGCN-RL (TD3, gatedgcn, 143k frames)"
stage 344064 "gatedgcn_td3_12x_s$SEED" "MP-GatedGCN-RL (TD3, gatedgcn, 344k frames)"
