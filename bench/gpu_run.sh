#!/usr/bin/env bash
# GPU checks and benchmarks in one short run on a lent GPU machine (the device tool), from the
# repository root, with $OUT the folder whose files come back:
#   1. tests/test_cuda.py: the CUDA path against the CPU path on a tiny synthetic scene;
#   2. `cmc bench llff` on fern with the `fast` preset on CUDA (train seconds, render ms, scores);
#   3. the `paper` preset on fern on CUDA: its step time first, then the bench with as many of
#      its 20000 steps as the time left allows (the report's config says how many ran).
#   4. profile: bench/profile_job.py on fern (seconds per stage of one `fast` job);
#   5. explore: bench/explore_gpu.py, the variants in $VARIANTS (a JSON file) on the validation
#      views of fern, room and trex (LPIPS-vgg too), then the synthetic scene posts, for the
#      seconds left less 150.
# The data travel in .gpudata/ (ignored; ../shared stays behind), made here once with
# `python bench/gpudata.py pack` and carried with the device tool's `carry: [".gpudata"]`.
# Usage: GIT_COMMIT=$(git rev-parse --short HEAD) [VARIANTS=F.json] bash bench/gpu_run.sh [SECONDS [STAGE...]]
# with STAGE tests, fast, paper, profile or explore (default: the first three, in that order).
set -u
budget=${1:-540}
shift
stages=" ${*:-tests fast paper} "
python3 bench/gpudata.py unpack
start=$(date +%s)
left() { echo $((budget - ($(date +%s) - start))); }
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 CMC_LPIPS_DIR=$PWD/.gpudata/weights
export CMC_GIT_COMMIT=${GIT_COMMIT:-} TQDM_DISABLE=1
OUT=${OUT:-/tmp/gpu_out}
mkdir -p "$OUT"
{
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
  python3 -c 'import sys, torch, numpy, numba; print(sys.version.split()[0], "torch", torch.__version__, "numpy", numpy.__version__, "numba", numba.__version__)'
  nproc
} 2>&1 | tee "$OUT/env.txt"

if [[ $stages == *" tests "* ]]; then
echo "== tests/test_cuda.py ($(left) s left)"
timeout 150 python3 -m pytest -q --noconftest -p no:cacheprovider tests/test_cuda.py 2>&1 | tail -n 30 | tee "$OUT/test_cuda.txt"
fi

if [[ $stages == *" fast "* ]]; then
echo "== fern, fast, cuda ($(left) s left)"
timeout 200 python3 -m cmc.cli bench llff --data .gpudata/llff --scenes fern --preset fast --device cuda \
  --out "$OUT/fern_fast_cuda.json" 2>&1 | tail -n 20
fi

if [[ $stages == *" paper "* ]]; then
echo "== paper preset: step time ($(left) s left)"
python3 - "$(left)" "$OUT/paper_steps.txt" <<'EOF' 2>&1 | tail -n 20
import sys, time
from pathlib import Path
import torch
from cmc.config import preset_config
from cmc.data.datasets import load_llff
from cmc.method.training import Trainer

left, out = float(sys.argv[1]), sys.argv[2]
cfg = preset_config("paper")
trainer = Trainer(load_llff(Path(".gpudata/llff/fern")).train, cfg, "cuda")
per_phase = []
for first in (0, int(cfg.loss.recon_only_fraction * cfg.steps)):  # reconstruction only, then all terms
    trainer.step = first
    trainer.train_step()
    torch.cuda.synchronize()
    t = time.perf_counter()
    for _ in range(10):
        trainer.train_step()
    torch.cuda.synchronize()
    per_phase.append((time.perf_counter() - t) / 10)
frac = cfg.loss.recon_only_fraction
full_s = cfg.steps * (frac * per_phase[0] + (1 - frac) * per_phase[1])
train_budget = left - 150  # bake, eight renders and the scoring, with room to spare
steps = min(cfg.steps, int(cfg.steps * train_budget / full_s))
print(f"paper step: {per_phase[0] * 1000:.1f} ms (reconstruction only), {per_phase[1] * 1000:.1f} ms (all terms); "
      f"20000 steps would take {full_s:.0f} s; running {steps}")
Path(out).write_text(f"{per_phase[0]} {per_phase[1]} {full_s} {steps}\n")
EOF
steps=$(awk '{print $4}' "$OUT/paper_steps.txt" 2>/dev/null)
if [ -n "$steps" ] && [ "$steps" -gt 0 ]; then
  echo "== fern, paper ($steps steps), cuda ($(left) s left)"
  timeout $(( $(left) - 10 )) python3 -m cmc.cli bench llff --data .gpudata/llff --scenes fern --preset paper \
    --device cuda --set steps="$steps" --out "$OUT/fern_paper_cuda.json" 2>&1 | tail -n 20
fi
fi
if [[ $stages == *" profile "* ]]; then
echo "== profile of one fast job on fern, cuda ($(left) s left)"
timeout 120 python3 bench/profile_job.py --data .gpudata/llff/fern --device cuda \
  --out "$OUT/profile_fern_cuda.json" 2>&1 | tail -n 25
fi

if [[ $stages == *" explore "* ]]; then
echo "== explore $VARIANTS ($(left) s left)"
python3 bench/explore_gpu.py "$VARIANTS" "$OUT" --data .gpudata/llff --scenes fern,room,trex \
  --synthetic posts --lpips --blend-powers 2,4,8 --workers 9 --seconds $(( $(left) - 150 )) --grace 130 2>&1 \
  | cut -c1-400 | tail -n 40
fi
echo "== done ($(left) s left)"
