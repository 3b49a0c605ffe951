#!/bin/bash
# GPU-path check on the device machine (repo root). Writes logs/JSON under $OUT.
set -u
T0=$(date +%s); el() { echo "[$(( $(date +%s) - T0 ))s] $*"; }
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 3
export PYTHONPATH=/tmp/site:$PWD/src PYTHONUNBUFFERED=1 TORCH_EXTENSIONS_DIR=/tmp/torch_ext MAX_JOBS=16 TORCH_CUDA_ARCH_LIST=9.0
el installed; nvidia-smi -L; nvcc --version | tail -1
python3 -c "import torch; print('torch', torch.__version__, torch.version.cuda, torch.cuda.get_device_name(0))"
python3 -c "import realityavatar, hydra, mujoco, embreex, kornia, gsplat; print('imports ok, gsplat', gsplat.__version__)" 2>&1 | tail -2
el "building gsplat"
timeout 330 python3 -c "
import time; t=time.time()
from realityavatar.render.splat import gsplat_status
s=gsplat_status(); print('gsplat_status:', s[-8000:]); print('build_s', round(time.time()-t,1))
" > $OUT/gsplat_build.log 2>&1; echo "rc $?" >> $OUT/gsplat_build.log
tail -c 1500 $OUT/gsplat_build.log; el "gpu.py"
timeout 200 python3 benchmarks/gpu.py --out $OUT/gpu_cuda.json --timeout 100 --repeats 5 --cpu-threads 16 \
  --tests tests/test_gpu_path.py tests/test_render.py > $OUT/gpu_py.log 2>&1; echo "rc $?" >> $OUT/gpu_py.log
tail -c 3500 $OUT/gpu_py.log
for b in gsplat torch; do
  el "train ci $b"
  timeout 50 python3 -m realityavatar.train data=synthetic_ci trainer=gpu render=$b iterations=300 seed=0 \
    eval.save_video=false hydra.run.dir=/tmp/runs/$b > $OUT/train_$b.log 2>&1; echo "rc $?" >> $OUT/train_$b.log
  tail -3 $OUT/train_$b.log
done
python3 - <<'P' > $OUT/train_ci.json
import json, glob
out = {}
for f in glob.glob('/tmp/runs/*/metrics.json'):
    m = json.load(open(f)); out[f.split('/')[3]] = {k: v for k, v in m.items() if k not in ('config',)}
print(json.dumps(out, indent=1))
P
el done
