# shellcheck shell=bash disable=SC2154,SC2034  # `me`, `usage_line` come from the sourcing script; `in`, `out`, `model`, `encode_flags` go to it
# Sourced by parallel.sh and slurm-submit.sh: what both do the same way. The caller sets `me`
# (its name) and `usage_line` (its synopsis) first.

die() {
  echo "$me: error: $*" >&2
  exit 1
}
usage() {
  echo "usage: $me $usage_line   (--help for more)" >&2
  exit 2
}
positive() { [[ $1 =~ ^[1-9][0-9]*$ ]]; }
# --help: the comment block at the top of the script $1.
show_help() {
  sed -n '2,/^set -euo/p' "$1" | sed '$d' | sed 's/^# \{0,1\}//'
  exit 0
}
# The path of colf binary $1 (in COLF's folder, or from PATH).
bin() { echo "${colf_dir:+$colf_dir/}$1"; }

# setup IN OUT STAGE...: checks the settings both scripts share (FRAMES, SIZE, RADIUS,
# ELEVATION, CHUNK, COLF, MODEL, SLOTS, ENCODE_FLAGS) and sets `in` and `out` (absolute paths;
# OUT/logs made), `colf_dir`, `model` (absolute, or empty for the bundled one), `encode_flags`
# and `images` (IN/*.png, at least one). The colf binaries STAGE... must exist. Paths are made
# absolute because the jobs may run on other hosts, in other working folders.
setup() {
  FRAMES=${FRAMES:-8} SIZE=${SIZE:-64} RADIUS=${RADIUS:-12.4} ELEVATION=${ELEVATION:-40}
  CHUNK=${CHUNK:-8}
  positive "$CHUNK" || die "CHUNK=$CHUNK: not a positive whole number"
  [ -d "$1" ] || die "$1: no such folder"
  in=$(cd "$1" && pwd)
  mkdir -p "$2/logs" || die "$2: cannot create the output folder"
  out=$(cd "$2" && pwd)
  shift 2
  colf_dir=
  if [ -n "${COLF:-}" ]; then
    [ -d "$COLF" ] || die "COLF=$COLF: no such folder"
    colf_dir=$(cd "$COLF" && pwd)
  fi
  local stage
  for stage in "$@"; do
    command -v "$(bin "$stage")" >/dev/null ||
      die "$(bin "$stage"): not found (set COLF to the folder of the colf binaries)"
  done
  model=
  if [ -n "${MODEL:-}" ]; then
    [ -f "$MODEL" ] || die "MODEL=$MODEL: no such file"
    model=$(cd "$(dirname "$MODEL")" && pwd)/$(basename "$MODEL")
  fi
  read -r -a encode_flags <<<"${ENCODE_FLAGS:-}"
  [ -z "${SLOTS:-}" ] || encode_flags+=(--slots "$SLOTS")
  shopt -s nullglob
  images=("$in"/*.png)
  [ ${#images[@]} -gt 0 ] || die "$in: no .png images"
}
