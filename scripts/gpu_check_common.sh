# Sourced by scripts/gpu_check.sh and scripts/gpu_check_cells.sh (not run on its own): the repository root as the
# working directory and on PYTHONPATH, the python (PYTHON; default the repository's .venv/bin/python where there is
# one, else python: `make test` runs the suite without activating .venv, so the python on the PATH may lack the
# project's packages) in $py, and their shared arguments.
#
#   gpu_check_args NAME DEFAULT_OUT HELP_LAST_LINE "$@"
#
# parses [--dry-run] [--out DIR] [-h|--help] into $dry (0 or 1) and $out (created, made absolute, with an empty
# steps.tsv); --help prints lines 2..HELP_LAST_LINE of scripts/NAME.sh; a bad argument is one line on stderr, exit 2.
cd "$(dirname "${BASH_SOURCE[0]}")/.."
root=$(pwd)
export PYTHONPATH="$root${PYTHONPATH:+:$PYTHONPATH}"
py=${PYTHON:-}
if [ -z "$py" ]; then
  if [ -x "$root/.venv/bin/python" ]; then py=$root/.venv/bin/python; else py=python; fi
fi

gpu_check_args() {
  local name=$1 help_end=$3
  out=$2
  dry=0
  shift 3
  while [ $# -gt 0 ]; do
    case "$1" in
      --dry-run) dry=1 ;;
      --out) [ $# -ge 2 ] || { echo "$name: --out needs a directory" >&2; exit 2; }; out=$2; shift ;;
      --out=*) out=${1#--out=} ;;
      -h|--help) sed -n "2,${help_end}p" "scripts/$name.sh" | sed 's/^# \{0,1\}//'; exit 0 ;;
      *) echo "$name: unknown argument '$1' (usage: scripts/$name.sh [--dry-run] [--out DIR])" >&2; exit 2 ;;
    esac
    shift
  done
  # the models and tests steps need pytest (a test extra): without it they would fail minutes in with a traceback
  if ! command -v "$py" > /dev/null 2>&1; then
    echo "$name: no python '$py' on the PATH: set PYTHON to the project's python (e.g. PYTHON=.venv/bin/python)" >&2
    exit 2
  fi
  if ! "$py" -c "import pytest" > /dev/null 2>&1; then
    echo "$name: $py lacks pytest, which the check's test steps need: install the test extras," \
      "$py -m pip install -e '.[test]'" >&2
    exit 2
  fi
  # every step imports the project: a python without it would fail each step in a second, for no reason of its own
  if ! "$py" -c "import warp, hel_warp" > /dev/null 2>&1; then
    echo "$name: $py cannot import warp and hel_warp, which every step needs: set PYTHON to the project's python" \
      "(e.g. PYTHON=.venv/bin/python) or install the project into it, $py -m pip install -e '.[test]'" >&2
    exit 2
  fi
  mkdir -p "$out" || exit 2
  out=$(cd "$out" && pwd)
  : > "$out/steps.tsv"
}

# gpu_check_run NAME JSON COMMAND...: one step under the time caps (started, total_timeout, step_timeout, kill_grace:
# the step gets what is left of the total, at most step_timeout; with nothing left it is not started and counts as
# exit 124), its stdout to the file JSON (stderr to $out/NAME.log and the terminal), or with JSON "" stdout and stderr
# to $out/NAME.log and the terminal; its exit code in $step_rc and a row NAME, exit code, seconds, command in
# $out/steps.tsv. What a failure means is the caller's.
gpu_check_run() {
  local name=$1 json=$2
  shift 2
  local t0 t1 limit
  echo "== $name: $*"
  t0=$(date +%s.%N)
  limit=$(awk -v a="$started" -v b="$t0" -v total="$total_timeout" -v step="$step_timeout" \
    'BEGIN { left = total - (b - a); printf "%d", (left < step ? left : step) }')
  if [ "$limit" -le 0 ]; then
    step_rc=124
  elif [ -n "$json" ]; then
    timeout -k "$kill_grace" "$limit" "$@" > "$json" 2> >(tee "$out/$name.log" >&2)
    step_rc=$?
  else
    timeout -k "$kill_grace" "$limit" "$@" > >(tee "$out/$name.log") 2>&1
    step_rc=$?
  fi
  t1=$(date +%s.%N)
  printf '%s\t%s\t%s\t%s\n' "$name" "$step_rc" "$(awk -v a="$t0" -v b="$t1" 'BEGIN { printf "%.2f", b - a }')" "$*" \
    >> "$out/steps.tsv"
}
