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
rm -rf "$OUT/quaternius-cars" "$OUT/quaternius-transport" "$OUT/kenney-car-kit" "$OUT/quaternius-cars-bundle" \
    "$OUT/quaternius-car-pack-2016" "$OUT/quaternius-basic-car-pack-2017" "$OUT/kaykit-city-builder-bits" \
    "$OUT/khronos-cesium-milk-truck" "$OUT/openmaterial-examples"
# where the pack says where it comes from, that travels with its meshes too
source_txt() { mkdir -p "$OUT/$2" && cp "$1/SOURCE.txt" "$OUT/$2/SOURCE.txt"; }

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

# --- Packs added for shape space v2 (issue 13). Axes checked on `adv3d assets preview` and on
# each pack's Preview image; fronts of the untextured Quaternius .blend cars told by the
# windscreen (more raked than the rear window) and the hood (longer and lower than the trunk).
TOYV2="toy proportions scaled to real dimensions of the class"

# Quaternius "Cars Bundle" pickup (CC0; licence evidence in SOURCE.txt): glTF Y up, front +Z.
# Modelled 5.18 x 2.31 x 1.85 m (2.31 m is wider than any pickup); kept at 5.5 m long so the
# shape-space cube (1.1 x the longest shape-space vehicle) keeps its 9.6 cm voxel.
QB="$PACKS/quaternius-cars-bundle-pickup"
adv3d assets import "$QB/car-pickup.glb" --class pickup --id quaternius-cars-bundle.pickup --source-pack quaternius-cars-bundle \
    --up=+y --forward=+z --dimensions 5.50 2.05 2.00 --licence-file "$QB/SOURCE.txt" --licence CC0-1.0 \
    --author Quaternius --url https://poly.pizza/m/qn4grQgHm8 \
    --note "$TOYV2 (lifted full-size extended-cab pickup, e.g. Chevrolet Silverado Double Cab 5.84 x 2.06 x 1.9)"
source_txt "$QB" quaternius-cars-bundle

