#!/bin/bash
# Issue 45 on a GPU, one command: fern (the packed 17 / 3 split) trained with the fast recipe,
# then with the faithful 3dgs recipe as the same machine's baseline, both on the CUDA fast
# blending path (the default), each with held-out PSNR and a COB-GS refinement
# (tests/benchmarks/bm_cuda.py fern). Results under $OUT (the device tool's folder) or $1.
#
#   RECIPES="fast 3dgs" SCENE=.gpu/fern/scene.pt IMAGES=.gpu/fern/images WHEELS=.whl \
#     bash tests/benchmarks/gpu_recipes.sh [OUT]
#
# Prepare here: `python tests/benchmarks/bm_cuda.py pack-fern --sfm-dir SFM --test-every 8
# --out .gpu/fern/scene.pt` and copy SFM/images to .gpu/fern/images; plyfile's wheel in .whl
# (the GPU machine reaches no package index). A budget of 570 s: each training is stopped at
# what is left.
set -u
OUT=${1:-${OUT:?give an output folder}}
SCENE=${SCENE:-.gpu/fern/scene.pt} IMAGES=${IMAGES:-.gpu/fern/images} WHEELS=${WHEELS:-.whl}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
T0=$(date +%s)
left() { echo $((570 - ($(date +%s) - T0))); }
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "$WHEELS"/plyfile-*.whl
export PYTHONPATH=$PWD:/tmp/site
[ -x /usr/bin/g++ ] && export CXX=/usr/bin/g++  # a compiler that links libstdc++ dynamically (issue 46)
export TORCH_CUDA_ARCH_LIST=$(python3 -c "import torch; print('%d.%d' % torch.cuda.get_device_capability())")
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader; nproc
  python3 -c "import torch; print(torch.__version__)"; git rev-parse --short HEAD; } | tee "$OUT/run.log"
MAX_JOBS=16 python3 -m stages.commands.cli build >"$OUT/build.log" 2>&1
echo "build rc=$? at +$(( $(date +%s) - T0 )) s" | tee -a "$OUT/run.log"
for r in ${RECIPES:-fast 3dgs}; do
  echo "== fern recipe $r, $(left) s left" | tee -a "$OUT/run.log"
  timeout --signal=INT $(( $(left) - 5 )) python3 tests/benchmarks/bm_cuda.py fern --scene "$SCENE" \
    --images-dir "$IMAGES" --recipe "$r" --path fast --out "/tmp/f_$r" >"$OUT/fern_$r.log" 2>&1
  echo "fern $r rc=$? at +$(( $(date +%s) - T0 )) s" | tee -a "$OUT/run.log"
  cp "/tmp/f_$r/bm_cuda_fern.json" "$OUT/fern_recipe_$r.json" 2>/dev/null
done
