#!/usr/bin/env bash
# Paired comparison of two accuracy campaigns (tools/campaign.sh) run over the same seeds:
# for each set (the run name without its seed: orbit, loop, hall160, kitti_clip...) and each
# ATE column (tracked frames, re-anchored, final-map keyframes), the geometric mean of A and B
# over the runs neither diverged nor failed (each counted apart, A/B), the mean of log(B/A)
# per run with its standard error, and how many runs B wins. A change is worth believing when
# the mean log ratio is at least two standard errors from 0; lockstep runs are deterministic
# but chaotic (a small change moves single runs by up to 2x either way), so single runs and
# small sets say little.
#
#   tools/campaign_compare.sh [--diverged PCT] A/results.txt B/results.txt
#     --diverged PCT   a run above this re-anchored ATE counts as diverged and is left out of
#                      the ratios, counted apart (default 2.0, as tools/campaign.sh)
set -euo pipefail

DIVERGED=2.0
usage() { sed -n '2,/^[^#]/{/^#/s/^# \{0,1\}//p}' "${BASH_SOURCE[0]}"; exit "${1:-2}"; }
while [ $# -gt 0 ]; do
  case "$1" in
    --diverged) DIVERGED="${2:?--diverged needs a number}"; shift 2 ;;
    -h|--help) usage 0 ;;
    --) shift; break ;;
    -*) echo "campaign_compare: unknown option $1" >&2; usage ;;
    *) break ;;
  esac
done
[ $# -eq 2 ] || usage
for f in "$1" "$2"; do
  [ -r "$f" ] || { echo "campaign_compare: cannot read $f" >&2; exit 2; }
done

case "$DIVERGED" in
  ''|*[!0-9.]*|*.*.*) echo "campaign_compare: --diverged must be a number, not '$DIVERGED'" >&2; exit 2 ;;
esac

awk -v div="$DIVERGED" -v fa="$1" -v fb="$2" '
  # A run name without its seed: orbit_s3 -> orbit, orbit_s3_mbr05 -> orbit_mbr05 (robust),
  # kitti_clip1 -> kitti_clip1 (a set of one run).
  function setname(run) { sub(/_s[0-9]+/, "", run); return run }
  function ok(v) { return v ~ /^[0-9.eE+-]+$/ && v + 0 > 0 }
  # Rows of results.txt: run tracked% final% keyfr% final_m loops kfstep gtconv gtshuf, or
  # "run failed: see LOG"; the header and the summary lines (runs ..., diverged: ...) are not runs.
  function is_run() { return NF >= 2 && $1 != "run" && ($2 == "failed:" || $2 ~ /^([0-9.eE+-]+|-)$/) }
  FNR == 1 { file++ }
  is_run() {
    if (file == 1) { if ($1 in seen_a) dup++; seen_a[$1] = 1; for (c = 2; c <= 4; c++) a[$1, c] = $c }
    else { if ($1 in seen_b) dup++; seen_b[$1] = 1; for (c = 2; c <= 4; c++) b[$1, c] = $c }
  }
  END {
    n_only = 0
    for (r in seen_a) if (!(r in seen_b)) n_only++
    for (r in seen_b) if (!(r in seen_a)) n_only++
    if (n_only > 0) printf("0 note: runs in one campaign only, left out: %d\n", n_only)
    if (dup > 0) printf("0 note: runs listed twice in a campaign (the last row counts): %d\n", dup)
    for (r in seen_a) {
      if (!(r in seen_b)) continue
      s = setname(r); sets[s] = 1; runs[s]++
      # Failed, or without a re-anchored ATE: counted apart from the diverged runs.
      xa = !ok(a[r, 3]); xb = !ok(b[r, 3])
      da = !xa && a[r, 3] + 0 > div + 0
      db = !xb && b[r, 3] + 0 > div + 0
      fail_a[s] += xa; fail_b[s] += xb; div_a[s] += da; div_b[s] += db
      if (xa || xb || da || db) continue
      for (c = 2; c <= 4; c++) {
        if (!ok(a[r, c]) || !ok(b[r, c])) continue
        la = log(a[r, c]); lb = log(b[r, c]); d = lb - la
        sa[s, c] += la; sb[s, c] += lb; sd[s, c] += d; sd2[s, c] += d * d; np[s, c]++
        if (d < 0) wins[s, c]++
      }
    }
    printf("0 A: %s\n0 B: %s\n", fa, fb)
    printf("1 %-12s %5s %9s %9s  %-11s %8s %8s %15s %7s\n", "set", "runs", "diverged", "failed",
           "column", "gm A", "gm B", "log(B/A) +- se", "B wins")
    name[2] = "tracked"; name[3] = "re-anchored"; name[4] = "keyframes"
    for (s in sets) {
      for (c = 2; c <= 4; c++) {
        n = np[s, c]
        head = sprintf("2 %s %d %-12s %5d %4d/%-4d %4d/%-4d  %-11s", s, c, s, runs[s], div_a[s],
                       div_b[s], fail_a[s], fail_b[s], name[c])
        if (n == 0) { printf("%s %8s\n", head, "-"); continue }
        m = sd[s, c] / n
        if (n > 1) {
          var = (sd2[s, c] - n * m * m) / (n - 1)
          se = sprintf("%5.3f", sqrt(var > 0 ? var / n : 0))
        } else {
          se = "    -"  # one run: no spread
        }
        printf("%s %8.4f %8.4f %+7.3f +- %s %3d/%d\n", head, exp(sa[s, c] / n),
               exp(sb[s, c] / n), m, se, wins[s, c] + 0, n)
      }
    }
  }' "$1" "$2" | sort -s -k1,1n -k2,2 -k3,3n | sed -E 's/^[01] //; s/^2 [^ ]+ [0-9] //'
