#!/usr/bin/env bash
# A run folder's pipeline (runs/<name>/config.yaml; wc/run_folder.py) run by DVC on this machine, from a bare machine
# to the run's DVC record, resumably: run it again after an interruption and DVC skips every stage its lock records
# as done (docs/gpu.md, docs/versioning.md).
#
#   bash scripts/gpu/run_pipeline.sh run RUN [STAGE]     set up, then dvc repro RUN/dvc.yaml (up to STAGE), then push
#   bash scripts/gpu/run_pipeline.sh pack RUN DEST [STAGE ...]
#        the run's record (params.yaml, dvc.yaml, dvc.lock, its git-tracked reports) and the DVC objects of the
#        STAGEs' outputs (default: every stage's and the run's inputs') as DEST/run.tar.NN pieces of PIECE_MB (15) MB
#   bash scripts/gpu/run_pipeline.sh unpack SRC         those pieces back: the record into the run folder, the
#        objects into .dvc/cache, where the next `run` finds the packed stages' outputs
#
# Environment of `run` and `pack`:
#   WHEELS=DIR     an offline machine: .venv made on BASE_PYTHON (default python3, an interpreter with torch 2.11)
#                  plus the wheels under DIR: *.whl files (pip download), or the part-* pieces of an xz tar of
#                  tmp/site/<unpacked wheels>; scripts/gpu/missing_wheels.py lists what a machine lacks.
#                  Without it: scripts/install.sh (network) unless .venv exists.
#   PUSH=0         skip the final `dvc push` of the run's outputs to the default remote (.dvc/config)
#   FORCE=1        `run` starts the record afresh (removes RUN/dvc.lock): for a committed record whose outputs no cache
#                  or remote here holds (DVC would skip the recorded stages and fail where a later one needs them)
set -euo pipefail
cd "$(dirname "$0")/../.."
PY=.venv/bin/python
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"  # this checkout's code, from any run folder
export HF_HUB_OFFLINE=${HF_HUB_OFFLINE:-1}  # the pipeline reads no hub: no network waits on an offline machine
TMP=$(mktemp -d); trap 'rm -rf "$TMP"' EXIT
usage() { echo "usage: $0 run RUN [STAGE] | pack RUN DEST [STAGE ...] | unpack SRC" >&2; exit 2; }
fail() { echo "run_pipeline: error: $*" >&2; exit 2; }
# dvc in the run folder RUN: DVC (3.67) pulls a stage's missing dependency by its path relative to the current
# directory, so a run folder's pipeline is reproduced from inside it
dvc_in() { local run=$1; shift; (cd "$run" && "$OLDPWD/$PY" -m dvc "$@"); }

# .venv from BASE_PYTHON + the wheels in $WHEELS: the base interpreter's packages (torch) stay visible through a .pth,
# the wheels unpack into the venv, the repository is importable from any run folder
venv_from_wheels() {
  local base=${BASE_PYTHON:-python3} site wheels parts stamp
  wheels=$(find "$WHEELS" -type f -name '*.whl' | sort)
  # a pack's parts are numbered across its folders (.gpu/1/part-00, .gpu/2/part-01, ...): all, in that order
  parts=$(find "$WHEELS" -type f -name 'part-*' -printf '%f %p\n' | sort | cut -d' ' -f2-)
  [ -n "$wheels$parts" ] || fail "WHEELS=$WHEELS holds no *.whl or part-* files"
  "$base" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 12))' || fail "BASE_PYTHON=$base is not Python 3.12"
  [ -x $PY ] || "$base" -m venv --without-pip .venv
  stamp=$(ls -l $wheels $parts | md5sum)
  [ "$(cat .venv/wheels.md5 2>/dev/null)" = "$stamp" ] && return  # these wheels are in already
  site=$($PY -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
  "$base" -c 'import site; print("\n".join(site.getsitepackages()))' > "$site/base_python.pth"
  [ -z "$parts" ] || cat $parts | xz -dc -T0 | tar x -C "$site" --strip-components=2  # a pack holds tmp/site/...
  [ -z "$wheels" ] || "$base" -m pip install -q --no-index --no-deps --no-compile --upgrade --target "$site" $wheels
  echo "$PWD" > "$site/worldcontact_repository.pth"
  echo "$stamp" > .venv/wheels.md5
}

