#!/usr/bin/env bash
# Style checks run by CTest (label 'lint') and by `tools/dev.sh lint`.
#   tools/lint.sh format             clang-format --dry-run over every project C++ file
#   tools/lint.sh tidy BUILD_DIR     clang-tidy (naming rules of .clang-tidy) over project .cpp
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"

# Tracked files plus new files not yet added (ignored ones excluded).
files() {
  git ls-files --cached --others --exclude-standard -- platform hal src tools tests 2>/dev/null \
    | grep -E "$1" | sort -u || true
}
git rev-parse --git-dir >/dev/null 2>&1 || { echo "lint: not a git checkout" >&2; exit 1; }

find_tool() {
  for t in "$1" "$1-14" "$1-15" "$1-16"; do command -v "$t" >/dev/null && { echo "$t"; return; }; done
  echo "lint: $1 not found (tools/dev.sh setup installs it)" >&2; exit 1
}

case "${1:-}" in
  format)
    cf=$(find_tool clang-format)
    mapfile -t fs < <(files '\.(h|cpp)$')
    [ ${#fs[@]} -gt 0 ] || { echo "lint: no source files found" >&2; exit 1; }
    "$cf" --dry-run --Werror "${fs[@]}"
    echo "lint: clang-format clean (${#fs[@]} files)"
    ;;
  tidy)
    build="${2:?usage: lint.sh tidy BUILD_DIR}"
    ct=$(find_tool clang-tidy)
    mapfile -t fs < <(files '\.cpp$')
    [ ${#fs[@]} -gt 0 ] || { echo "lint: no source files found" >&2; exit 1; }
    # -j2: one clang-tidy per core.
    printf '%s\n' "${fs[@]}" | xargs -P 2 -n 4 "$ct" -p "$build" --quiet --extra-arg=-Wno-unknown-warning-option 2>&1 \
      | grep -v -E '^[0-9]+ warnings? generated|^Suppressed|^Use -header-filter' | tee /tmp/mer_tidy.$$ || true
    if grep -qE 'error:|warning:' /tmp/mer_tidy.$$; then rm -f /tmp/mer_tidy.$$; echo "lint: clang-tidy found problems"; exit 1; fi
    rm -f /tmp/mer_tidy.$$
    echo "lint: clang-tidy clean (${#fs[@]} files)"
    ;;
  *) echo "usage: tools/lint.sh format | tidy BUILD_DIR" >&2; exit 2 ;;
esac
