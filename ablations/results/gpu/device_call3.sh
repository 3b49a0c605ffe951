#!/bin/bash
set -u
T0=$(date +%s); el() { echo "[$(( $(date +%s) - T0 ))s] $*"; }
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 3
export PYTHONPATH=/tmp/site:$PWD/src PYTHONUNBUFFERED=1 TORCH_EXTENSIONS_DIR=/tmp/torch_ext MAX_JOBS=16 TORCH_CUDA_ARCH_LIST=9.0
el installed
timeout 100 python3 -c "
from realityavatar.render.splat import gsplat_status; print('gsplat_status:', gsplat_status()[-2000:])"
el "pytest -m gpu"
timeout 75 python3 -m pytest -q -m gpu -p no:cacheprovider tests/test_gpu_path.py tests/test_render.py > $OUT/pytest_gpu.log 2>&1; echo "rc $?" >> $OUT/pytest_gpu.log
grep -E "passed|failed|^FAILED|^E " $OUT/pytest_gpu.log | tail -8
el "step profile"
timeout 45 python3 .whl/gpustep.py cuda 2>&1 | grep -v "Warn\|USDT" | tail -4 | tee $OUT/gpustep.txt
el done
