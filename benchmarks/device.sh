#!/bin/bash
# One GPU check in one call (repo root, a GPU machine with CUDA torch and nvcc, no network): install the project's
# missing packages from wheels in .whl/, build gsplat's kernels, run the `gpu` tests, profile the training step and
# write everything under $OUT. STEP_SIZES="7000 128;35000 512" picks the profiled sizes, STEP_VIEWS="1 4" the cameras
# per step (data.views_per_step) timed at each, STEP_COMPILE="default reduce-overhead" the torch.compile modes timed at
# the first size (the networks compiled; reduce-overhead adds CUDA graphs); BASELINE=<folder with another
# commit's src/ conf/ benchmarks/> profiles that commit's step too, in the same call (compare timings only within one
# call). SWEEP=1 trains the sweep preset (1,000 steps at 128 px; the baseline's too with BASELINE) and reports its
# seconds per step; PAPER_SCALE=<seconds> trains `+experiment=paper_scale` for at most that long (15,000 steps if it
# gets there) and evaluates it; their scenes are built while the gpu tests run. A 15-minute device session fits one
# call of at most 10 minutes, e.g. SWEEP=1 PAPER_SCENE=1 BASELINE=<tree> STEP_SIZES="7000 128", then a second on the
# warm machine (scenes and kernels kept under outputs/) with GPU_TESTS=0 STEP_SIZES="" PAPER_SCALE=<s>; a third with
# PAPER_RESUME=1 continues that run (resume=true) towards its 15,000 steps. After training, paper_scale is evaluated
# and probed on the 128 px sweep scene, 4x supersampled (beside the CPU sweep preset); PAPER_EVAL=1 does only that, for
# a run an earlier call on the warm machine trained. COMPILE=<mode> trains this commit's sweep and paper_scale runs
# with compile=<mode> (torch.compile of the networks' path and the losses; unset: the configs' own, none for the sweep
# preset, reduce-overhead for paper_scale). PAPER_ARGS="<overrides>" adds hydra
# overrides to the paper_scale run (e.g. data.num_workers=2). LOADER=1 times the training process's work per paper_scale
# batch moved to the GPU, with the training set on the host and kept on the GPU (data.device_cache).
# COMPILE=auto: the STEP_COMPILE mode whose step was fastest in this call if 30 % faster than eager, else none.
# PAPER_VARIANTS="name:overrides;name:overrides" trains each as `+experiment=paper_scale <PAPER_ARGS> <its overrides>`, all at
# once on the one GPU (PAPER_THREADS CPU threads each), evaluates each at 512² (the garment per motion phase) and brings
# back their metrics, logs, held-out grids and checkpoints (those under 16 MiB); PAPER_VARIANTS_S caps their training
# time (default: what DEADLINE leaves after PAPER_RESERVE).
# STEP_ARGS="<step.py arguments>" adds them to every step row (e.g. "--override density=off": a fixed Gaussian count,
# which compiled graphs specialise on; with density control they take it as dynamic).
#
# Wheels (Python 3.12, x86_64; on a machine with pip and network):
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#     --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl \
#     hydra-core==1.3.8 omegaconf==2.3.1 mannequin-x==0.3.0 nanomanifold kornia==0.9.0 kornia_rs==0.2.0 \
#     trimesh==5.2.0 embreex==4.4.0.post1 mujoco==4.0.0 mujoco-core==4.0.0 mujoco-studio==4.0.0 glfw pyopengl threadpoolctl \
#     gsplat==1.5.3
#   python3 -m pip wheel --no-deps -w .whl antlr4-python3-runtime==4.9.3
set -u
# Everything is written under $WORK (ignored, kept on a warm machine) and packed into $OUT/device.tgz at the end (the
# device returns at most 8 files from $OUT; checkpoints and videos stay behind). DEADLINE=<s>: the script ends by then
# (the call's own limit kills without packing); paper_scale's training time is cut to fit it.
OUT=$(realpath -m "${OUT:-outputs/device_out}"); mkdir -p "$OUT"
WORK=$(realpath -m "${WORK:-outputs/device}"); mkdir -p "$WORK"
DEADLINE=${DEADLINE:-580}
pack() { tar czf "$OUT/device.tgz" --exclude='*.ckpt' --exclude='*.mp4' --exclude='*.png' -C "$WORK" . 2>/dev/null
  ls -la "$OUT"; }
