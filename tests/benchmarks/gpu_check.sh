#!/usr/bin/env bash
# The whole GPU check in one command (issue 49): build, CUDA parity tests (exact and fast
# paths), the kernel benchmark against gsplat (both paths, 4 channels and 1 channel with
# label counts), and, while time is left, fern trained for 30k iterations on the fast path
# with its step profile (CUDA events per phase, issue 60), then with gsplat's rasterizer on
# the same trainer (TrainConfig.rasterizer = "gsplat"), then on the exact path (held-out PSNR
# of each, COB-GS refinement after each).
#
#   tests/benchmarks/gpu_check.sh OUT [--wheels DIR] [--fern-scene PT --fern-images DIR]
#                                     [--budget-s 570] [--fern-iterations 30000]
#   make gpu-check [GPU_CHECK_OUT=runs/gpu_check] [GPU_CHECK_ARGS="--wheels .whl ..."]
#
# --wheels DIR: wheels to install first (pip --no-index --target; the GPU machine reaches no
#   package index): gsplat (its JIT build, ~200 s on 16 cores, starts in the background at
#   the top), plyfile, ... Without gsplat the benchmark times ours alone.
# --fern-scene PT / --fern-images DIR: the scene written by
#   `bm_cuda.py pack-fern --sfm-dir SFM --test-every 8 --out PT` and SFM/images (no pycolmap
#   needed on the GPU machine). Without them fern is skipped.
# --budget-s: wall-clock budget of the whole check; a step that cannot finish in what is
#   left is skipped (fern) or stopped at the deadline, and says so.
#
# Every result goes to OUT as it is made (8 files, what the GPU machine returns): gpu_check.log
# (everything), summary.md, parity.txt, gsplat_build.log, bm_cuda_kernels.json, fern_fast.json,
# fern_gsplat.json, fern_exact.json. Exit status: 0 when every step that ran passed, 1
# otherwise, 2 on usage errors, 3 without a CUDA device.
set -u -o pipefail

OUT=${1:-}
if [ -z "$OUT" ] || [ "${OUT#-}" != "$OUT" ]; then
  sed -n '2,25p' "$0" | sed 's/^# \{0,1\}//'
  exit 2
fi
shift
WHEELS="" FERN_SCENE="" FERN_IMAGES="" BUDGET=570 FERN_ITERS=30000
while [ $# -gt 0 ]; do
  case "$1" in
    --wheels) WHEELS=$2; shift 2 ;;
    --fern-scene) FERN_SCENE=$2; shift 2 ;;
    --fern-images) FERN_IMAGES=$2; shift 2 ;;
    --budget-s) BUDGET=$2; shift 2 ;;
    --fern-iterations) FERN_ITERS=$2; shift 2 ;;
    *) echo "gpu_check.sh: unknown argument $1" >&2; exit 2 ;;
  esac
done
ROOT=$(cd "$(dirname "$0")/../.." && pwd)
PY=${PYTHON:-python3}
export PYTHONUNBUFFERED=1 PYTHONPATH="$ROOT${PYTHONPATH:+:$PYTHONPATH}"
mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)
LOG=$OUT/gpu_check.log SUMMARY=$OUT/summary.md
: >"$LOG"
START=$(date +%s)
FAILED=0
left() { echo $((BUDGET - ($(date +%s) - START))); }
say() { echo "[gpu-check +$(($(date +%s) - START))s] $*" | tee -a "$LOG"; }
row() { echo "| $1 | $2 | $3 |" >>"$SUMMARY"; }
# step NAME LIMIT_S CMD...: runs CMD with a time limit, output to the log; records the result.
step() {
  local name=$1 limit=$2 t0 rc
  shift 2
  t0=$(date +%s)
  say "== $name (limit ${limit} s)"
  timeout --signal=INT --kill-after=10 "$limit" "$@" >>"$LOG" 2>&1
  rc=$?
  local dt=$(($(date +%s) - t0))
  if [ $rc -eq 0 ]; then row "$name" "passed" "${dt} s"
  elif [ $rc -eq 124 ] || [ $rc -eq 137 ]; then row "$name" "STOPPED at its ${limit} s limit" "${dt} s"; FAILED=1
  else row "$name" "FAILED (exit $rc)" "${dt} s"; FAILED=1
  fi
  say "== $name: exit $rc after ${dt} s"
  return $rc
}

