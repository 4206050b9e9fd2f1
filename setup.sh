#!/usr/bin/env bash
# One-step set-up: a virtual environment in .venv with cobel and everything its tests need.
# Idempotent: re-running it only installs what changed. Works on any Linux/macOS with Python >= 3.11.
set -euo pipefail
cd "$(dirname "$0")"

PYTHON="${PYTHON:-python3}"
VENV="${COBEL_VENV:-.venv}"
EXTRAS="${COBEL_EXTRAS:-all,dev,docs}"

if [ ! -x "$VENV/bin/python" ]; then
  "$PYTHON" -m venv "$VENV"
fi
PIP=("$VENV/bin/python" -m pip --disable-pip-version-check -q)
# some machines list pip index folders that do not exist; pip warns once per package about them
quiet_pip() { "${PIP[@]}" "$@" 2> >(grep -v "is ignored: it is neither a file nor a directory" >&2); }

# Fast route for torch: where pip's find-links folder holds a CPU build of torch (as on our
# CI machines), install that file first so that resolving the deep extras does not download
# several GB of CUDA packages. Elsewhere this finds nothing and pip resolves torch normally.
local_torch=$("$VENV/bin/python" - <<'PY'
import glob, os, subprocess, sys
dirs = [d for d in os.environ.get("PIP_FIND_LINKS", "").split() if d]
try:
    out = subprocess.run([sys.executable, "-m", "pip", "config", "list"], capture_output=True, text=True).stdout
    for line in out.splitlines():
        if "find-links" in line:
            dirs += line.split("=", 1)[1].strip().strip("'\"").split()
except Exception:
    pass
tag = f"cp{sys.version_info.major}{sys.version_info.minor}"
for d in dirs:
    d = d.removeprefix("file://")
    hits = sorted(glob.glob(os.path.join(d, f"torch-*+cpu-{tag}-*.whl")))
    if hits:
        print(hits[-1])
        break
PY
)
if [ -n "$local_torch" ] && ! "$VENV/bin/python" -c "import torch" 2>/dev/null; then
  echo "setup: installing local CPU torch wheel $(basename "$local_torch")"
  quiet_pip install "$local_torch"
fi

quiet_pip install -e ".[${EXTRAS}]"
echo "setup: ready ($VENV/bin/cobel)"
