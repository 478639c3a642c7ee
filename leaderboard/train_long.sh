#!/usr/bin/env bash
# Longer TD3 runs in stages, one seed per call, each stage submitted (docs/reproduction.md).
#
#   [ENCODER=gatedgcn|gcn|mlp] [REPLAY=per|uniform] [STAGES=2|1] bash leaderboard/train_long.sh SEED
#   e.g.  REPLAY=uniform bash leaderboard/train_long.sh 1
#
# The rows' recipe (leaderboard/train_rows.sh) at 5x and 12x the rows' budget: stage 1 trains
# runs/long/<ENCODER>_td3_<TAG>s<SEED> to 143,360 frames and submits <ENCODER>_td3_<TAG>5x_s<SEED>;
# stage 2 resumes the same run to 344,064 frames and submits <ENCODER>_td3_<TAG>12x_s<SEED>.
# A stage that is already done is skipped, so a call cut off by the end of a session continues
# where it stopped. On one core a gatedgcn stage 1 takes ~45-55 min, stage 2 ~70-80 min. The replay
# buffer is not checkpointed: stage 2 starts with an empty buffer (2,000 frames before its first
# update), and a stage killed mid-way and resumed is valid training but no longer the bit-identical
# run of the uninterrupted commands.
#   ENCODER  default gatedgcn (the *_fast configs, D=32).
#   REPLAY   default per (the recipe's). uniform adds algo.replay=uniform and TAG=uniform_ to the run
#            directory, the submission names and the entries (143k frames: 0.932 over 3 seeds against
#            0.905 with PER, one seed; docs/training.md, sessions 6-7).
#   STAGES   default 2; 1 stops after stage 1.
set -euo pipefail
cd "$(dirname "$0")/.."
SEED=${1:?usage: [ENCODER=gatedgcn|gcn|mlp] [REPLAY=per|uniform] [STAGES=2|1] bash leaderboard/train_long.sh SEED}
ENCODER=${ENCODER:-gatedgcn}
REPLAY=${REPLAY:-per}
STAGES=${STAGES:-2}
case $ENCODER in
  gatedgcn) row="MP-GatedGCN-RL" ;;
  gcn) row="GCN-RL" ;;
  mlp) row="DNN-RL" ;;
  *) echo "train_long.sh: ENCODER must be gatedgcn, gcn or mlp, got '$ENCODER'" >&2; exit 2 ;;
esac
RECIPE="algo=td3 encoder=${ENCODER}_fast seed=$SEED train.progress_reward=0.1 algo.exploration_sigma=0.3 \
algo.critic_lookahead=0.25 train.probe_every=28672 eval.episodes=250"
case $REPLAY in
  per) tag="" label="" ;;
  uniform) tag="uniform_" label="uniform replay, " RECIPE="$RECIPE algo.replay=uniform" ;;
  *) echo "train_long.sh: REPLAY must be per or uniform, got '$REPLAY'" >&2; exit 2 ;;
esac
case $STAGES in
  1|2) ;;
  *) echo "train_long.sh: STAGES must be 1 or 2, got '$STAGES'" >&2; exit 2 ;;
esac
out=runs/long/${ENCODER}_td3_${tag}s$SEED
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
    --notes "trained by ENCODER=$ENCODER REPLAY=$REPLAY bash leaderboard/train_long.sh $SEED: crowdbench run $RECIPE train.total_frames=$frames out=RUN (stage 2: the same with resume=true on the stage-1 run)"
}

stage 143360 "${ENCODER}_td3_${tag}5x_s$SEED" "$row (TD3, $ENCODER, ${label}143k frames)"
[ "$STAGES" = 1 ] && exit 0
stage 344064 "${ENCODER}_td3_${tag}12x_s$SEED" "$row (TD3, $ENCODER, ${label}344k frames)"
