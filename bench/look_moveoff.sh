#!/bin/bash
# The one look of the move-off jam distance (docs/benchmark.md, "Standstill starts"): Autonomy-A
# with bench/configs/planner-moveoff.json on the fresh part (seeds 0-4), the generated benchmark
# (seed 0), the tuned-on benchmark part (seed 0, with the shipped stack again on this machine) and
# the train crawls (seeds 0-2, shipped and changed). Run from the repository root:
#     nice -n 5 bash bench/look_moveoff.sh
set -e
CFG=bench/configs/planner-moveoff.json
S="nice -n 5 .venv/bin/python bench/sanity.py --autonomy A --workers 2"
for seed in 0 1 2 3 4; do
  $S --sets real --real-part fresh --seed $seed --planner-config $CFG --name sanity.real-fresh.A-moveoff.seed$seed
done
$S --sets generated --seed 0 --planner-config $CFG --name sanity.A-moveoff
$S --sets real --real-part benchmark --seed 0 --planner-config $CFG --name sanity.real-benchmark.A-moveoff
$S --sets real --real-part benchmark --seed 0 --name sanity.real-benchmark.A.moveoff-reference
for seed in 0 1 2; do
  $S --sets real --real-dir scenes/real-train-crawls --seed $seed --name sanity.real-train-crawls.A.seed$seed
  $S --sets real --real-dir scenes/real-train-crawls --seed $seed --planner-config $CFG --name sanity.real-train-crawls.A-moveoff.seed$seed
done
echo "look done"