# Quaternius "Car Pack - Mar 2016" (CC0): .blend, Z up; chunky toys 4.5-6.1 m long.
Q16="$PACKS/quaternius-car-pack-2016"
Q16A=(--source-pack quaternius-car-pack-2016 --author Quaternius --url https://quaternius.com)
adv3d assets import "$Q16/Car.blend"       --class sedan     --forward=-y --dimensions 4.70 1.80 1.45 "${Q16A[@]}" --note "$TOYV2 (modelled 6.12 x 2.57 x 2.42 m; 3-box sedan, e.g. VW Passat 4.78 x 1.83 x 1.48)"
adv3d assets import "$Q16/SimpleCar.blend" --class hatchback --forward=+x --dimensions 3.70 1.65 1.55 "${Q16A[@]}" --note "$TOYV2 (modelled 4.55 x 2.25 x 2.24 m; boxy small car, e.g. Fiat Panda 3.65 x 1.64 x 1.55)"
adv3d assets import "$Q16/Truck.blend"     --class pickup    --forward=+x --dimensions 5.30 2.00 1.85 "${Q16A[@]}" --note "$TOYV2 (modelled 6.02 x 2.51 x 2.39 m; regular-cab pickup, e.g. Ford F-150 regular cab 5.3 x 2.03 x 1.91)"
source_txt "$Q16" quaternius-car-pack-2016

# Quaternius "Basic Car Pack - Jan 2017" (CC0): .blend (the .fbx fail in bpy 5.0), Z up, front -Y.
Q17="$PACKS/quaternius-basic-car-pack-2017"
Q17A=(--source-pack quaternius-basic-car-pack-2017 --author Quaternius --url https://quaternius.com --forward=-y)
adv3d assets import "$Q17/BasicCar.blend"      --class sedan --dimensions 4.40 1.75 1.45 "${Q17A[@]}" --note "$TOYV2 (modelled 4.20 x 2.01 x 1.58 m, too wide; compact sedan, e.g. VW Polo sedan 4.39 x 1.70 x 1.47)"
adv3d assets import "$Q17/SimpleCarHigh.blend" --class sedan --dimensions 4.60 1.80 1.45 "${Q17A[@]}" --note "$TOYV2 (modelled 4.03 x 2.14 x 1.60 m, too wide; sedan)"
adv3d assets exclude "$Q17/SimpleCarShort.blend" "$Q17/Taxi.blend" "$Q17/CopCar.blend" --source-pack quaternius-basic-car-pack-2017 \
    --reason "variant of one body (SimpleCarShort, Taxi and CopCar share it; the pack README says so): one body per shape"
adv3d assets exclude "$Q17/RaceCar.blend" --source-pack quaternius-basic-car-pack-2017 \
    --reason "race car (hood scoop and spoiler street racer): not a road vehicle of traffic scenes"
source_txt "$Q17" quaternius-basic-car-pack-2017

# KayKit "City Builder Bits" (CC0): glTF Y up, front +Z (the wheel nodes say front/rear); 0.94 m toys.
KK2="$PACKS/kaykit-city-builder-bits"
KKA=(--source-pack kaykit-city-builder-bits --author "Kay Lousberg (www.kaylousberg.com)" --url https://kaylousberg.com --up=+y --forward=+z)
adv3d assets import "$KK2/car_hatchback.gltf"    --class hatchback --id kaykit-city-builder-bits.hatchback    --dimensions 4.10 1.75 1.50 "${KKA[@]}" --note "$TOYV2 (modelled 0.81 m long; hatchback, e.g. VW Golf 4.28 x 1.79 x 1.46)"
adv3d assets import "$KK2/car_sedan.gltf"        --class sedan     --id kaykit-city-builder-bits.sedan        --dimensions 4.70 1.80 1.45 "${KKA[@]}" --note "$TOYV2 (modelled 0.94 m long; mid-size sedan)"
adv3d assets import "$KK2/car_stationwagon.gltf" --class sedan     --id kaykit-city-builder-bits.stationwagon --dimensions 4.80 1.83 1.50 "${KKA[@]}" --note "$TOYV2 (modelled 0.94 m long; station wagon, e.g. VW Passat Variant 4.77 x 1.83 x 1.52; class sedan: same footprint)"
adv3d assets exclude "$KK2/car_taxi.gltf" "$KK2/car_police.gltf" --source-pack kaykit-city-builder-bits \
    --reason "variant of the sedan body (roof sign / light bar added): one body per shape"
source_txt "$KK2" kaykit-city-builder-bits

# Godot "Truck Town" demo (MIT): four bodies in one glb.
GT="$PACKS/godot-truck-town"
adv3d assets exclude "$GT/meshes.glb" --source-pack godot-truck-town \
    --reason "minivan, tow truck and tractor cab are body shells without wheels (the demo mounts wheel nodes at run time; their positions are not in the pack) and the fourth body is a semi-trailer; stored alone each would stand on its floor pan"

# Khronos glTF sample "Cesium Milk Truck" (CC-BY 4.0 with a trademark limitation on the logo
# texture; geometry plain CC-BY; attribution: "Cesium Milk Truck (c) 2017 Cesium"): Y up, front +Z.
CM="$PACKS/khronos-cesium-milk-truck"
adv3d assets import "$CM/CesiumMilkTruck.glb" --class truck --id khronos-cesium-milk-truck.milk-truck --source-pack khronos-cesium-milk-truck \
    --up=+y --forward=+z --dimensions 6.00 2.30 2.90 --licence-file "$CM/LICENSE.md" --licence LicenseRef-CC-BY-TM \
    --author "Cesium (c) 2017 Cesium" --url https://github.com/KhronosGroup/glTF-Sample-Assets --exclude-from-shape-space \
    --note "$TOYV2 (modelled 4.87 x 2.79 x 2.58 m; step van, e.g. a 6 m walk-in delivery van 6.0 x 2.3 x 2.9)"
source_txt "$CM" khronos-cesium-milk-truck

# OpenMaterial examples (CC-BY-SA 4.0, attribution: OpenMaterial project; share-alike applies to
# these files): glTF Y up, front -X, metric, with interiors (seats, dashboard, steering wheel).
OM="$PACKS/openmaterial-examples"
OMA=(--source-pack openmaterial-examples --author "OpenMaterial project (Ludwig Friedmann et al.)" \
     --url https://github.com/LudwigFriedmann/OpenMATERIAL --up=+y --forward=-x --licence-file "$OM/README.md" --licence CC-BY-SA-4.0)
adv3d assets import "$OM/vehicle_example.gltf" --class sports --id openmaterial-examples.coupe "${OMA[@]}" \
    --note "kept as modelled: metric CAD-like model (1950s coupe, e.g. VW Karmann Ghia 4.14 x 1.63 x 1.33)"
adv3d assets import "$OM/truck_example.gltf" --class truck --id openmaterial-examples.rigid-truck "${OMA[@]}" --exclude-from-shape-space \
    --note "kept as modelled: metric CAD-like model (7.5-12 t rigid truck with tarpaulin body; width includes the mirrors)"
source_txt "$OM" openmaterial-examples

adv3d assets check
