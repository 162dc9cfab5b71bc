#!/usr/bin/env bash
# Accuracy campaign: runs mer_slam in lockstep over several seeds of the synthetic scenes (and
# the KITTI clips when ../shared/data has them) and prints one line per run plus a summary:
# ATE of the tracked frames (trajectory.txt), of every frame re-anchored to the final map
# (trajectory_final.txt) and of the final map's keyframes, each in % of the path length, the
# re-anchored ATE in metres, the loops closed and the new-keyframe step ratio (summary.json
# backend.new_keyframe_step_ratio: how much the first local BA lengthens a new keyframe's
# step from tracking's; 1 is no bias, needs no ground truth) and, with --gt-check, the
# keyframe ATE of the full BA started at the truth and of the same with the keypoint errors
# shuffled (mer_slam --gt-check; '-' without it). Lockstep runs are deterministic: a change's
# effect is the difference between two campaigns, run by run.
#
#   tools/campaign.sh [options] SET...
#     SET: orbit   room_orbit mono, seeds 1-8
#          loop    room_loop mono, seeds 1-5
#          hall    hall_drive (KITTI-like: 10 Hz, 1241x376, 81.6 deg), 160 frames, seeds 1-6
#          kitti   kitti_clip1, kitti_clip2 (skipped, and said so, without ../shared/data)
#          hard    the reproductions of held-out failures, each with its
#                  configs/scenarios/NAME.yaml: hall_turn, room_explore, room_rotation,
#                  corridor, room_kidnap_unknown, seeds 1-3; printed in a table of their own:
#                  frames, first frame with a pose, % tracked after it (summary.json
#                  accuracy.tracked_after_init_pct), frames lost, ATE (m and % of the path),
#                  ATE of the first 5 s after the start aligned on their own (m; summary.json
#                  accuracy.first_5s_ate_rmse_m: a fast start must not be a bad one)
#          lookalike  the look-alike places, room_repeated and hall_repeated (configs/
#                  scenarios), seeds 1-3, in the hard table; its last columns count, against
#                  the ground truth (summary.json gt_audit), the accepted relocalizations
#                  and closed loops that were wrong (more than 0.10 m / 0.5 m off) and all
#                  of them, and the map segments at the end
#          merge   the camera comes back to mapped ground after a loss: room_explore and
#                  room_kidnap_unknown, seeds 4-11, in the hard table; its last columns
#                  are the map segments at the end (never merged), the main segment's share
#                  of the tracked frames (%) and trajectory.txt's ATE over the best own ATE
#                  (each segment's frames aligned on their own, >= 30 frames) of the
#                  segments joined in it ('-' without a merge); the hard table's last
#                  column counts the failed starts (summary.json tracking.failed_starts:
#                  segments lost within 1 s of their start with at most 5 keyframes)
#          robust  orbit and loop seeds under four small keyframe-policy changes besides the
#                  default (tracking.keyframe.min_baseline_ratio 0.05 / 0.015, min_spread
#                  0.40 / 0.50): counts the runs that diverge (re-anchored ATE above
#                  --diverged %), which single runs do not show
#   options:
#     --bin PATH        mer_slam to run (default build/release/src/app/mer_slam)
#     --config FILE     YAML added to every run's configuration; it must not contain the
#                       sections the campaign sets (camera, and tracking for robust)
#     --out DIR         where runs and results.txt go (default build/campaign)
#     --jobs N          runs at once (default 2)
#     --diverged PCT    a run above this re-anchored ATE counts as diverged (default 2.0)
#     --keep            keep every run's output directory (default: summary.json only)
#     --max-frames N    stop every run after N frames (a quick check of the campaign itself)
#     --photo-set SET   camera.synthetic.photo_set of the hard runs: all (default), dev or
#                       heldout (choose settings on dev, check them on heldout)
#     --seeds A-B       seeds A to B for orbit, loop, hall and hard instead of their defaults (seeds
#                       not used to choose a setting: a check that a change generalizes)
#     --gt-check        run mer_slam --gt-check: what each map's observations allow (columns
#                       gtconv% and gtshuf%, and their geometric means)
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BIN="$ROOT/build/release/src/app/mer_slam"
OUT="$ROOT/build/campaign"
EXTRA=""
JOBS=2
DIVERGED=2.0
KEEP=0
MAX_FRAMES=()
SEEDS=""
GT_CHECK=()
PHOTO_SET=all
SHARED="$ROOT/../shared/data"

usage() { sed -n '2,/^[^#]/{/^#/s/^# \{0,1\}//p}' "${BASH_SOURCE[0]}"; exit "${1:-2}"; }
die() { echo "campaign: $*" >&2; exit 2; }

