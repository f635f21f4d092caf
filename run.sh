#!/usr/bin/env bash
# The README's main command: set up .venv (first run), then relight the built-in demo clip with
# the batch script on the bpy module into out/demo/. Extra arguments go to the batch script
# (e.g. ./run.sh --studio forest --preset fast). out/demo/ is this command's own scratch folder:
# --overwrite lets a rerun after an update (another model or default) replace the earlier demo run
# instead of refusing it.
set -euo pipefail
cd "$(dirname "$0")"
bash tools/bootstrap.sh
exec .venv/bin/python scripts/relight_batch.py --demo --out out/demo --overwrite "$@"
