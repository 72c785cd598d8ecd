#!/bin/bash
# The one look of the move-off refinements (docs/benchmark.md, "Rolling-in starts"): Autonomy-A
# with bench/configs/planner-moveoff-stand.json on the fresh part (seeds 0-4), the generated
# benchmark (seed 0), the tuned-on benchmark part (seed 0), the train crawls (seeds 0-2) and the
# rolling-in train crawls (seeds 0-2, shipped and changed), all on Autonomy-A with the predictor
# shipped before the anchored one; the shipped stack's references are the kept files the rule names. Run from the repository root:
#     nice -n 10 bash bench/look_moveoff_stand.sh
set -e
CFG=bench/configs/planner-moveoff-stand.json
# the stack of the references: Autonomy-A with the predictor shipped before the anchored one
S="nice -n 10 .venv/bin/python bench/sanity.py --autonomy bench.stack_variants:a_predictor_2026_shipped --workers 2"
for seed in 0 1 2 3 4; do
  $S --sets real --real-part fresh --seed $seed --planner-config $CFG --name sanity.real-fresh.A-moveoff-stand.seed$seed
done
$S --sets generated --seed 0 --planner-config $CFG --name sanity.A-moveoff-stand
$S --sets real --real-part benchmark --seed 0 --planner-config $CFG --name sanity.real-benchmark.A-moveoff-stand
for seed in 0 1 2; do
  $S --sets real --real-dir scenes/real-train-crawls --seed $seed --planner-config $CFG --name sanity.real-train-crawls.A-moveoff-stand.seed$seed
  $S --sets real --real-dir scenes/real-train-crawls-rolling --seed $seed --name sanity.real-train-crawls-rolling.A.seed$seed
  $S --sets real --real-dir scenes/real-train-crawls-rolling --seed $seed --planner-config $CFG --name sanity.real-train-crawls-rolling.A-moveoff-stand.seed$seed
done
echo "look done"
