#!/bin/bash
# The accelerator figures of the performance section, in one command, on one GPU (or TPU chip):
#   launch/accelerator_bench.sh [--out DIR] [--budget SECONDS] [--tiny]
# (default DIR: bench-$(hostname); default budget: 480 s). Each step runs in its own process under
# `timeout`, within what is left of the budget; a step that fails or runs out of time is reported and
# the next one runs. The steps, the main figure of each item first:
#  1. the ~1.2B STDiT-3 preset's train step (bf16 compute, fp32 master weights, cuDNN attention on a
#     GPU, scanned layers) at remat "dots" and "full", each at the largest batch that fits the
#     device (`--batch auto`): step time, tokens/s, MFU against the vendor bf16 peak and against a
#     measured 8192^3 bf16 matmul, the device's peak memory, and a jax.profiler trace of 2 steps
#     whose largest device costs are named;
#  2. the CogVideoX-2B VAE: decode of 49 frames at 480 x 720 in bf16, chunked and whole-clip, each in
#     a process of its own (the device's peak memory never goes down within a process);
#  3. the long-video strategies at 33 / 145 / 721 frames, one process per strategy;
#  4. where a controls recipe exists (configs/world.py, or $WORLD_CONFIG), training it for what is
#     left of the budget (at least 3 minutes) and `jaxdrive eval` with routes.
# DIR gets log.txt (everything printed), figures.jsonl (every figure, one JSON object a line, with
# the step that printed it), figures.md (the tables, printed last) and profile_top.json (the
# largest costs of the fastest train setting). --tiny runs every step at toy sizes on the CPU.
# Missing Python packages are installed from the wheels in .whl/, when there is such a folder;
# jaxdrive itself runs from this checkout (PYTHONPATH).
set -uo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd) || exit 1
OUT=""; TINY=0; BUDGET=480; BUDGET_GIVEN=0
while [ $# -gt 0 ]; do
  case "$1" in
    --out) OUT=$2; shift 2 ;;
    --budget) BUDGET=$2; BUDGET_GIVEN=1; shift 2 ;;
    --tiny) TINY=1; shift ;;
    -h|--help) sed -n '2,21p' "$ROOT/launch/accelerator_bench.sh"; exit 0 ;;
    -*) echo "accelerator_bench.sh: expected --out DIR, --budget SECONDS or --tiny, got $1" >&2; exit 2 ;;
    *) OUT=$1; shift ;;
  esac
done
case "$BUDGET" in ''|*[!0-9]*) echo "accelerator_bench.sh: --budget: expected whole seconds, got $BUDGET" >&2; exit 2 ;; esac
OUT=${OUT:-bench-$(hostname)}
mkdir -p "$OUT" || exit 1
OUT=$(cd "$OUT" && pwd)
cd "$ROOT" || exit 1
PY=${PYTHON:-python3}
export PYTHONUNBUFFERED=1
START=$SECONDS
WORK=$(mktemp -d "${TMPDIR:-/tmp}/jaxdrive-accel.XXXXXX")
: > "$WORK/steps.tsv"
: > "$OUT/log.txt"
log() { echo "$*" | tee -a "$OUT/log.txt"; }