{
  echo "# GPU check ($(date -u +%Y-%m-%dT%H:%M:%SZ))"
  echo
  echo "commit: $(git -C "$ROOT" rev-parse --short HEAD 2>/dev/null || echo unknown)$(git -C "$ROOT" diff --quiet 2>/dev/null || echo ' (with local changes)')"
  echo
  echo "| step | result | time |"
  echo "|---|---|---|"
} >"$SUMMARY"

say "machine: $(nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null || echo 'no nvidia-smi'); $(nproc) CPU cores"
if ! "$PY" -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)" 2>>"$LOG"; then
  say "no CUDA device: nothing to check"
  row "CUDA device" "none" "-"
  exit 3
fi
"$PY" -c "import torch; print('torch', torch.__version__, 'CUDA', torch.version.cuda, torch.cuda.get_device_name())" 2>&1 | tee -a "$LOG"
nvcc --version 2>&1 | tail -1 | tee -a "$LOG"

if [ -n "$WHEELS" ]; then
  step "install wheels from $WHEELS" 120 "$PY" -m pip install -q --no-index --no-deps --no-compile \
    --no-cache-dir --upgrade --target /tmp/gpu_check_site "$WHEELS"/*.whl
  export PYTHONPATH="$PYTHONPATH:/tmp/gpu_check_site"
fi

# gsplat's JIT build in the background (its own MAX_JOBS; ours builds beside it).
GSPLAT_PID=""
if "$PY" -c "import gsplat" >/dev/null 2>&1; then
  say "gsplat $("$PY" -c 'import gsplat; print(gsplat.__version__)'): JIT build in the background"
  (MAX_JOBS=8 timeout "$(left)" "$PY" -c "from gsplat.cuda._backend import _C; assert _C is not None, 'gsplat did not build'; print('gsplat built')" \
    >"$OUT/gsplat_build.log" 2>&1) &
  GSPLAT_PID=$!
else
  say "gsplat not importable: the kernel benchmark times ours alone"
fi

export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-$("$PY" -c "import torch; print('%d.%d' % torch.cuda.get_device_capability())")}
step "build (cobgs build, arch $TORCH_CUDA_ARCH_LIST)" 300 env MAX_JOBS=8 "$PY" -m stages.commands.cli build || {
  say "the build failed: nothing else can run"; exit 1; }
step "doctor" 60 "$PY" -m stages.commands.cli doctor

step "parity tests (tests/render/test_cuda.py, both paths)" "$(( $(left) > 300 ? 300 : $(left) - 60 ))" \
  "$PY" -m pytest tests/render/test_cuda.py -q -rfE -p no:cacheprovider -o addopts="" \
  --junit-xml=/tmp/gpu_check_parity.xml
"$PY" - "$LOG" >"$OUT/parity.txt" 2>&1 <<'EOF' || true
import sys, xml.etree.ElementTree as ET
try:
    root = ET.parse("/tmp/gpu_check_parity.xml").getroot()
except Exception as e:
    sys.exit(f"no junit report: {e}")
for case in root.iter("testcase"):
    res = "passed"
    for tag in ("failure", "error", "skipped"):
        el = case.find(tag)
        if el is not None:
            res = f"{tag}: {(el.get('message') or '').splitlines()[0][:300] if el.get('message') else ''}"
    print(f"{case.get('name')}\t{float(case.get('time', 0)):.2f} s\t{res}")
EOF
say "parity: $(grep -cP '\tpassed$' "$OUT/parity.txt") passed, $(grep -cP '\t(failure|error)' "$OUT/parity.txt") failed"

if [ -n "$GSPLAT_PID" ]; then
  say "waiting for gsplat's build"
  wait "$GSPLAT_PID" && row "gsplat JIT build" "passed" "-" || { row "gsplat JIT build" "FAILED (gsplat_build.log)" "-"; }
fi
step "kernels (bm_cuda.py kernels --reps 30: 100k / 1M, 4 ch / 1 ch + labels, exact / fast)" \
  "$(( $(left) > 240 ? 240 : $(left) - 30 ))" \
  "$PY" tests/benchmarks/bm_cuda.py kernels --reps 30 --out "$OUT"

fern() {  # path need [rasterizer]
  local path=$1 need=$2 rast=${3:-ours}
  local tag=$path
  [ "$rast" = gsplat ] && tag=gsplat
  if [ -z "$FERN_SCENE" ]; then row "fern ($tag)" "skipped: no --fern-scene" "-"; return; fi
  if [ "$(left)" -lt "$need" ]; then row "fern ($tag)" "skipped: $(left) s left" "-"; return; fi
  if [ "$rast" = gsplat ] && ! "$PY" -c "import gsplat" >/dev/null 2>&1; then
    row "fern (gsplat rasterizer)" "skipped: gsplat not importable" "-"; return; fi
  step "fern $FERN_ITERS its, $path path, rasterizer $rast (+ step profile, held-out PSNR, COB-GS refinement)" \
    "$(( $(left) - 5 ))" \
    "$PY" tests/benchmarks/bm_cuda.py fern --scene "$FERN_SCENE" --images-dir "$FERN_IMAGES" \
    --iterations "$FERN_ITERS" --path "$path" --rasterizer "$rast" --out "/tmp/gpu_check_fern_$tag"
  [ -f "/tmp/gpu_check_fern_$tag/bm_cuda_fern.json" ] && cp "/tmp/gpu_check_fern_$tag/bm_cuda_fern.json" "$OUT/fern_$tag.json"
}
fern fast 60
fern fast 60 gsplat
fern exact 60

# The summary: every number with the GPU's and gsplat's names.
"$PY" - "$OUT" >>"$SUMMARY" 2>>"$LOG" <<'EOF' || true
import json, sys
from pathlib import Path

out = Path(sys.argv[1])


def num(v, fmt):
    return "-" if v is None else format(v, fmt)


k = out / "bm_cuda_kernels.json"
if k.exists():
    d = json.loads(k.read_text())
    print(f"\n## Kernels: {d['gpu']}, {d['width']}x{d['height']}, gsplat {d.get('gsplat') or 'absent'}\n")
    print("| N | channels | path | ours fwd+bwd ms [min] | gsplat best ms | ratio | ours fwd ms | fwd ratio |")
    print("|---|---|---|---|---|---|---|---|")
    for r in d["rows"]:
        ch = f"{r['channels']}{' + 2-label counts' if r.get('labels') else ''}"
        print(f"| {r['n']:,} | {ch} | {r['path']} | {r['ours_ms']:.2f} [{r['ours_min_ms']:.2f}] | "
              f"{num(r.get('gsplat_ms'), '.2f')} | {num(r.get('ratio'), '.3f')} | "
              f"{r['ours_fwd_ms']:.2f} | {num(r.get('fwd_ratio'), '.3f')} |")
rows = [json.loads((out / f"fern_{p}.json").read_text()) for p in ("fast", "gsplat", "exact")
        if (out / f"fern_{p}.json").exists()]
if rows:
    print(f"\n## fern ({rows[0]['gpu']})\n")
    print("| path | rasterizer | iterations | train s | s / 1000 its | Gaussians | held-out PSNR | train PSNR (last log) | "
          "refine s | peak GPU GiB |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        mem = r.get("train_peak_gpu_mem")
        rast = r.get("rasterizer", "ours") + (f" {r['gsplat']}" if r.get("gsplat") else "")
        per = r["train_s"] / r["iterations"] * 1000 if r.get("train_s") and r.get("iterations") else None
        print(f"| {r['path']} | {rast} | {r['iterations']} | {num(r.get('train_s'), '.1f')} | {num(per, '.2f')} | "
              f"{num(r.get('num_gaussians'), ',')} | {num(r.get('test_psnr'), '.3f')} | "
              f"{num(r.get('train_psnr_last'), '.2f')} | {num(r.get('refine_s'), '.1f')} | "
              f"{num(mem / 2**30 if mem else None, '.2f')} |")
    for r in rows:
        for k, rep in (r.get("profile") or {}).items():
            print(f"\n### step profile: {r['path']} path, rasterizer {r.get('rasterizer', 'ours')}, {k} "
                  f"({rep['steps']} steps, {rep['ms_per_step']:.2f} ms / step; CUDA events per phase)\n")
            print("| phase | ms / step | share |")
            print("|---|---|---|")
            for p, v in rep["phases"].items():
                print(f"| {p} | {v['ms_per_step']:.3f} | {100 * v['share']:.1f} % |")
EOF
say "done in $(($(date +%s) - START)) s; summary:"
cat "$SUMMARY" | tee -a "$LOG"
exit $FAILED
