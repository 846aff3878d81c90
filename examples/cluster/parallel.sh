#!/usr/bin/env bash
# Encode every PNG of a folder and render an orbit of each with GNU parallel: on this machine's
# job slots, or on many machines over ssh that share one folder (docs/cluster.md).
#
#   examples/cluster/parallel.sh [-j N | --hosts FILE] IN OUT
#
# IN/NAME.png is encoded to OUT/NAME.codes (with IN/NAME.json, a transforms.json, as its camera
# when there is one), then the cameras are rendered to OUT/NAME/ (PNG + mask), one job per CHUNK
# frames, so the frames of one image spread over several job slots or hosts. The cameras are
# OUT/orbit.json (colf-cameras orbit, rewritten only when FRAMES, SIZE, ... change), or CAMERAS.
#
#   -j N         N job slots on this machine (default 1). Each colf process also uses every core
#                unless THREADS says otherwise.
#   --hosts FILE GNU parallel's --sshloginfile: one ssh login a line, `N/host` for N slots,
#                `:` for this machine. IN, OUT, CAMERAS, MODEL and the colf binaries (COLF) must
#                be at the same paths on every host: a shared folder (NFS, ...) for the files.
#
# Idempotent: a job whose outputs exist and are newer than its inputs does nothing (codes: the
# image, its camera file and MODEL; frames: the codes, the cameras and MODEL, recorded by a stamp
# OUT/NAME/.frames_A-B.done written after the chunk's frames). So after a failed host or job, run
# the same command again: only what is missing or stale is redone. Every output is written
# atomically by the colf stages, so a job killed half-way leaves no partial file. A job is tried
# up to RETRIES times (a retry goes to another host where there is one) before it counts as failed.
#
# Logs: GNU parallel's --joblog, OUT/logs/encode.joblog and OUT/logs/render.joblog (appended by
# every run: host, start, run time, exit status, command of each job).
#
# Environment: COLF (folder of the colf binaries; empty = from PATH), FRAMES (8), SIZE (64),
# RADIUS (12.4), ELEVATION (40), CAMERAS (a transforms.json to render instead of the orbit),
# CHUNK (frames a render job, 8), SLOTS (empty = the model's default), MODEL (empty = the bundled
# default), ENCODE_FLAGS (more colf-encode flags, e.g. --fast), THREADS (threads a colf process,
# RAYON_NUM_THREADS; empty = all cores), RETRIES (1).
# Exit status: 0 done, 1 an error or failed jobs (one line on stderr), 2 a usage error.
set -euo pipefail

me=parallel.sh
# shellcheck disable=SC2034  # read by common.sh
usage_line="[-j N | --hosts FILE] IN OUT"
# shellcheck source=examples/cluster/common.sh
. "$(dirname "${BASH_SOURCE[0]}")/common.sh"

