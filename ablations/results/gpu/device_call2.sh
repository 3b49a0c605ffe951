#!/bin/bash
# GPU-path check, second call: the fixed gpu tests, then the sweep-preset training on gsplat. Logs under $OUT.
set -u
T0=$(date +%s); el() { echo "[$(( $(date +%s) - T0 ))s] $*"; }
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 3
export PYTHONPATH=/tmp/site:$PWD/src PYTHONUNBUFFERED=1 TORCH_EXTENSIONS_DIR=/tmp/torch_ext MAX_JOBS=16 TORCH_CUDA_ARCH_LIST=9.0
export REALITYAVATAR_SCENES=$PWD/scenes
el installed; echo "ffmpeg: $(command -v ffmpeg || echo none)"; git log --oneline -1 2>/dev/null
(python3 -c "from realityavatar.data.synthetic import build_scene; build_scene('demo', 'scenes', seed=0, sequence='skirt_spin', progress=False)" > /tmp/scene.log 2>&1; echo "scene rc $?" >> /tmp/scene.log) &
SCENE=$!
timeout 150 python3 -c "
import time; t=time.time()
from realityavatar.render.splat import gsplat_status
print('gsplat_status:', gsplat_status()[-3000:], 'build_s', round(time.time()-t,1))"
el "pytest -m gpu"
timeout 150 python3 -m pytest -q -m gpu -p no:cacheprovider tests/test_gpu_path.py tests/test_render.py > $OUT/pytest_gpu.log 2>&1; echo "rc $?" >> $OUT/pytest_gpu.log
grep -E "passed|failed|Error|error" $OUT/pytest_gpu.log | tail -8
wait $SCENE; cat /tmp/scene.log | tail -2; el "train sweep preset, gsplat"
timeout 230 python3 -m realityavatar.train +ablation=paper +variant=full data=synthetic_sweep seed=0 trainer=gpu \
  render=gsplat hydra.run.dir=/tmp/runs/sweep0 > $OUT/train_sweep0.log 2>&1; echo "rc $?" >> $OUT/train_sweep0.log
tail -4 $OUT/train_sweep0.log; cp /tmp/runs/sweep0/metrics.json $OUT/metrics_sweep0.json; cp /tmp/runs/sweep0/per_frame.csv $OUT/per_frame_sweep0.csv
el "probe"
timeout 60 python3 ablations/probe.py /tmp/runs/sweep0 --labels gpu --heldout-only --threads 8 --out $OUT/probe > $OUT/probe.log 2>&1; echo "rc $?" >> $OUT/probe.log
tail -12 $OUT/probe.log; ls $OUT/probe; el done
