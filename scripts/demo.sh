#!/usr/bin/env bash
# Set everything up (idempotent) and run the main demo: RUMI rummaging for the pose of a mug whose handle faces away from the camera (task mug-2).
# Figures and CSV/JSON results land in runs/demo/.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/activetouch demo --out runs/demo "$@"
