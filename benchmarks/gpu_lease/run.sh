#!/usr/bin/env bash
# On a GPU machine without network, from the repository root: bash benchmarks/gpu_lease/run.sh LIMIT_S [gpu_check args...]
# with the missing packages as wheels in .whl/ (benchmarks/gpu_lease/wheels.txt; docs/benchmarks.md, GPU).
# Installs the carried wheels and sked_ns, builds nerfacc's patched kernels and gsplat in the background (niced),
# runs benchmarks/gpu_check.py (waiting for a build only where it needs it), all inside LIMIT_S seconds.
set -u
start=$(date +%s)
limit=${1:?LIMIT_S}; shift
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
exec > >(tee -a "$OUT/log.txt") 2>&1
left() { echo $(( limit - ($(date +%s) - start) )); }
echo "== start $(date -u +%FT%TZ), limit ${limit}s"
nvidia-smi --query-gpu=name,memory.total,memory.used,driver_version,clocks.sm,clocks.max.sm,power.limit --format=csv
nproc; free -g | head -2
export PATH="$PATH:/usr/local/cuda/bin"
which nvcc ninja python3; nvcc --version | tail -1
# The toolkit folder with the headers (gsplat's JIT build takes torch's CUDA_HOME guess, wrong for a wrapper nvcc).
for d in "${CUDA_HOME:-}" /usr/local/cuda /usr/local/cuda-13.0 "$(dirname "$(dirname "$(readlink -f "$(which nvcc)")")")"; do
  [ -n "$d" ] && [ -f "$d/include/cuda_runtime.h" ] && export CUDA_HOME="$d" && break
done
echo "CUDA_HOME=${CUDA_HOME:-unset}"
ls "$(python3 -c 'import sysconfig; print(sysconfig.get_paths()["include"])')/Python.h"
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 3
export PYTHONPATH=/tmp/site
python3 -m pip install -q --no-deps --no-build-isolation -e . || exit 4
echo "== installed at $(( $(date +%s) - start ))s"
python3 -m pip list 2>/dev/null | grep -iE "^(torch|numpy|transformers|huggingface.hub|diffusers|nerfstudio|gsplat|nerfacc|triton|sked.ns|setuptools) "
export TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 HF_HUB_OFFLINE=1 PYTHONUNBUFFERED=1
rm -f /tmp/gsplat_built /tmp/nerfacc_built
(
  nice -n 10 python3 -c "
import time; t = time.time()
from sked_ns.models.nerf.nerfacc_kernels import ensure_kernels
print('nerfacc kernels:', ensure_kernels(), f'{time.time() - t:.0f} s', flush=True)" > /tmp/build_nerfacc.txt 2>&1
  echo $? > /tmp/nerfacc_built.tmp; mv /tmp/nerfacc_built.tmp /tmp/nerfacc_built
  echo "== nerfacc build exit $(cat /tmp/nerfacc_built) at $(( $(date +%s) - start ))s"
) &
(
  nice -n 10 python3 -c "
import time; t = time.time()
from gsplat.cuda._backend import _C
assert _C is not None, 'gsplat: no CUDA extension'
print('gsplat kernels built and loaded', f'{time.time() - t:.0f} s', flush=True)" > /tmp/build_gsplat.txt 2>&1
  echo $? > /tmp/gsplat_built.tmp; mv /tmp/gsplat_built.tmp /tmp/gsplat_built
  echo "== gsplat build exit $(cat /tmp/gsplat_built) at $(( $(date +%s) - start ))s"
) &
run_for=$(( $(left) - 25 ))
echo "== gpu_check for at most ${run_for}s"
timeout -s INT -k 10 "$run_for" python3 benchmarks/gpu_lease/waiting.py benchmarks/gpu_check.py --output "$OUT/gpu_check.json" \
  --budget-s $(( run_for - 10 )) "$@"
echo "== gpu_check exit $? at $(( $(date +%s) - start ))s"
{ echo "--- nerfacc"; cat /tmp/build_nerfacc.txt; echo "--- gsplat"; cat /tmp/build_gsplat.txt; } > "$OUT/builds.txt" 2>&1
tail -c 3000 /tmp/build_nerfacc.txt /tmp/build_gsplat.txt
ext=$HOME/.cache/torch_extensions
ls -la "$ext"/*/ 2>/dev/null | head -20
sos=$(ls "$ext"/*/nerfacc_csrc_sked_*/nerfacc_csrc_sked_*.so "$ext"/*/gsplat_cuda/gsplat_cuda.so 2>/dev/null)
[ -n "$sos" ] && tar -czf "$OUT/kernels.tar.gz" $sos 2>/dev/null; ls -la "$OUT"
nvidia-smi --query-gpu=memory.used,clocks.sm --format=csv
echo "== end at $(( $(date +%s) - start ))s"
