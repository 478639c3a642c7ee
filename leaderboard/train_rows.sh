#!/usr/bin/env bash
# Train the learned leaderboard rows and turn each run into a submission (docs/reproduction.md).
#
#   bash leaderboard/train_rows.sh [JOBS] [ROW_FILTER]     e.g.  bash leaderboard/train_rows.sh 2 gcn_td3
#
# Every row is trained with the same frame budget (a frame budget, not wall time, so that a
# seed reproduces its run bit for bit: same seed, same torch build, one thread; checked by
# tests/test_train.py::test_same_seed_same_run) and the same recipe; only the encoder, the
# algorithm and the seed change. Runs go to runs/leaderboard/<name>/, one single-threaded process per job.
# Then: crowdbench leaderboard --jobs 2
set -euo pipefail
cd "$(dirname "$0")/.."
JOBS=${1:-2}
FILTER=${2:-}
FRAMES=${FRAMES:-28672}
# the crowdbench CPU recipe (docs/training.md, session 3): lookahead critic (one step, the env's dt),
# progress shaping 0.1 per metre (training only), exploration sigma 0.3; everything else is configs/algo/*
RECIPE="train.total_frames=$FRAMES train.progress_reward=0.1 algo.exploration_sigma=0.3 algo.critic_lookahead=0.25 \
train.probe_every=7168 eval.episodes=50"

seeds() {  # NAME LABEL OVERRIDES -> one row per training seed
  for s in 0 1 2; do echo "$1_s$s|$2|$3 seed=$s"; done
}

rows() {  # name | entry label | overrides   (longest first: better packing over the jobs)
  seeds gatedgcn_sac "MP-GatedGCN (SAC)" "algo=sac encoder=gatedgcn_fast"
  seeds gatedgcn_td3 "MP-GatedGCN-RL (TD3, gatedgcn)" "algo=td3 encoder=gatedgcn_fast"
  seeds gatedgcn_ddpg "MP-GatedGCN (DDPG)" "algo=ddpg encoder=gatedgcn_fast"
  seeds gcn_td3 "GCN-RL (TD3, gcn)" "algo=td3 encoder=gcn_fast"
  seeds mlp_td3 "DNN-RL (TD3, mlp)" "algo=td3 encoder=mlp_fast"
}

train_row() {
  IFS='|' read -r name entry overrides <<<"$1"
  out=runs/leaderboard/$name
  rm -rf "$out"  # a row is retrained from scratch (crowdbench run refuses to overwrite a saved run)
  # shellcheck disable=SC2086
  # the previous submission is replaced only by a finished run (xargs' bash has no set -e)
  if ! OMP_NUM_THREADS=1 RL_WARNINGS=False crowdbench run $overrides $RECIPE out="$out" >"$out.log" 2>&1; then
    echo "train_rows.sh: $name failed, see $out.log; leaderboard/submissions/$name left as it was" >&2
    return 1
  fi
  rm -rf "leaderboard/submissions/$name"
  crowdbench submit "$out" --name "$name" --entry "$entry" \
    --notes "trained by leaderboard/train_rows.sh: crowdbench run $overrides $RECIPE"
}
export -f train_row
export RECIPE

mkdir -p runs/leaderboard
rows | grep -- "$FILTER" | xargs -d '\n' -P "$JOBS" -I{} bash -c 'train_row "$@"' _ {}
