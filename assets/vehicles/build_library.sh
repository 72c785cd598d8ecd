#!/usr/bin/env bash
# Rebuild the curated vehicle library (assets/vehicles/) from the source packs.
#
#   assets/vehicles/build_library.sh [PACKS_DIR]
#
# PACKS_DIR defaults to ../shared/vehicle-packs relative to the repository root. The output is
# deterministic: running this twice gives byte-identical library.json and .glb files.
# ADV3D_LIBRARY_DIR=DIR builds into DIR instead of assets/vehicles (the tests use it to check
# that a rebuild reproduces the shipped files byte for byte).
# Every choice below (axes, class, real-world dimensions) is recorded in library.json; the
# reasons are in docs/library.md. Axes were checked on `adv3d assets preview` renders.
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
PACKS="$(cd "${1:-$REPO/../shared/vehicle-packs}" && pwd)"
PY="${PYTHON:-$REPO/.venv/bin/python}"
[ -x "$PY" ] || PY=python3
cd "$REPO"
OUT="${ADV3D_LIBRARY_DIR:-$REPO/assets/vehicles}"
LIB="$OUT/library.json"
adv3d() { "$PY" -m adv3d_runner.cli --quiet "$@" --library "$LIB"; }

# start clean so removed assets do not linger (git keeps the previous library)
rm -f "$LIB"
rm -rf "$OUT/quaternius-cars" "$OUT/quaternius-transport" "$OUT/kenney-car-kit"

# --- Quaternius "Realistic Car Pack" (CC0): .blend files, Blender Z up, front towards -Y ----
# Already metric and within 30 % of their class's typical size on every axis: kept as modelled.
Q="$PACKS/quaternius-realistic-car-pack"
QC=(--source-pack quaternius-cars --author Quaternius --url https://quaternius.com --forward=-y
    --note "kept as modelled: metric, and within 30 % of the class's typical size on every axis")
adv3d assets import "$Q/NormalCar1.blend" --class sedan     "${QC[@]}"
adv3d assets import "$Q/NormalCar2.blend" --class hatchback     "${QC[@]}"
adv3d assets import "$Q/Cop.blend"        --class sedan     "${QC[@]}"
adv3d assets import "$Q/Taxi.blend"       --class sedan     "${QC[@]}"
adv3d assets import "$Q/SUV.blend"        --class suv       "${QC[@]}"
adv3d assets import "$Q/SportsCar.blend"  --class sports    "${QC[@]}"
adv3d assets import "$Q/SportsCar2.blend" --class sports    "${QC[@]}"