# Missing packages from the carried wheels (no network needed), then this checkout's jaxdrive.
if ls .whl/*.whl >/dev/null 2>&1 && ! "$PY" -c "import grain, tensorflow_datasets, array_record, av, dm_pix, tensorboardX" 2>/dev/null; then
  "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site || exit 1
fi
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
JD=("$PY" -m jaxdrive.cli)

CAPS=1
if [ "$TINY" = 1 ]; then
  export JAX_PLATFORMS=cpu
  CAPS=10                # a CPU compiles slowly: the steps' time limits stretch (the budget too, unless given)
  [ "$BUDGET_GIVEN" = 1 ] || BUDGET=3600
  TRAIN=(--presets tiny --frames 2 --height 4 --width 4 --max-batch 2 --device-memory 256MiB --repeats 1
         --measure-peak 64 --profile-steps 1)
  VAE=(--arch tiny --speed-size 32 48 --speed-frames 9)
  LONG=(--frames 17 --steps 2 --views 1)
  STRATEGIES=(coarse-fine)
else
  # 8 latent frames of 32 x 56 (a 256 x 448 clip after an 8x VAE): 3584 tokens a clip
  TRAIN=(--presets stdit3-xl/2 --frames 8 --height 32 --width 56 --max-batch 32 --repeats 3 --measure-peak 8192
         --profile-steps 2)
  VAE=(--speed-size 480 720 --speed-frames 49)
  LONG=(--frames 33 145 721)
  STRATEGIES=(coarse-fine rollout streaming coarse-to-refine coarse-fine-capped)
  # the device's memory for the steps (the allocator takes 75% by default)
  export XLA_PYTHON_CLIENT_MEM_FRACTION=${XLA_PYTHON_CLIENT_MEM_FRACTION:-0.92}
fi

DEADLINE=$((START + BUDGET))

# step NAME CAP_SECONDS COMMAND...: run COMMAND under `timeout` within what is left of the budget,
# its output into WORK/NAME.log and log.txt; the figures so far into DIR after each step.
step() {
  local name=$1 cap=$2; shift 2
  local left=$((DEADLINE - SECONDS)) t rc t0
  # ACCEL_ONLY=REGEX: only the steps whose names match (a rerun of some), the preflight always
  if [ -n "${ACCEL_ONLY:-}" ] && [ "$name" != preflight ] && ! [[ "$name" =~ $ACCEL_ONLY ]]; then
    return 0
  fi
  cap=$((cap * CAPS))
  t=$(( cap < left ? cap : left ))
  if [ "$t" -lt 15 ]; then
    log "== $name: skipped, $(( left > 0 ? left : 0 ))s of the budget left"
    printf '%s\tskipped\t0\tno time left in the budget\n' "$name" >> "$WORK/steps.tsv"
    return 0
  fi
  log "== $name (at most ${t}s): $(echo "$*" | tr '\n' ' ' | cut -c1-240)"
  t0=$SECONDS
  timeout -k 10 "$t" "$@" 2>&1 | tee "$WORK/$name.log" >> "$OUT/log.txt"
  rc=${PIPESTATUS[0]}
  local status=ok
  if [ "$rc" = 124 ] || [ "$rc" = 137 ]; then status=timeout; elif [ "$rc" != 0 ]; then status="failed ($rc)"; fi
  printf '%s\t%s\t%s\t%s\n' "$name" "$status" "$((SECONDS - t0))" "$(grep -v '^{' "$WORK/$name.log" | grep -v '^\s*$' | tail -n 2 | tr '\t\n' '  ' | cut -c1-300)" >> "$WORK/steps.tsv"
  log "== $name: $status in $((SECONDS - t0))s"
  "$PY" launch/accelerator_figures.py "$WORK" "$OUT" > /dev/null || log "(figures: summary failed)"
}

step preflight 90 "$PY" -c "
import importlib.metadata as m, platform, jax
names = ['jax', 'jaxlib', 'flax', 'optax', 'orbax-checkpoint', 'numpy', 'protobuf', 'etils', 'grain',
         'tensorflow-datasets', 'array-record', 'av', 'dm-pix', 'tensorboardX']
def v(n):
    try:
        return m.version(n)
    except m.PackageNotFoundError:
        return 'missing'
print('python', platform.python_version(), ' '.join(f'{n}={v(n)}' for n in names))
d = jax.devices()[0]
print('backend', jax.default_backend(), 'devices', len(jax.devices()), 'kind', d.device_kind)
import jaxdrive.data.pipeline, jaxdrive.data.tfds_io, jaxdrive.media, jaxdrive.eval.frames
print('imports ok')
"
BACKEND=$(grep -o '^backend [a-z]*' "$WORK/preflight.log" | cut -d' ' -f2)
ATTN=xla
WANT=""
if [ "$BACKEND" = gpu ]; then
  ATTN=cudnn
  # XLA flags for one Hopper GPU
  WANT="--xla_gpu_enable_latency_hiding_scheduler=true --xla_gpu_enable_while_loop_double_buffering=true
        --xla_gpu_enable_triton_gemm=false"
elif [ "$BACKEND" = tpu ]; then
  ATTN=auto
fi
# XLA aborts at start on a flag it does not know: keep only those this jaxlib knows, the CPU flag
# that jaxdrive's commands add (jaxdrive.xla_flags) included
known() { XLA_FLAGS="${XLA_FLAGS:-} $*" timeout 60 "$PY" -c "import jax; jax.devices()" > /dev/null 2>&1; }
CPU_FLAG=--xla_cpu_experimental_ynn_fusion_type=
FLAGS=$(echo $WANT)
if ! known $FLAGS $CPU_FLAG; then
  if ! known $CPU_FLAG; then
    export JAXDRIVE_CPU_FLAGS=0
    log "XLA flag $CPU_FLAG: not known to this jaxlib, jaxdrive runs without it (JAXDRIVE_CPU_FLAGS=0)"
  fi
  FLAGS=""
  for f in $WANT; do
    if known $FLAGS $f; then FLAGS="$FLAGS $f"; else log "XLA flag $f: not known to this jaxlib, left out"; fi
  done
fi
export XLA_FLAGS="${XLA_FLAGS:-} $FLAGS"
echo "XLA_FLAGS=${XLA_FLAGS:-} XLA_PYTHON_CLIENT_MEM_FRACTION=${XLA_PYTHON_CLIENT_MEM_FRACTION:-} attention=$ATTN" \
  | tee -a "$OUT/log.txt" > "$WORK/env.txt"

train() {    # train REMAT CAP
  step "train-$1" "$2" "${JD[@]}" bench train "${TRAIN[@]}" --no-torch --dtype bfloat16 --attn-impl "$ATTN" \
    --remat "$1" --scan-layers --batch auto --profile "$WORK/profile-$1"
}
vae() {      # vae MODE CAP
  step "vae-$1" "$2" "${JD[@]}" bench vae "${VAE[@]}" --no-memory --speed-modes "$1" --speed-ops decode \
    --speed-repeats 1 --dtype bfloat16
}
long() {     # long STRATEGY CAP
  step "longvideo-$1" "$2" "${JD[@]}" bench longvideo "${LONG[@]}" --strategies "$1"
}

# each item's main figure first, then the rest
train dots 200
vae chunked 100
long "${STRATEGIES[0]}" 70
train full 170
vae whole 100
for s in "${STRATEGIES[@]:1}"; do long "$s" 60; done

WORLD=${WORLD_CONFIG:-configs/world.py}
LEFT=$((DEADLINE - SECONDS))
if [ "$TINY" = 1 ]; then
  log "== world: skipped (--tiny)"
elif [ ! -f "$WORLD" ]; then
  log "== world: skipped, no controls recipe ($WORLD does not exist)"
elif [ "$LEFT" -lt 240 ]; then
  log "== world: skipped, ${LEFT}s of the budget left (training needs at least 180s, its eval a minute)"
else
  W=$WORK/world
  SYNTH=(--out "$W/data" --scenes 24 --frames 33)
  ROUTES=""
  if "${JD[@]}" data synth --help 2>/dev/null | grep -q -- --counterfactuals; then
    SYNTH+=(--counterfactuals stop,lane-left,lane-right); ROUTES=recorded,stop,lane-left,lane-right
  fi
  step world-data 120 "${JD[@]}" data synth "${SYNTH[@]}"
  TRAIN_S=$((DEADLINE - SECONDS - 75))
  # SIGTERM at the end of the time saves a checkpoint; the eval samples it
  step world-train "$TRAIN_S" "${JD[@]}" train --config "$WORLD" --workdir "$W/run" --set data.path="$W/data" \
    --checkpoint-every 100
  EVAL=(--workdir "$W/run" --out "$W/eval" --clips 1)
  [ -n "$ROUTES" ] && EVAL+=(--routes "$ROUTES")
  step world-eval 75 "${JD[@]}" eval "${EVAL[@]}"
  [ -f "$W/eval/eval.md" ] && cp "$W/eval/eval.md" "$OUT/world_eval.md"
fi

"$PY" launch/accelerator_figures.py "$WORK" "$OUT" --print || echo "(figures: summary failed; see $OUT/log.txt)"
echo "total $((SECONDS - START))s; files in $OUT: $(ls "$OUT" | tr '\n' ' ')"