sets=()
while [ $# -gt 0 ]; do
  case "$1" in
    --bin) BIN="${2:?--bin needs a path}"; shift 2 ;;
    --config) EXTRA="${2:?--config needs a file}"; shift 2 ;;
    --out) OUT="${2:?--out needs a directory}"; shift 2 ;;
    --jobs) JOBS="${2:?--jobs needs a number}"; shift 2 ;;
    --diverged) DIVERGED="${2:?--diverged needs a number}"; shift 2 ;;
    --keep) KEEP=1; shift ;;
    --max-frames) MAX_FRAMES=(--max-frames "${2:?--max-frames needs a number}"); shift 2 ;;
    --seeds) SEEDS="${2:?--seeds needs A-B}"; shift 2 ;;
    --gt-check) GT_CHECK=(--gt-check); shift ;;
    --photo-set) PHOTO_SET="${2:?--photo-set needs all, dev or heldout}"; shift 2 ;;
    -h|--help) usage 0 ;;
    orbit|loop|hall|kitti|robust|hard|lookalike|merge) sets+=("$1"); shift ;;
    *) die "unknown argument '$1' (see --help)" ;;
  esac
done
[ ${#sets[@]} -gt 0 ] || usage 2
[ -x "$BIN" ] || die "no mer_slam at '$BIN' (tools/dev.sh build release, or --bin)"
[ -z "$EXTRA" ] || [ -r "$EXTRA" ] || die "cannot read --config '$EXTRA'"
[[ "$JOBS" =~ ^[1-9][0-9]*$ ]] || die "--jobs must be a positive integer, not '$JOBS'"
[[ "$PHOTO_SET" =~ ^(all|dev|heldout)$ ]] || die "--photo-set must be all, dev or heldout, not '$PHOTO_SET'"
[[ "$DIVERGED" =~ ^[0-9]+(\.[0-9]+)?$ ]] || die "--diverged must be a number, not '$DIVERGED'"
if [ -n "$SEEDS" ]; then
  [[ "$SEEDS" =~ ^([0-9]+)-([0-9]+)$ ]] && [ "${BASH_REMATCH[1]}" -le "${BASH_REMATCH[2]}" ] ||
    die "--seeds must be A-B with A <= B, not '$SEEDS'"
fi
# Seeds of a set: --seeds if given, else the set's default list.
seeds_of() {
  if [ -n "$SEEDS" ]; then seq "${SEEDS%-*}" "${SEEDS#*-}"; else printf '%s\n' "$@"; fi
}
mkdir -p "$OUT"
RESULTS="$OUT/results.txt"
HARD_RESULTS="$OUT/results_hard.txt"
: > "$RESULTS"
: > "$HARD_RESULTS"

# One run: NAME INPUT then the YAML text of its configuration on stdin.
run_one() {
  local name="$1" input="$2" dir="$OUT/$1"
  rm -rf "$dir"
  mkdir -p "$dir"
  cat > "$dir/config.yaml"
  # (the run's YAML may lack its final newline: command substitution drops it)
  if [ -n "$EXTRA" ]; then printf '\n' >> "$dir/config.yaml" && cat "$EXTRA" >> "$dir/config.yaml"; fi
  if ! "$BIN" --input "$input" --lockstep --quiet --config "$dir/config.yaml" --output "$dir" \
      "${MAX_FRAMES[@]}" "${GT_CHECK[@]}" > "$dir/log.txt" 2>&1; then
    if [[ "$name" == hard_* ]]; then echo "$name failed: see $dir/log.txt" >> "$HARD_RESULTS"
    else echo "$name failed: see $dir/log.txt" >> "$RESULTS"; fi
    return
  fi
  local s
  s="$(cat "$dir/summary.json")"
  field() {  # SECTION KEY: a number from summary.json's one-line SECTION object, or '-'
    local v
    v="$(sed -n "s/.*\"$1\": {[^}]*\"$2\": \([-0-9.eE+]*\).*/\1/p" <<< "$s" | head -n 1)"
    echo "${v:--}"
  }
  if [[ "$name" == hard_* ]]; then
    # frames, first frame with a pose in a segment that was kept (summary.json
    # first_pose_seq: a discarded failed start does not count), tracked after it, lost, ATE.
    local first frames
    first="$(sed -n 's/.*"first_pose_seq": \(-\{0,1\}[0-9]*\).*/\1/p' <<< "$s" | head -n 1)"
    [ "$first" = "-1" ] && first="-"
    frames="$(sed -n 's/.*"frames_processed": \([0-9]*\).*/\1/p' <<< "$s" | head -n 1)"
    # Map segments at the end (those that never merged), the main segment's share of the
    # tracked frames, and trajectory.txt's ATE over the best own ATE of the segments joined
    # in it (each segment's own frames aligned on their own, at least 30 of them; '-'
    # without a merge).
    local segstat
    segstat="$( (grep -o '{"id": [^}]*}' <<< "$s" || true) | awk '
      function num(key) {
        if (!match($0, "\"" key "\": [-0-9.eE+]+")) return -1
        return substr($0, RSTART + length(key) + 4, RLENGTH - length(key) - 4) + 0
      }
      {
        if (index($0, "\"discarded\": true")) next  # a failed start: its frames are lost
        frames += num("frames"); into = num("merged_into")
        if (into < 0) segs++
        else merged++
        if (index($0, "\"main\": true") || into >= 0) {
          joined += num("frames"); own = num("own_ate_rmse_m")
          if (num("own_pairs") >= 30 && own > 0 && (best == 0 || own < best)) best = own
        }
      }
      END {
        pct = "-"; if (frames > 0) pct = sprintf("%.1f", 100 * joined / frames)
        b = "-"; if (merged > 0 && best > 0) b = best
        printf "%d %s %s %d", segs, pct, b, merged
      }')"
    local segs main_pct best_own merged ratio
    read -r segs main_pct best_own merged <<< "$segstat"
    ratio="-"
    if [ "$best_own" != "-" ] && [ "$(field accuracy ate_rmse_m)" != "-" ]; then
      ratio="$(awk -v a="$(field accuracy ate_rmse_m)" -v b="$best_own" 'BEGIN { printf "%.2f", a / b }')"
    fi
    printf '%-30s %7s %7s %9s %6s %9s %9s %9s %9s %9s %4s %6s %6s %6s\n' "$name" "${frames:--}" \
      "${first:--}" "$(field accuracy tracked_after_init_pct)" "$(field tracking lost)" \
      "$(field accuracy ate_rmse_m)" "$(field accuracy ate_pct_of_path)" \
      "$(field accuracy first_5s_ate_rmse_m)" \
      "$(field gt_audit relocalizations_wrong)/$(field gt_audit relocalizations)" \
      "$(field gt_audit loops_wrong)/$(field gt_audit loops)" "$segs" "$main_pct" "$ratio" \
      "$(field tracking failed_starts)" >> "$HARD_RESULTS"
    if [ "$KEEP" -eq 0 ]; then
      find "$dir" -mindepth 1 ! -name summary.json ! -name log.txt ! -name config.yaml \
        ! -name frames.csv -delete
    fi
    return
  fi
  printf '%-22s %9s %9s %9s %10s %6s %8s %8s %8s\n' "$name" \
    "$(field accuracy ate_pct_of_path)" "$(field accuracy_final ate_pct_of_path)" \
    "$(field accuracy_keyframes ate_pct_of_path)" "$(field accuracy_final ate_rmse_m)" \
    "$(field loop loops_closed)" "$(field backend new_keyframe_step_ratio)" \
    "$(field accuracy_gt_converged ate_pct_of_path)" \
    "$(field accuracy_gt_shuffled ate_pct_of_path)" >> "$RESULTS"
  if [ "$KEEP" -eq 0 ]; then
    find "$dir" -mindepth 1 ! -name summary.json ! -name log.txt ! -name config.yaml -delete
  fi
}

running=0
queue() {  # NAME INPUT YAML
  printf '%b' "$3" | run_one "$1" "$2" &
  running=$((running + 1))
  if [ "$running" -ge "$JOBS" ]; then
    wait -n || true
    running=$((running - 1))
  fi
}

seed_yaml() { printf 'camera:\n  synthetic:\n    seed: %s\n' "$1"; }
# A hard run: its scenario file with the seed and photo set added to camera.synthetic.
hard_yaml() {
  awk -v seed="$2" -v set="$PHOTO_SET" '
    { print }
    /^  synthetic:[[:space:]]*$/ { printf "    seed: %s\n    photo_set: \"%s\"\n", seed, set }' \
    "$ROOT/configs/scenarios/$1.yaml"
}
hall_yaml() {
  printf 'camera:\n  synthetic:\n    fps: 10\n    num_frames: 160\n    width: 1241\n'
  printf '    height: 376\n    fov_x_deg: 81.6\n    seed: %s\n' "$1"
}

for set in "${sets[@]}"; do
  case "$set" in
    orbit)
      for s in $(seeds_of 1 2 3 4 5 6 7 8); do
        queue "orbit_s$s" synthetic:room_orbit "$(seed_yaml "$s")"
      done
      ;;
    loop) for s in $(seeds_of 1 2 3 4 5); do queue "loop_s$s" synthetic:room_loop "$(seed_yaml "$s")"; done ;;
    hall)
      for s in $(seeds_of 1 2 3 4 5 6); do
        queue "hall160_s$s" synthetic:hall_drive "$(hall_yaml "$s")"
      done
      ;;
    kitti)
      if [ -d "$SHARED/kitti_clip1" ]; then
        for c in 1 2; do queue "kitti_clip$c" "kitti:$SHARED/kitti_clip$c" ""; done
      else
        echo "campaign: $SHARED/kitti_clip1 not found: kitti set skipped" >&2
      fi
      ;;
    hard)
      for n in hall_turn room_explore room_rotation corridor room_kidnap_unknown; do
        [ -r "$ROOT/configs/scenarios/$n.yaml" ] || die "missing configs/scenarios/$n.yaml"
        for s in $(seeds_of 1 2 3); do queue "hard_${n}_s$s" "synthetic:$n" "$(hard_yaml "$n" "$s")"; done
      done
      ;;
    merge)
      for n in room_explore room_kidnap_unknown; do
        [ -r "$ROOT/configs/scenarios/$n.yaml" ] || die "missing configs/scenarios/$n.yaml"
        for s in $(seeds_of 4 5 6 7 8 9 10 11); do
          queue "hard_${n}_s$s" "synthetic:$n" "$(hard_yaml "$n" "$s")"
        done
      done
      ;;
    lookalike)
      for n in room_repeated hall_repeated; do
        [ -r "$ROOT/configs/scenarios/$n.yaml" ] || die "missing configs/scenarios/$n.yaml"
        for s in $(seeds_of 1 2 3); do queue "hard_${n}_s$s" "synthetic:$n" "$(hard_yaml "$n" "$s")"; done
      done
      ;;
    robust)
      for p in "def:" "mbr05:min_baseline_ratio: 0.05" "mbr015:min_baseline_ratio: 0.015" \
               "ms040:min_spread: 0.40" "ms050:min_spread: 0.50"; do
        tag="${p%%:*}"
        kv="${p#*:}"
        policy=""
        [ -z "$kv" ] || policy="tracking:\n  keyframe:\n    $kv\n"
        for s in 1 2 3 4 5 6 7 8; do
          queue "orbit_s${s}_$tag" synthetic:room_orbit "$(seed_yaml $s)\n$policy"
        done
        for s in 1 2 3 4 5; do
          queue "loop_s${s}_$tag" synthetic:room_loop "$(seed_yaml $s)\n$policy"
        done
      done
      ;;
  esac
