#!/usr/bin/env bash
# Sets up .venv (first run) and runs every test. Tests needing ../shared/data skip where it is absent.
set -euo pipefail
cd "$(dirname "$0")"
bash tools/bootstrap.sh
exec .venv/bin/python -m pytest -q -p no:cacheprovider "$@" tests
