#!/usr/bin/env bash
# Job: re-fly every committed policy and built-in agent on env version 3 (issue 69: obstacle placement changed every
# id's scenes), from a clean checkout, into OUT (default: this repository). Campaign 1's checkpoints (replaced by
# campaign 2's seed-0 runs as they land) are flown on their own main id only (100 episodes; vision-ppo-S and
# state-ppo-S also 50 on the other two main ids, the cross-track column); the teacher-student checkpoints and the
# built-ins keep their full suites. The env-version-2 records stay in git history and, for campaign 1, in
# baselines/experiments/campaign-4m/<run>/eval and results/env-v2/. Resumable (each evaluation is); the
# cross-track and hard-id phases come last. Usage: bash scripts/reevaluate_env_v3.sh [OUT] [WORKERS] [PHASES]
# (PHASES: any of 1 own main ids, 2 built-ins, 3 cross-track, 4 hard ids; default 1234)
set -euo pipefail
OUT=${1:-.}
W=${2:-2}
PHASES=${3:-1234}
ev() { racebench evaluate --workers "$W" "$@"; }
# 1. every committed checkpoint on its own main id (100 episodes)
[[ $PHASES == *1* ]] && for config in vision-ppo state-ppo vision-com vision-no-avoid vision-one-step vision-no-gru vision-distill \
    vision-distill-ppo; do
  for t in S J Circle; do
    p=baselines/checkpoints/$config-$t
    ev --agent "$p/$config-$t.zip" --name "$config$([[ $config == vision-distill* ]] || echo -seed0)" \
       --envs "RaceObs-$t-v0" --episodes 100 --out "$OUT/$p/eval"
  done
done
# 2. the built-ins: 10 episodes per id of the paper suite, 50 per main id
[[ $PHASES == *2* ]] && for agent in planner planner-fast follow hover; do
  traj=$([[ $agent == planner* ]] && echo --save-trajectories || true)
  ev --agent $agent --envs paper --episodes 10 --out "$OUT/results/$agent" $traj
  ev --agent $agent --envs main --episodes 50 --out "$OUT/results/$agent" $traj
done
# 3. the cross-track columns: vision-ppo-S, state-ppo-S and the teacher-student students on the other main ids (50)
[[ $PHASES == *3* ]] && for p in baselines/checkpoints/vision-ppo-S baselines/checkpoints/state-ppo-S; do
  ev --agent "$p/$(basename $p).zip" --name "$(basename $p -S)-seed0" --envs RaceObs-Circle-v0 RaceObs-J-v0 \
     --episodes 50 --out "$OUT/$p/eval"
done
[[ $PHASES == *3* ]] && for config in vision-distill vision-distill-ppo; do
  for t in S J Circle; do
    p=baselines/checkpoints/$config-$t
    others=$(for o in S Circle J; do if [ $o != $t ]; then echo -n "RaceObs-$o-v0 "; fi; done)
    # shellcheck disable=SC2086
    ev --agent "$p/$config-$t.zip" --name $config --envs $others --episodes 50 --out "$OUT/$p/eval"
  done
done
# 4. the teacher-student students' hard ids (50 each)
[[ $PHASES == *4* ]] && for config in vision-distill vision-distill-ppo; do
  for t in S J Circle; do
    p=baselines/checkpoints/$config-$t
    ev --agent "$p/$config-$t.zip" --name $config --envs "RaceObs-$t-Density5-v0" "RaceObs-$t-GateShift1.0-v0" \
       --episodes 50 --out "$OUT/$p/eval-hard"
  done
done
true
