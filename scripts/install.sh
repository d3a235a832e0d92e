#!/usr/bin/env bash
# Install the project and its pinned stack into ./.venv (Python 3.12). Idempotent; ~1 min with uv.
set -euo pipefail
cd "$(dirname "$0")/.."

find_python312() {
  local candidates=("${PYTHON312:-}" "$HOME"/.pyenv/versions/3.12*/bin/python3.12 /root/.pyenv/versions/3.12*/bin/python3.12
                    /usr/local/bin/python3.12 /usr/bin/python3.12)
  if command -v pyenv >/dev/null 2>&1; then
    candidates+=("$(pyenv root)"/versions/3.12*/bin/python3.12)
  fi
  for c in "${candidates[@]}"; do
    if [ -n "$c" ] && [ -x "$c" ] && "$c" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 12))' 2>/dev/null; then
      echo "$c"; return 0
    fi
  done
  return 1
}

if [ ! -x .venv/bin/python ] || ! .venv/bin/python -c 'import sys; sys.exit(sys.version_info[:2] != (3, 12))'; then
  py=$(find_python312) || { echo "install: no Python 3.12 interpreter found (set PYTHON312=/path/to/python3.12)" >&2; exit 1; }
  echo "install: creating .venv with $py"
  rm -rf .venv
  "$py" -m venv .venv
fi
.venv/bin/python -m pip install -q --disable-pip-version-check uv==0.13.9
.venv/bin/uv pip install -q --python .venv/bin/python --compile-bytecode -r requirements.lock  # bytecode now, not in every stage process
.venv/bin/uv pip install -q --python .venv/bin/python --no-deps -e .
echo "install: done ($(du -sh .venv | cut -f1) in .venv)"