done
wait || true

sort -o "$RESULTS" "$RESULTS"
if [ -s "$HARD_RESULTS" ]; then
  sort -o "$HARD_RESULTS" "$HARD_RESULTS"
  printf '%-30s %7s %7s %9s %6s %9s %9s %9s %9s %9s %4s %6s %6s %6s\n' run frames first \
    tracked% lost ate_m ate% ate5s_m reloc_bad loop_bad segs main% merge_x fstart
  cat "$HARD_RESULTS"
  awk '$2 != "failed:" { n++; if ($4 != "-") { t += $4; m++ } } $2 == "failed:" { f++ }
    END { printf "hard runs %d, failed %d", n + f, f + 0
          if (m > 0) printf ", mean tracked after the first pose %.1f %%", t / m
          printf "\n" }' "$HARD_RESULTS"
  [ -s "$RESULTS" ] || exit 0
fi
printf '%-22s %9s %9s %9s %10s %6s %8s %8s %8s\n' run tracked% final% keyfr% final_m loops kfstep \
  gtconv% gtshuf%
cat "$RESULTS"
median="$(awk '$2 != "failed:" && $3 != "-" { print $3 }' "$RESULTS" | sort -g |
  awk '{ v[NR] = $1 } END { if (NR > 0) print v[int((NR + 1) / 2)] }')"
awk -v lim="$DIVERGED" -v median="$median" '
  $2 == "failed:" { failed++; next }
  $3 == "-" { unscored++; next }
  { n++; if ($3 + 0 > lim) { div++; names = names " " $1 } else { ok++; lsum += log($3) } }
  END {
    if (n + unscored == 0) { print "no run finished"; exit 1 }
    printf "runs %d, failed %d, without a re-anchored ATE %d, diverged (re-anchored ATE > %s %%) %d",
           n + unscored, failed + 0, unscored + 0, lim, div + 0
    if (n > 0) printf ", median re-anchored %s %%", median
    if (ok > 0) printf ", geometric mean of the others %.3f %%", exp(lsum / ok)
    printf "\n"
    if (div > 0) print "diverged:" names
  }' "$RESULTS"
if [ ${#GT_CHECK[@]} -gt 0 ]; then
  awk '$2 != "failed:" && $8 != "-" && $9 != "-" { n++; c += log($8); s += log($9) }
    END {
      if (n == 0) { print "ground-truth check: no run checked"; exit }
      printf "ground-truth check: %d runs, geometric mean %.3f %% from the truth, %.3f %% with the keypoint errors shuffled\n",
             n, exp(c / n), exp(s / n)
    }' "$RESULTS"
fi
