#!/usr/bin/env bash
# Paired comparison of two accuracy campaigns (tools/campaign.sh) run over the same seeds:
# for each set (the run name without its seed: orbit, loop, hall160, kitti_clip...) and each
# ATE column (tracked frames, re-anchored, final-map keyframes), the geometric mean of A and B
# over the runs neither diverged, the mean of log(B/A) per run with its standard error, and
# how many runs B wins. A change is worth believing when the mean log ratio is at least two
# standard errors from 0; lockstep runs are deterministic but chaotic (a small change moves
# single runs by up to 2x either way), so single runs and small sets say little.
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

awk -v div="$DIVERGED" -v fa="$1" -v fb="$2" '
  function setname(run) { sub(/_s[0-9]+$/, "", run); return run }
  # Rows of results.txt: run tracked% final% keyfr% final_m loops kfstep gtconv gtshuf.
  function ok(v) { return v ~ /^[0-9.eE+-]+$/ && v + 0 > 0 }
  FNR == 1 { file++ }
  $1 ~ /_s[0-9]+$/ && NF >= 4 {
    if (file == 1) { for (c = 2; c <= 4; c++) a[$1, c] = $c; seen_a[$1] = 1 }
    else { for (c = 2; c <= 4; c++) b[$1, c] = $c; seen_b[$1] = 1 }
  }
  END {
    n_only = 0
    for (r in seen_a) if (!(r in seen_b)) n_only++
    for (r in seen_b) if (!(r in seen_a)) n_only++
    if (n_only > 0) printf("0 note: runs in one campaign only, left out: %d\n", n_only)
    for (r in seen_a) {
      if (!(r in seen_b)) continue
      s = setname(r); sets[s] = 1; runs[s]++
      da = !ok(a[r, 3]) || a[r, 3] + 0 > div + 0
      db = !ok(b[r, 3]) || b[r, 3] + 0 > div + 0
      div_a[s] += da; div_b[s] += db
      if (da || db) continue
      paired[s]++
      for (c = 2; c <= 4; c++) {
        if (!ok(a[r, c]) || !ok(b[r, c])) { missing[s, c]++; continue }
        la = log(a[r, c]); lb = log(b[r, c]); d = lb - la
        sa[s, c] += la; sb[s, c] += lb; sd[s, c] += d; sd2[s, c] += d * d; np[s, c]++
        if (d < 0) wins[s, c]++
      }
    }
    printf("0 A: %s\n0 B: %s\n", fa, fb)
    printf("1 %-12s %5s %9s  %-11s %8s %8s %15s %7s\n", "set", "runs", "diverged", "column",
           "gm A", "gm B", "log(B/A) +- se", "B wins")
    name[2] = "tracked"; name[3] = "re-anchored"; name[4] = "keyframes"
    for (s in sets) {
      for (c = 2; c <= 4; c++) {
        n = np[s, c]
        if (n == 0) {
          printf("2 %s %d %-12s %5d %4d/%-4d  %-11s %8s\n", s, c, s, runs[s], div_a[s], div_b[s],
                 name[c], "-")
          continue
        }
        m = sd[s, c] / n
        var = n > 1 ? (sd2[s, c] - n * m * m) / (n - 1) : 0
        se = n > 1 ? sqrt(var > 0 ? var / n : 0) : 0
        printf("2 %s %d %-12s %5d %4d/%-4d  %-11s %8.4f %8.4f %+7.3f +- %5.3f %3d/%-3d\n", s, c,
               s, runs[s], div_a[s], div_b[s], name[c], exp(sa[s, c] / n), exp(sb[s, c] / n), m,
               se, wins[s, c] + 0, n)
      }
    }
  }' "$1" "$2" | sort -s -k1,1n -k2,2 -k3,3n | sed -E 's/^[01] //; s/^2 [^ ]+ [0-9] //' 