slots=(-j 1)
while [ $# -gt 0 ]; do
  case $1 in
    -j)
      if [ $# -lt 2 ] || ! positive "$2"; then usage; fi
      slots=(-j "$2")
      shift 2
      ;;
    --hosts)
      [ $# -ge 2 ] || usage
      [ -f "$2" ] || die "$2: no such hosts file"
      slots=(--sshloginfile "$(cd "$(dirname "$2")" && pwd)/$(basename "$2")")
      shift 2
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

RETRIES=${RETRIES:-1} THREADS=${THREADS:-}
positive "$RETRIES" || die "RETRIES=$RETRIES: not a positive whole number"
[ -z "$THREADS" ] || positive "$THREADS" || die "THREADS=$THREADS: not a positive whole number"
command -v parallel >/dev/null || die "GNU parallel is not installed (Debian: apt-get install parallel)"
setup "$1" "$2" colf-encode colf-render colf-cameras
colf=${colf_dir:+$colf_dir/}
names="$out/logs/images.txt"
for img in "${images[@]}"; do
  name=$(basename "$img" .png)
  printf '%s\n' "$name"
done >"$names"

if [ -n "${CAMERAS:-}" ]; then
  [ -f "$CAMERAS" ] || die "CAMERAS=$CAMERAS: no such file"
  cams=$(cd "$(dirname "$CAMERAS")" && pwd)/$(basename "$CAMERAS")
else
  # Rewritten only when it changes, so its time stamp says when the cameras last changed.
  cams=$out/orbit.json
  "${colf}colf-cameras" orbit --frames "$FRAMES" --size "$SIZE" --radius "$RADIUS" \
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

# The jobs: OUT/logs/job.sh, written here with this run's settings, so that every host reads it
# from the shared folder and the job logs show short commands (`job.sh render NAME START`).
job=$out/logs/job.sh
{
  echo '#!/usr/bin/env bash'
  echo "# Written by $me for the jobs of one run (examples/cluster/parallel.sh)."
  printf '%s=%q\n' colf "$colf" model "$model" threads "$THREADS" in "$in" out "$out" \
    cams "$cams" count "$count" chunk "$CHUNK"
  cat <<'EOF'
set -u
if [ -n "$threads" ]; then export RAYON_NUM_THREADS=$threads; fi
model_flag=()
if [ -n "$model" ]; then model_flag=(--model "$model"); fi
case $1 in
  encode) # encode NAME [FLAGS...]: IN/NAME.png -> OUT/NAME.codes
    name=$2
    shift 2
    img=$in/$name.png cam=$in/$name.json codes=$out/$name.codes
    if [ -s "$codes" ] && [ "$codes" -nt "$img" ] && { [ ! -e "$cam" ] || [ "$codes" -nt "$cam" ]; } &&
      { [ -z "$model" ] || [ "$codes" -nt "$model" ]; }; then
      echo "$codes: up to date"
      exit 0
    fi
    cam_flag=()
    if [ -e "$cam" ]; then cam_flag=(--camera "$cam"); fi
    echo "$codes: encoding on $(hostname)"
    exec "${colf}colf-encode" "$img" "${cam_flag[@]}" "${model_flag[@]}" "$@" -o "$codes"
    ;;
  render) # render NAME START: frames START..START+CHUNK of the cameras -> OUT/NAME/
    name=$2 start=$3
    end=$((start + chunk < count ? start + chunk : count))
    codes=$out/$name.codes dir=$out/$name
    stamp=$dir/.frames_$start-$end.done
    if [ -e "$stamp" ] && [ "$stamp" -nt "$codes" ] && [ "$stamp" -nt "$cams" ] &&
      { [ -z "$model" ] || [ "$stamp" -nt "$model" ]; }; then
      echo "$dir frames $start..$end: up to date"
      exit 0
    fi
    echo "$dir frames $start..$end: rendering on $(hostname)"
    rm -f "$stamp"
    "${colf}colf-render" "$codes" --cameras "$cams" --out "$dir" --frames "$start..$end" \
      --masks -q "${model_flag[@]}" && touch "$stamp"
    ;;
  *)
    echo "job.sh: error: unknown job '$1'" >&2
    exit 2
    ;;
esac
EOF
} >"$job.new"
mv "$job.new" "$job"

run() { # run PHASE ARGS...: one GNU parallel run, its jobs logged in OUT/logs/PHASE.joblog
  local phase=$1 log=$out/logs/$1.joblog status=0
  shift
  # Appended to (+), which GNU parallel does without its header line: written here once.
  [ -s "$log" ] || printf 'Seq\tHost\tStarttime\tJobRuntime\tSend\tReceive\tExitval\tSignal\tCommand\n' >"$log"
  parallel --will-cite "${slots[@]}" --retries "$RETRIES" --joblog "+$log" -q "$@" || status=$?
  if [ "$status" -ne 0 ]; then
    if [ "$status" -le 100 ]; then
      die "$status $phase job(s) failed (see $log); run the same command again to resume"
    fi
    die "GNU parallel failed in the $phase phase (status $status)"
  fi
}

run encode bash "$job" encode '{}' "${encode_flags[@]}" <"$names"
run render bash "$job" render '{1}' '{2}' :::: "$names" ::: $(seq 0 "$CHUNK" $((count - 1)))
echo "$me: ${#images[@]} image(s), $count frame(s) each, in $out (logs: $out/logs)" >&2
