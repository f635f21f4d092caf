#!/usr/bin/env bash
# Creates .venv and installs the pinned requirements; quiet and quick when nothing changed.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3.11}
command -v "$PY" >/dev/null 2>&1 || PY=python3
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
  .venv/bin/python -m pip install -q --upgrade pip
fi
stamp=.venv/.requirements.sha256
want=$(cat requirements.txt requirements-train.txt | sha256sum | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "[bootstrap] installing requirements into .venv (first run takes a few minutes)"
  .venv/bin/python -m pip install -q -r requirements.txt -r requirements-train.txt
  # Some packages pull numpy 2 in silently; bpy 5.0.1 needs numpy<2.
  .venv/bin/python -m pip install -q "numpy==1.26.4"
  echo "$want" > "$stamp"
fi