trap pack EXIT
# Scenes and gsplat's kernels under outputs/ (ignored): one build for this commit and the baseline, and a later call on
# the warm machine finds them (the device keeps ignored outputs in the tree between calls).
export REALITYAVATAR_SCENES=${REALITYAVATAR_SCENES:-$PWD/outputs/scenes}
T0=$(date +%s); el() { echo "[$(( $(date +%s) - T0 ))s] $*"; }; left() { echo $(( DEADLINE - $(date +%s) + T0 )); }
# Installed once per machine, under outputs/ beside gsplat's kernels: a reinstall gives its sources new times, and
# ninja rebuilds the kernels (85 s on an H100), so a later call on the warm machine keeps both.
SITE=$PWD/outputs/site
[ -f "$SITE/.done" ] || { python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
  --target "$SITE" .whl/*.whl && touch "$SITE/.done"; } || exit 3
export PYTHONPATH=$SITE:$PWD/src PYTHONUNBUFFERED=1 TORCH_EXTENSIONS_DIR=${TORCH_EXTENSIONS_DIR:-$PWD/outputs/torch_ext} MAX_JOBS=16 \
  TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
el installed; nvidia-smi -L; python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda)"
timeout 240 python3 -c "
import time; t = time.time()
from realityavatar.render.splat import gsplat_status
print('gsplat_status:', gsplat_status()[-1500:], '| build_s', round(time.time() - t, 1))" 2>&1 | tail -2
# The scenes the trainings below read, built by their own data configs while the gpu tests run (ray casting on every
# core, after gsplat's build: beside it, nvcc took 225 s instead of 85 s on an H100). The step profile waits for
# them: no timing shares the CPU.
SCENES=(); [ -n "${PAPER_SCALE:-}${PAPER_SCENE:-}${PAPER_VARIANTS:-}" ] && SCENES+=("+experiment=paper_scale ${PAPER_ARGS:-}")  # *_SCENE=1: for a later call
# the sweep scene: the sweep preset's, and the one paper_scale is evaluated on beside it (below)
[ -n "${SWEEP:-}${SWEEP_SCENE:-}${PAPER_SCALE:-}${PAPER_SCENE:-}" ] && SCENES+=("+preset=sweep data=synthetic_sweep")
if [ ${#SCENES[@]} -gt 0 ]; then
  python3 - "${SCENES[@]}" > "$WORK/scenes.log" 2>&1 <<'PY' &
import sys
from hydra.utils import instantiate
from realityavatar.config import compose
for overrides in sys.argv[1:]:
    instantiate(compose(overrides.split()).data, body=None).prepare_data()
PY
  SCENES_PID=$!
fi
if [ "${GPU_TESTS:-1}" != 0 ]; then  # GPU_TESTS=0: a later call on the warm machine skips them
  el "gpu tests"
  timeout ${PYTEST_TIMEOUT:-200} python3 -m pytest -q -m gpu -p no:cacheprovider ${GPU_TESTS_K:+-k "$GPU_TESTS_K"} \
    > "$WORK/pytest_gpu.log" 2>&1
  echo "pytest rc $?"; grep -E "passed|failed|^FAILED|^E " "$WORK/pytest_gpu.log" | tail -8
fi
if [ -n "${SCENES_PID:-}" ]; then wait "$SCENES_PID"; el "scenes built (rc $?; $WORK/scenes.log)"; fi
STEP="benchmarks/step.py --device cuda --backends gsplat ${STEP_ARGS:-}"  # STEP_ARGS: e.g. "--override density=off"
IFS=";" read -ra SIZES <<< "${STEP_SIZES-7000 128;35000 512}"   # "N size;N size"; STEP_SIZES="" profiles nothing
for NS in "${SIZES[@]}"; do set -- $NS
  el "step profile ($1 / $2)"
  timeout 150 python3 $STEP --n $1 --size $2 --views ${STEP_VIEWS:-1 4} --profile 15 --out "$WORK/step_cuda_$1_$2.json" \
    2>&1 | grep -E "^  gsplat|ms  x|^  sync" | cut -c1-500
done
for MODE in ${STEP_COMPILE:-}; do  # e.g. STEP_COMPILE="default reduce-overhead" (CUDA graphs): the networks compiled
  set -- ${SIZES[0]:-7000 128}
  el "step profile, torch.compile $MODE ($1 / $2; first_step_s includes compiling)"
  timeout ${STEP_COMPILE_TIMEOUT:-240} python3 $STEP --n $1 --size $2 --compile $MODE --out "$WORK/step_cuda_$1_$2_compile_$MODE.json" \
    > "$WORK/step_compile_$MODE.log" 2>&1; echo "rc $?"; grep -E "^  gsplat|Error|^  sync|skipping cudagraphs" "$WORK/step_compile_$MODE.log" | cut -c1-500
done
if [ "${COMPILE:-}" = auto ]; then  # the mode whose step was fastest above (at the first size), if 30 % faster than eager
  COMPILE=$(python3 - "$WORK" ${SIZES[0]:-7000 128} <<'PY'
import json, sys
from pathlib import Path
work, n, size = Path(sys.argv[1]), *sys.argv[2:]
step = {}
for f in work.glob(f"step_cuda_{n}_{size}*.json"):
    for r in json.loads(f.read_text())["results"]:
        step[r["compile"]] = min(step.get(r["compile"], 1e9), r["step_s"])
best = min(step, key=step.get, default="none")
print(best if "none" in step and step[best] < 0.7 * step["none"] else "none", end="")
print(f"compile=auto: step seconds {step}", file=sys.stderr)
PY
); el "compile=auto chose $COMPILE"
fi
if [ -n "${BASELINE:-}" ] && [ ${#SIZES[@]} -gt 0 ]; then
  el "baseline step profile ($BASELINE, 7000 / 128)"
  (cd "$BASELINE" && PYTHONPATH=$SITE:$PWD/src timeout 120 python3 $STEP --n 7000 --size 128 \
    --out "$WORK/step_cuda_baseline_7000_128.json" 2>&1 | grep -E "^  gsplat" | cut -c1-400)
fi
if [ -n "${LOADER:-}" ] && [ "$(left)" -gt 90 ]; then  # LOADER=1 (the paper_scale scene built): per 512 px batch
  el "loader, paper_scale batches moved to the GPU (without and with data.device_cache)"
  timeout 150 python3 benchmarks/loader.py "+experiment=paper_scale" --workers 0 --device-cache --device cuda \
    --batches 100 --out "$WORK/loader_cuda.json" 2>&1 | grep -E "^workers|Error" | cut -c1-300
fi
run_train() {  # <tree> <run dir> <timeout s> <overrides...>: train (+ evaluate) and print the step rate and metrics
  local tree=$1 dir=$2 limit=$3; shift 3
  (cd "$tree" && PYTHONPATH=$SITE:$PWD/src timeout "$limit" python3 -m realityavatar.train "$@" \
    hydra.run.dir="$dir" > "$dir.log" 2>&1); echo "train rc $? ($dir)"; grep -E "Error|error:" "$dir.log" | tail -3
  # Lightning's simple profiler (+trainer.profiler=simple below): host seconds per hook, e.g. the loader's next batch
  grep -E "^\|  (run_training_batch|\[Strategy\]SingleDeviceStrategy\.(training_step|batch_to_device)|\[_TrainingEpochLoop\]\.train_dataloader_next|\[Callback\][A-Za-z]+.*on_train_batch_end)" \
    "$dir.log" | sed -E 's/\{[^}]*\}//; s/ {3,}/  /g' | cut -c1-160
  python3 - "$dir" <<'PY'
import json, sys
from pathlib import Path
m = Path(sys.argv[1]) / "metrics.json"
if not m.is_file():
    sys.exit(f"no metrics.json in {sys.argv[1]}")
r = json.loads(m.read_text())
keys = ("train_seconds", "iterations", "num_gaussians", "peak_gpu_memory_gb", "render_fps", "backend", "training_set")
print(json.dumps({k: r.get(k) for k in keys}))
print(json.dumps({f"{s}/{k}": r.get(f"test/{s}/{k}") for s in ("novel_view", "novel_pose") for k in ("psnr", "ssim", "iou")}))
PY
}
if [ -n "${SWEEP:-}" ]; then
  el "sweep preset, 1000 steps (this commit)"
  run_train "$PWD" "$WORK/sweep" 300 +preset=sweep data=synthetic_sweep trainer=gpu render.backend=gsplat \
    +trainer.profiler=simple ${COMPILE:+compile=$COMPILE}
  if [ -n "${BASELINE:-}" ]; then
    el "sweep preset, 1000 steps ($BASELINE)"
    run_train "$BASELINE" "$WORK/sweep_baseline" 300 +preset=sweep data=synthetic_sweep trainer=gpu render.backend=gsplat
  fi
fi
if [ -n "${PAPER_SCALE:-}" ]; then
  # Lightning's max_time stops training after PAPER_SCALE seconds, cut to what DEADLINE leaves after PAPER_RESERVE
  # seconds for set-up and evaluation (metrics.json's iterations: the steps reached); the hard limit is the deadline.
  # PAPER_RESUME=1 (a later call on the warm machine): the run in $WORK/paper_scale goes on (resume=true) for
  # PAPER_SCALE more seconds; Lightning's limit counts the earlier part's training time, so it is raised by that.
  S=$(( $(left) - ${PAPER_RESERVE:-110} )); [ "$S" -lt "$PAPER_SCALE" ] && PAPER_SCALE=$S  # set-up + evaluation
  RESUME=(); T=$PAPER_SCALE
  if [ -n "${PAPER_RESUME:-}" ] && [ -f "$WORK/paper_scale/last.ckpt" ]; then
    RESUME=(resume=true); T=$(( T + $(python3 -c "import json; print(int(json.load(open('$WORK/paper_scale/metrics.json'))['train_seconds']))") ))
  fi
  MAXT=$(printf '00:%02d:%02d:%02d' $((T / 3600)) $((T % 3600 / 60)) $((T % 60)))
  el "+experiment=paper_scale ${RESUME[*]} (training stops after ${PAPER_SCALE}s more: max_time $MAXT)"
  run_train "$PWD" "$WORK/paper_scale" $(( $(left) - 5 )) +experiment=paper_scale +trainer.max_time=$MAXT \
    +trainer.profiler=simple ${COMPILE:+compile=$COMPILE} "${RESUME[@]}" ${PAPER_ARGS:-}
fi
if [ -n "${PAPER_VARIANTS:-}" ]; then
  # Several paper_scale variants trained side by side on the one GPU (each step is host-bound: ~4 ms of kernels in a
  # ~22 ms eager step), each stopped by Lightning's max_time if its iterations do not fit, then tested at 512².
  S=$(( $(left) - ${PAPER_RESERVE:-110} )); [ -n "${PAPER_VARIANTS_S:-}" ] && [ "$PAPER_VARIANTS_S" -lt "$S" ] && S=$PAPER_VARIANTS_S
  MAXT=$(printf '00:%02d:%02d:%02d' $((S / 3600)) $((S % 3600 / 60)) $((S % 60)))
  IFS=";" read -ra VARIANTS <<< "$PAPER_VARIANTS"; PIDS=()
  for V in "${VARIANTS[@]}"; do NAME=${V%%:*}; read -ra OV <<< "${V#*:}"
    el "paper_scale variant $NAME: ${OV[*]} (training stops after ${S}s at the latest)"
    run_train "$PWD" "$WORK/$NAME" $(( $(left) - 5 )) +experiment=paper_scale +trainer.max_time=$MAXT \
      threads=${PAPER_THREADS:-4} ${PAPER_ARGS:-} "${OV[@]}" > "$WORK/$NAME.summary" 2>&1 &
    PIDS+=($!)
  done
  wait "${PIDS[@]}"; el "paper_scale variants done"
  for V in "${VARIANTS[@]}"; do NAME=${V%%:*}; echo "== $NAME"; cat "$WORK/$NAME.summary"
    [ -f "$WORK/$NAME/metrics.json" ] && python3 -c "import json, sys; from realityavatar.evaluate import format_table
print(format_table(json.load(open(sys.argv[1]))))" "$WORK/$NAME/metrics.json"  # a row per split and motion phase
    [ -f "$WORK/$NAME/last.ckpt" ] && [ "$(stat -c %s "$WORK/$NAME/last.ckpt")" -lt 16000000 ] && cp "$WORK/$NAME/last.ckpt" "$OUT/$NAME.ckpt"
  done
  (cd "$WORK" && tar czf "$OUT/grids.tgz" */images/*.png 2>/dev/null)
fi
if [ -n "${PAPER_SCALE:-}${PAPER_EVAL:-}" ] && [ -f "$WORK/paper_scale/metrics.json" ] && [ "$(left)" -gt 40 ]; then
  # Beside the CPU sweep preset on equal terms: the 512 px model on the sweep scene (the same sequence and cameras at
  # 128 px, every 2nd frame), each image rendered at 512 px and averaged over 4 x 4 pixels (eval.supersample; rendered
  # at 128 px directly, its sub-pixel Gaussians would be widened by the rasterizer's filter), -> paper_scale/eval/;
  # then the per-phase probe of the held-out cameras (rest / spin / after the stop) and the novel-pose spin's phases.
  AT128=(data.sequence=skirt_spin_demo data.build_overrides=null data.image_scale=0.5 data.frame_subsample=2
         eval.supersample=4)
  el "paper_scale on the sweep scene (128 px, 4x supersampled)"
  timeout $(( $(left) - 5 )) python3 -m realityavatar.evaluate run_dir="$WORK/paper_scale" eval.save_video=false \
    "${AT128[@]}" > "$WORK/eval128.log" 2>&1; echo "evaluate rc $?"; tail -7 "$WORK/eval128.log" | cut -c1-300
  el "probe of paper_scale (held-out cameras, 128 px, 4x supersampled)"
  timeout $(( $(left) - 5 )) python3 -m realityavatar.analysis.probe "$WORK/paper_scale" --heldout-only \
    --override "${AT128[@]}" --out "$WORK/probe" > "$WORK/probe.log" 2>&1; echo "probe rc $?"
  tail -12 "$WORK/probe.log" | cut -c1-300
fi
el done
