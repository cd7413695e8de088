#!/bin/bash
# The accelerator figures of the performance section, in one command, on one GPU or TPU chip:
#   launch/accelerator_bench.sh [OUT_DIR]        (default: bench-$(hostname))
# 1. the ~1.2B STDiT-3 preset's train step in bf16 (fp32 master weights), cuDNN attention on a
#    GPU (splash on a TPU: --attn-impl auto), remat "dots", scanned layers: step time, tokens/s,
#    MFU against the vendor bf16 peak and against a measured 8192^3 bf16 matmul;
# 2. the CogVideoX-2B VAE: decode / encode of 49 frames at 480 x 720, chunked and whole-clip:
#    seconds (frames/s) and the compiled programs' memory;
# 3. the long-video strategies at 33 / 145 / 721 frames.
# Each writes its JSON lines and table to OUT_DIR/<bench>.log.
set -euo pipefail
OUT=${1:-bench-$(hostname)}
mkdir -p "$OUT"
ATTN=cudnn
if python -c "import jax, sys; sys.exit(jax.default_backend() != 'tpu')"; then ATTN=auto; fi
jaxdrive bench train --presets stdit3-xl/2 --no-torch --dtype bfloat16 --attn-impl "$ATTN" --remat dots \
  --scan-layers --measure-peak 8192 --batch 4 --frames 8 --height 32 --width 56 2>&1 | tee "$OUT/train.log"
jaxdrive bench vae --frames 49 --size 480 720 --speed-size 480 720 --speed-frames 49 2>&1 | tee "$OUT/vae.log"
jaxdrive bench longvideo 2>&1 | tee "$OUT/longvideo.log"
