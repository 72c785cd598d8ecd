#!/usr/bin/env bash
# The anchored predictor's one look at the fresh part (docs/benchmark.md, "The anchored
# predictor"): open loop first, then closed loop on the fresh part (seeds 0-4) and on the
# generated benchmark beside the shipped stack run again on the same machine.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=.venv/bin/python
$PY bench/predictor_real.py --parts fresh,benchmark --out predictor_real.fresh-anchored \
    shipped=assets/models/predictor finetuned=assets/models/predictor-fresh-ft anchored=assets/models/predictor-anchored
for S in 0 1 2 3 4; do
    $PY bench/sanity.py --sets real --real-part fresh --autonomy bench.stack_variants:a_predictor_anchored \
        --seed "$S" --workers 2 --name "sanity.real-fresh.A-predictor-anchored.seed$S"
done
$PY bench/sanity.py --sets generated --autonomy bench.stack_variants:a_predictor_anchored --workers 2 \
    --name sanity.A-predictor-anchored
$PY bench/sanity.py --sets generated --autonomy A --workers 2 --name sanity.A.anchored-reference
$PY bench/fresh_table.py --stacks A,A-predictor-anchored --out bench/results/sanity.real-fresh.table.anchored.json