# --- Quaternius "Public Transport Pack" (CC0) -------------------------------------------------
T="$PACKS/quaternius-public-transport-pack"
# cars face -Y like the car pack; the two buses are modelled along the file's X axis, front at -X.
# The pack's scale is toy-like for the large vehicles (a 4.1 m city bus): those are curated to
# real class dimensions; the taxi is already a plausible metric size and is kept as modelled.
QT=(--source-pack quaternius-transport --author Quaternius --url https://quaternius.com)
adv3d assets import "$T/Taxi.blend"       --class sedan     "${QT[@]}" --forward=-y \
    --note "kept as modelled: metric, and within 30 % of the class's typical size on every axis"
adv3d assets import "$T/Ambulance.blend"  --class ambulance "${QT[@]}" --forward=-y --dimensions 6.00 2.30 2.80 \
    --note "modelled 5.72 x 2.84 x 2.91 m (too wide for a road vehicle): scaled to a box ambulance on a van chassis" --exclude-from-shape-space
adv3d assets import "$T/Bus.blend"        --class bus       "${QT[@]}" --forward=-x --dimensions 12.00 2.55 3.20 \
    --note "modelled as a 4.1 m toy bus: scaled to a standard 12 m city bus (EU max width 2.55 m)" --exclude-from-shape-space
adv3d assets import "$T/SchoolBus.blend"  --class bus       "${QT[@]}" --forward=-x --dimensions 11.50 2.44 3.20 \
    --note "modelled as a 4.6 m toy bus: scaled to a conventional (type C) US school bus" --exclude-from-shape-space

# --- Kenney "Car Kit" 2.0 (CC0): glTF Y up, front towards +Z; toy proportions -> real sizes ----
K="$PACKS/kenney-car-kit"
KK=(--source-pack kenney-car-kit --author "Kenney (www.kenney.nl)" --url https://kenney.nl/assets/car-kit --up=+y --forward=+z)
TOY="toy proportions scaled to typical real dimensions of the class"
adv3d assets import "$K/sedan.glb"            --class sedan     --dimensions 4.70 1.80 1.45 "${KK[@]}" --note "$TOY (mid-size sedan, e.g. VW Passat 4.78 x 1.83 x 1.48)"
adv3d assets import "$K/sedan-sports.glb"     --class sports    --dimensions 4.60 1.85 1.35 "${KK[@]}" --note "$TOY (sports sedan/coupe)"
adv3d assets import "$K/hatchback-sports.glb" --class hatchback --dimensions 4.25 1.80 1.45 "${KK[@]}" --note "$TOY (hot hatch, e.g. VW Golf GTI 4.29 x 1.79 x 1.46)"
adv3d assets import "$K/police.glb"           --class sedan     --dimensions 4.90 1.90 1.70 "${KK[@]}" --note "$TOY (police sedan, height includes the light bar)"
adv3d assets import "$K/taxi.glb"             --class sedan     --dimensions 4.80 1.80 1.70 "${KK[@]}" --note "$TOY (taxi sedan, height includes the roof sign)"
adv3d assets import "$K/suv.glb"              --class suv       --dimensions 4.70 1.90 1.85 "${KK[@]}" --note "$TOY (off-road SUV, e.g. Jeep Wrangler 4.3-4.9 x 1.9 x 1.85)"
adv3d assets import "$K/suv-luxury.glb"       --class suv       --dimensions 5.00 2.00 1.80 "${KK[@]}" --note "$TOY (full-size luxury SUV)"
adv3d assets import "$K/van.glb"              --class van       --dimensions 5.20 2.00 2.10 "${KK[@]}" --note "$TOY (passenger van, e.g. VW Transporter 5.3 x 1.9 x 2.0)"
adv3d assets import "$K/delivery.glb"         --class truck     --dimensions 6.60 2.30 3.10 "${KK[@]}" --note "$TOY (cab with a separate cargo box: a 3.5 t box truck, e.g. Ford Transit Luton 6.6 x 2.3 x 3.1)" --exclude-from-shape-space
adv3d assets import "$K/truck.glb"            --class pickup    --dimensions 5.50 2.00 1.85 "${KK[@]}" --note "$TOY (pickup, e.g. Toyota Hilux double cab 5.3 x 1.86 x 1.8)"
adv3d assets import "$K/truck-flat.glb"       --class pickup    --dimensions 5.50 2.00 1.85 "${KK[@]}" --note "$TOY (flatbed pickup)"
adv3d assets import "$K/delivery-flat.glb"    --class truck     --dimensions 7.00 2.30 2.60 "${KK[@]}" --note "$TOY (light flatbed truck, 7.5 t class)" --exclude-from-shape-space
adv3d assets import "$K/ambulance.glb"        --class ambulance --dimensions 6.50 2.30 2.80 "${KK[@]}" --note "$TOY (box ambulance, EN 1789 type C on a van chassis)" --exclude-from-shape-space
adv3d assets import "$K/firetruck.glb"        --class fire_truck --dimensions 9.00 2.50 3.30 "${KK[@]}" --note "$TOY (fire engine, e.g. HLF 20 on a 16 t chassis)" --exclude-from-shape-space
adv3d assets import "$K/garbage-truck.glb"    --class garbage_truck --dimensions 9.50 2.50 3.50 "${KK[@]}" --note "$TOY (rear-loader refuse truck, 3 axles)" --exclude-from-shape-space
adv3d assets exclude "$K/race.glb" "$K/race-future.glb" --source-pack kenney-car-kit \
    --reason "open-wheel racing car: not a road vehicle (not street legal, never in road traffic scenes)"

adv3d assets check
