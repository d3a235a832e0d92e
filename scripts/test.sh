#!/usr/bin/env bash
# Run the test suite offline on CPU (kernel cache kept in ~/.cache/warp between runs).
set -euo pipefail
cd "$(dirname "$0")/.."
export HF_HUB_OFFLINE=1 PYTHONUNBUFFERED=1
exec .venv/bin/python -m pytest -q "$@"
