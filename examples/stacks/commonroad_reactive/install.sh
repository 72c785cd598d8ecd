#!/usr/bin/env bash
# Autonomy-C in one command (run from anywhere):
#   bash examples/stacks/commonroad_reactive/install.sh
# 1. this folder's own venv (.venv, Python 3.11: commonroad-reactive-planner needs < 3.12) from
#    requirements.lock.txt, with the adv3d_crp adapter installed editable;
# 2. the plugin (plugin/, entry point C of adv3d.stacks) installed editable into adv3d's venv
#    ($ADV3D_VENV, default <adv3d checkout>/.venv);
# 3. `adv3d stacks info C` starts the stack once and prints what it is.
# $PYTHON names the interpreter for step 1 (default python3.11).
set -euo pipefail
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
ROOT="$(cd "$HERE/../../.." && pwd)"
ADV3D_VENV="${ADV3D_VENV:-$ROOT/.venv}"
PY="${PYTHON:-python3.11}"

if [ ! -x "$ADV3D_VENV/bin/python" ]; then
    echo "install.sh: no adv3d venv at $ADV3D_VENV (set ADV3D_VENV)" >&2
    exit 1
fi
if [ ! -x "$HERE/.venv/bin/python" ]; then
    "$PY" -m venv "$HERE/.venv"
fi
"$HERE/.venv/bin/python" -m pip install -q -r "$HERE/requirements.lock.txt"
"$HERE/.venv/bin/python" -m pip install -q --no-deps -e "$HERE"
"$ADV3D_VENV/bin/python" -m pip install -q --no-deps -e "$HERE/plugin"
"$ADV3D_VENV/bin/adv3d" stacks info C
