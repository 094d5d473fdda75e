#!/usr/bin/env bash
# Pack the Python packages a lent GPU machine lacks into parts small enough for the device tool to carry.
#
#   scripts/gpu_bundle.sh [--python-version 3.12] [--part-mb 58] [--wheels DIR] [--out DIR]
#
# The GPU machine (see ../.library/device/) has Python with NumPy, SciPy, matplotlib and pytest, but no Warp,
# XGBoost or zarr. It reaches no registry, and one call carries at most 64 MiB of working tree. Warp's wheel alone
# unpacks to ~350 MB. This script unzips the wheels into one site-packages folder, packs it (`tar | xz -9`, ~106 MB
# for the default set) and splits it into parts of at most --part-mb MB: OUT/p1, OUT/p2, ... (OUT defaults to .gpu
# in the repository root, which .git/info/exclude should list). Without --wheels it first downloads, for
# --python-version, the manylinux wheels of warp-lang, xgboost-cpu, zarr, numcodecs, donfig and google-crc32c, at
# the versions installed here (xgboost-cpu: XGBoost's own version; it has no CUDA predictor). --wheels DIR packs the
# *.whl found there instead.
#
# Then, on the device, every part but the last goes in a call of its own, and the last call runs the work, each
# within the machine's 30 s warm window of the one before; the script prints the calls (carry .gpu/pK). Exit 2 on bad arguments or a failed
# download.
set -euo pipefail
cd "$(dirname "$0")/.."
pyver=3.12
part_mb=58
wheels=""
out=.gpu
usage="usage: scripts/gpu_bundle.sh [--python-version 3.12] [--part-mb 58] [--wheels DIR] [--out DIR]"
while [ $# -gt 0 ]; do
  case "$1" in
    --python-version) pyver=${2:?"gpu_bundle: --python-version needs a value, e.g. 3.12"}; shift ;;
    --part-mb) part_mb=${2:?"gpu_bundle: --part-mb needs a number of MB"}; shift ;;
    --wheels) wheels=${2:?"gpu_bundle: --wheels needs a directory"}; shift ;;
    --out) out=${2:?"gpu_bundle: --out needs a directory"}; shift ;;
    -h|--help) sed -n '2,20p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *) echo "gpu_bundle: unknown argument '$1' ($usage)" >&2; exit 2 ;;
  esac
  shift
done
case "$part_mb" in
  ''|*[!0-9]*) echo "gpu_bundle: --part-mb must be a whole number of MB (got '$part_mb'); use at most 60" >&2; exit 2 ;;
esac
if [ "$part_mb" -lt 1 ] || [ "$part_mb" -gt 60 ]; then
  echo "gpu_bundle: --part-mb $part_mb is outside 1..60 (a call carries at most 64 MiB with the repository)" >&2
  exit 2
fi
py=${PYTHON:-python3}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

if [ -z "$wheels" ]; then
  wheels=$work/wheels
  mkdir -p "$wheels"
  version() { "$py" -c "import importlib.metadata as m; print(m.version('$1'))"; }
  specs=("warp-lang==$(version warp-lang)" "xgboost-cpu==$(version xgboost)" "zarr==$(version zarr)"
         "numcodecs==$(version numcodecs)" "donfig==$(version donfig)" "google-crc32c==$(version google-crc32c)")
  platforms=()
  for p in manylinux_2_17_x86_64 manylinux2014_x86_64 manylinux_2_24_x86_64 manylinux_2_27_x86_64 \
           manylinux_2_28_x86_64 manylinux_2_34_x86_64; do
    platforms+=(--platform "$p")
  done
  if ! "$py" -m pip download -q --no-deps --only-binary=:all: --python-version "$pyver" --implementation cp \
      "${platforms[@]}" -d "$wheels" "${specs[@]}"; then
    echo "gpu_bundle: pip could not download ${specs[*]} for Python $pyver; give --wheels DIR" >&2
    exit 2
  fi
fi
shopt -s nullglob
found=("$wheels"/*.whl)
if [ ${#found[@]} -eq 0 ]; then
  echo "gpu_bundle: no *.whl in $wheels" >&2
  exit 2
fi
mkdir -p "$work/site"
for w in "${found[@]}"; do
  "$py" -c "import sys, zipfile; zipfile.ZipFile(sys.argv[1]).extractall(sys.argv[2])" "$w" "$work/site"
done
rm -rf "$work/site/warp/examples" "$work/site/warp/tests"  # not needed to run, ~10 MB
mkdir -p "$out"
rm -f "$out"/p[0-9]*
tar -cf - -C "$work/site" . | xz -9 -T0 > "$work/site.tar.xz"
split -b "${part_mb}000000" -d -a 2 "$work/site.tar.xz" "$work/part"
k=0
for f in "$work"/part*; do
  k=$((k + 1))
  mv "$f" "$out/p$k"
done
echo "gpu_bundle: ${#found[@]} wheels, $(du -sh "$work/site" | cut -f1) unpacked, $k part(s) in $out:"
ls -l "$out"/p[0-9]*
case "$(cd "$out" && pwd)/" in
  "$(pwd)/"*) ;;
  *) echo "gpu_bundle: note: $out is outside the repository; the device tool carries only paths inside it" \
       "(use --out .gpu, listed in .git/info/exclude)" >&2 ;;
esac
echo "Before the GPU run, compile the CUDA kernels here (a bare GPU machine spends ~120 s per process on them):"
echo "  python scripts/gpu_kernel_cache.py --jobs 2 --out .gpuc/cache   (~3 min; list /.gpuc/ in .git/info/exclude)"
echo "On the device (each call within 30 s of the one before; 'carry' lists what it takes):"
for i in $(seq 1 $((k - 1))); do
  echo "  call $i: carry [\"$out/p$i\"]: mkdir -p /tmp/stage && cp $out/p$i /tmp/stage/"
done
echo "  call $k: carry [\".gpuc\"]: cp -r .gpuc/cache /tmp/stage/"
stage=""
[ "$k" -gt 1 ] && stage="/tmp/stage/p* "
echo "  call $((k + 1)): carry [\"$out/p$k\", ...]: mkdir -p /tmp/site && cat $stage$out/p$k | xz -dc | tar -xf - -C /tmp/site" \
  "&& export PYTHONPATH=/tmp/site:\$PWD PYTHON=python3 WARP_CACHE_PATH=/tmp/stage/cache" \
  "&& <the work, e.g. bash scripts/gpu_check_cells.sh --out /tmp/o> ; tar -czf \$OUT/out.tgz -C /tmp o" \
  "(the tool returns at most 8 files: one archive)"
