#!/usr/bin/env bash
# Encode every PNG of a folder and render an orbit of each on a Slurm cluster: counts the images
# and the frames, then submits three jobs (docs/cluster.md):
#
#   1. encode-array.sbatch, an array of one task per image        (--array=0-(images - 1))
#   2. render-array.sbatch, an array of one task per CHUNK frames of each image, after 1 succeeded
#                                                                 (--array=0-(images × chunks - 1))
#   3. sheet.sbatch, the contact sheet OUT/sheet.png (colf-sheet), after 2 succeeded
#
#   examples/cluster/slurm-submit.sh [--wait] IN OUT
#
# IN/NAME.png is encoded to OUT/NAME.codes (IN/NAME.json is its camera when there is one), and
# the cameras rendered to OUT/NAME/ (PNG + mask). IN, OUT, CAMERAS, MODEL and the colf binaries
# (COLF) must be at the same paths on every node: a shared folder. The job ids go to stdout, one
# a line; the task logs to OUT/logs/. A job that fails cancels the jobs after it
# (--kill-on-invalid-dep). Submitting again redoes only what is missing or older than its inputs.
# --wait: wait for the last job (sbatch --wait) and exit 0 only if it completed.
#
# Environment: COLF (folder of the colf binaries; empty = from PATH), FRAMES (8), SIZE (64),
# RADIUS (12.4), ELEVATION (40), CAMERAS (a transforms.json to render instead of the orbit
# OUT/orbit.json), CHUNK (frames a render task, 8), SLOTS (empty = the model's default), MODEL
# (empty = the bundled default), ENCODE_FLAGS (more colf-encode flags, e.g. --fast), THREADS
# (CPUs a task, sbatch --cpus-per-task, 1), ARRAY_LIMIT (most tasks of an array running at once,
# sbatch --array=...%N; empty = no limit), SBATCH_FLAGS (more sbatch flags for every job, e.g.
# "--partition=cpu --time=1:00:00").
# Exit status: 0 submitted (or, with --wait, done), 1 an error (one line on stderr), 2 usage.
set -euo pipefail

me=slurm-submit.sh
# shellcheck disable=SC2034  # read by common.sh
usage_line="[--wait] IN OUT"
here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
# shellcheck source=examples/cluster/common.sh
. "$here/common.sh"

wait=
while [ $# -gt 0 ]; do
  case $1 in
    --wait)
      wait=1
      shift
      ;;
    -h | --help)
      show_help "$0"
      ;;
    --)
      shift
      break
      ;;
    -*) usage ;;
    *) break ;;
  esac
done
[ $# -eq 2 ] || usage

THREADS=${THREADS:-1} ARRAY_LIMIT=${ARRAY_LIMIT:-}
positive "$THREADS" || die "THREADS=$THREADS: not a positive whole number"
[ -z "$ARRAY_LIMIT" ] || positive "$ARRAY_LIMIT" || die "ARRAY_LIMIT=$ARRAY_LIMIT: not a positive whole number"
command -v sbatch >/dev/null || die "sbatch not found (is this a Slurm login node?)"
setup "$1" "$2" colf-encode colf-render colf-cameras colf-sheet
colf=$colf_dir
read -r -a sbatch_flags <<<"${SBATCH_FLAGS:-}"

# The images, in the order of the array's task ids.
list=$out/logs/images.txt
for img in "${images[@]}"; do
  printf '%s\n' "$(basename "$img" .png)"
done >"$list.new"
mv "$list.new" "$list"

if [ -n "${CAMERAS:-}" ]; then
  [ -f "$CAMERAS" ] || die "CAMERAS=$CAMERAS: no such file"
  cams=$(cd "$(dirname "$CAMERAS")" && pwd)/$(basename "$CAMERAS")
else
  # Rewritten only when it changes, so its time stamp says when the cameras last changed.
  cams=$out/orbit.json
  "$(bin colf-cameras)" orbit --frames "$FRAMES" --size "$SIZE" --radius "$RADIUS" \
    --elevation "$ELEVATION" -o "$out/.orbit.json.new"
  if cmp -s "$out/.orbit.json.new" "$cams"; then
    rm "$out/.orbit.json.new"
  else
    mv "$out/.orbit.json.new" "$cams"
  fi
fi
# Every frame of a transforms.json has one transform_matrix.
count=$(grep -o '"transform_matrix"' "$cams" | wc -l)
[ "$count" -gt 0 ] || die "$cams: no frames"

n_images=${#images[@]}
chunks=$(((count + CHUNK - 1) / CHUNK))
n_render=$((n_images * chunks))
max_array=$(scontrol show config 2>/dev/null | awk '$1 == "MaxArraySize" { print $3 }')
max_array=${max_array:-1001}
[ "$n_images" -lt "$max_array" ] ||
  die "$n_images images, but this cluster's arrays hold at most $((max_array - 1)) tasks (MaxArraySize): split IN"
[ "$n_render" -lt "$max_array" ] ||
  die "$n_render render tasks, but this cluster's arrays hold at most $((max_array - 1)) tasks (MaxArraySize): raise CHUNK"
array() { echo "0-$(($1 - 1))${ARRAY_LIMIT:+%$ARRAY_LIMIT}"; }

submit() { # submit SBATCH-ARGS...: the job id
  local id
  id=$(sbatch --parsable "${sbatch_flags[@]}" "$@") || die "sbatch refused the job: sbatch $*"
  echo "${id%%;*}"
}
enc=$(submit --job-name=colf-encode --array="$(array "$n_images")" --cpus-per-task="$THREADS" \
  --output="$out/logs/encode_%A_%a.log" \
  "$here/encode-array.sbatch" "$colf" "$model" "$list" "$in" "$out" "${encode_flags[@]}")
ren=$(submit --job-name=colf-render --array="$(array "$n_render")" --cpus-per-task="$THREADS" \
  --dependency="afterok:$enc" --kill-on-invalid-dep=yes --output="$out/logs/render_%A_%a.log" \
  "$here/render-array.sbatch" "$colf" "$model" "$list" "$cams" "$out" "$CHUNK" "$count")
sheet_args=(--job-name=colf-sheet --dependency="afterok:$ren" --kill-on-invalid-dep=yes
  --output="$out/logs/sheet_%j.log" "$here/sheet.sbatch" "$colf" "$list" "$in" "$out")
echo "$me: encode job $enc ($n_images tasks), render job $ren ($n_render tasks: $chunks of" \
  "$CHUNK frames an image, $count frames), then the contact sheet" >&2
if [ -z "$wait" ]; then
  sheet=$(submit "${sheet_args[@]}")
  printf '%s\n' "$enc" "$ren" "$sheet"
  exit 0
fi
# sbatch --wait prints the id first and returns when the job ends; a job cancelled because a
# job before it failed ends with status 0 there, so its state decides.
status=0
sheet=$(sbatch --parsable --wait "${sbatch_flags[@]}" "${sheet_args[@]}") || status=$?
sheet=${sheet%%;*}
[ -n "$sheet" ] || die "sbatch refused the contact sheet job"
printf '%s\n' "$enc" "$ren" "$sheet"
state=$(scontrol show job -o "$sheet" 2>/dev/null | grep -o 'JobState=[A-Z_]*' | cut -d= -f2 || true)
if [ "$status" -ne 0 ] || [ "$state" != COMPLETED ]; then
  die "the jobs did not complete (contact sheet job $sheet: ${state:-unknown state}, sbatch status $status); see $out/logs"
fi
echo "$me: done: $out/sheet.png" >&2