setup() {
  if [ -n "${WHEELS:-}" ]; then venv_from_wheels; elif [ ! -x $PY ]; then bash scripts/install.sh; fi
  $PY -c 'import importlib.util as u, sys; m = [n for n in sys.argv[1:] if u.find_spec(n) is None]
sys.exit(f"run_pipeline: error: {sys.executable} lacks {m} (scripts/gpu/missing_wheels.py)" if m else 0)' \
    dvc torch warp newton zarr trimesh lerobot wc
  if command -v nvidia-smi >/dev/null 2>&1; then  # Newton's CUDA kernels, compiled ahead (docs/gpu.md)
    local cache=${WARP_CACHE_PATH:-$HOME/.cache/warp}
    mkdir -p "$cache"
    for k in scripts/gpu/kernel_cache/*.tar.xz; do xz -dc "$k" | tar x -C "$cache" --skip-old-files; done
  fi
  if ! git rev-parse --is-inside-work-tree >/dev/null 2>&1; then  # a copy without git: DVC without an SCM
    $PY -m dvc config --local core.no_scm true
  fi
}

run() {
  local run=${1%/} stage=${2:-}
  [ -f "$run/config.yaml" ] || fail "no $run/config.yaml (a run folder, e.g. runs/gpu_policy)"
  setup
  $PY -m wc.run_folder --unfrozen "$run"  # frozen as committed: the root `dvc repro` leaves run folders alone
  [ -z "${FORCE:-}" ] || rm -f "$run/dvc.lock"  # a fresh record: every stage runs (git keeps the committed one)
  local rc=0
  dvc_in "$run" repro --pull --allow-missing ${stage:+"dvc.yaml:$stage"} || rc=$?
  $PY -m wc.run_folder "$run"  # frozen again, whatever the repro did
  [ "$rc" = 0 ] || exit "$rc"
  [ "${PUSH:-1}" = 0 ] || dvc_in "$run" push --with-deps dvc.yaml
}

pack() {
  local run=${1%/} dest=$2; shift 2
  [ -f "$run/dvc.lock" ] || fail "no $run/dvc.lock: nothing of $run has run yet"
  setup
  local targets=(--with-deps dvc.yaml); [ $# -gt 0 ] && targets=("${@/#/dvc.yaml:}")
  $PY -m dvc remote add --local --force pack "$TMP/objects"  # a remote of its own: only these stages' objects
  dvc_in "$run" push -r pack "${targets[@]}"
  $PY -m dvc remote remove --local pack
  mkdir -p "$TMP/stage/.dvc/cache" "$dest" && rm -f "$dest"/run.tar.*
  [ ! -d "$TMP/objects" ] || cp -r "$TMP/objects/." "$TMP/stage/.dvc/cache/"
  $PY -m wc.run_folder --record "$run" | tar cf - -T - | tar x -C "$TMP/stage"
  tar cf - -C "$TMP/stage" . | split -b "${PIECE_MB:-15}M" -d - "$dest/run.tar."
  ls -la "$dest"/run.tar.*
}

unpack() {
  local src=$1
  ls "$src"/run.tar.* >/dev/null 2>&1 || fail "$src holds no run.tar.* pieces (run_pipeline.sh pack)"
  cat "$src"/run.tar.* | tar x -C "$TMP"
  mkdir -p .dvc/cache
  cp -rn "$TMP/.dvc/cache/." .dvc/cache/  # content-addressed: an object already here is the same
  rm -rf "$TMP/.dvc"
  cp -r "$TMP/." .
  echo "run_pipeline: unpacked $(find "$TMP" -type f | wc -l) record files and the packed DVC objects"
}

case "${1:-}" in
  run) [ $# -ge 2 ] && [ $# -le 3 ] || usage; shift; run "$@" ;;
  pack) [ $# -ge 3 ] || usage; shift; pack "$@" ;;
  unpack) [ $# -eq 2 ] || usage; unpack "$2" ;;
  *) usage ;;
esac
