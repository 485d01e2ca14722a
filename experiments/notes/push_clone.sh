#!/bin/bash
# goal 2 probe: the noisy FetchPush memory cloned into a TD3 actor, original goals (successful episodes) vs hindsight goals
cd "$(git rev-parse --show-toplevel)" && mkdir -p bench_results/i27
for arm in "original 3" "hindsight 50" "hindsight 10"; do
  set -- $arm
  name=push-clone-$1-h$2
  rm -rf bench_results/i27/$name*
  python -m experiments.prior_variants.train env=push algo=td3 seed=0 prior=clone prior.clone_goals=$1 prior.clone_horizon=$2 \
    prior.paths=[bench_results/prior/scripted-push-500.zarr] collector.total_frames=100 collector.init_random_frames=0 \
    logger.eval_iter=5000 logger.eval_episodes=100 memory.pretrain_updates=250 memory.pretrain_eval_every=0 logger.plot=false \
    memory.path=bench_results/i27/$name.zarr hydra.run.dir=bench_results/i27/$name-out > bench_results/i27/$name.log 2>&1
  python3 -c "import json; s=json.load(open('bench_results/i27/$name-out/summary.json')); print('$name', s['curve'], s['cpu_s'])"
done
