#!/usr/bin/env bash
# CommonRoad CriMe for adv3d's criticality figures (docs/attack.md, "Criticality (CriMe)"), in one
# command (run from anywhere):
#   bash examples/crime/install.sh
# builds this folder's own venv (.venv, Python 3.11) from requirements.lock.txt: CriMe cannot go
# into adv3d's venv (it pulls numpy 2 and commonroad-io 2024.3; adv3d keeps numpy < 2 for bpy and
# commonroad-io 2026.1). adv3d finds it there, or where $ADV3D_CRIME_PYTHON points; then it checks
# that the server starts. $PYTHON names the interpreter (default python3.11).
set -euo pipefail
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
ROOT="$(cd "$HERE/../.." && pwd)"
PY="${PYTHON:-python3.11}"

if [ ! -x "$HERE/.venv/bin/python" ]; then
    "$PY" -m venv "$HERE/.venv"
fi
"$HERE/.venv/bin/python" -m pip install -q -r "$HERE/requirements.lock.txt"
HELLO="$("$HERE/.venv/bin/python" -P "$ROOT/adv3d_runner/sim/crime_server.py" < /dev/null 2>/dev/null)"
echo "$HELLO"
case "$HELLO" in
    *'"ready": true'*) echo "CriMe ready: adv3d attack evaluations now carry criticality figures" ;;
    *) echo "install.sh: the CriMe server does not start" >&2; exit 1 ;;
esac
