#!/usr/bin/env bash
# A later call: the kernels that run.sh built (its kernels.tar.gz, copied to .whl/) loaded as prebuilt modules
# (nerfacc.csrc, gsplat.csrc shims), so nothing compiles; then gpu_check with the given args inside LIMIT_S.
set -u
start=$(date +%s)
limit=${1:?LIMIT_S}; shift
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
exec > >(tee -a "$OUT/log.txt") 2>&1
echo "== start $(date -u +%FT%TZ), limit ${limit}s"
nvidia-smi --query-gpu=name,memory.used,clocks.sm,clocks.max.sm --format=csv
export PATH="$PATH:/usr/local/cuda/bin" CUDA_HOME=/usr/local/cuda
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 3
export PYTHONPATH=/tmp/site
python3 -m pip install -q --no-deps --no-build-isolation -e . || exit 4
mkdir -p /tmp/kernels && tar -xzf .whl/kernels.tar.gz -C /tmp/kernels || exit 5
gs=$(ls /tmp/kernels/root/.cache/torch_extensions/*/gsplat_cuda/gsplat_cuda.so)
na=$(ls /tmp/kernels/root/.cache/torch_extensions/*/nerfacc_csrc_sked_*/nerfacc_csrc_sked_*.so)
shim() {  # module file $1 loads extension $2 (its init name: the file's stem) and stands in for itself
cat > "$1" <<PY
import importlib.machinery, importlib.util, sys
import torch  # noqa: F401  (the extension links against it)
_loader = importlib.machinery.ExtensionFileLoader("$(basename "$2" .so)", "$2")
_spec = importlib.util.spec_from_file_location("$(basename "$2" .so)", "$2", loader=_loader)
_module = importlib.util.module_from_spec(_spec)
_loader.exec_module(_module)
sys.modules[__name__] = _module
PY
}
shim /tmp/site/gsplat/csrc.py "$gs"; shim /tmp/site/nerfacc/csrc.py "$na"
python3 -c "
import torch; from gsplat import csrc as g; from nerfacc import csrc as n
from sked_ns.models.nerf.nerfacc_kernels import ensure_kernels
print('prebuilt kernels:', g.__name__, n.__name__, ensure_kernels())" || exit 6
echo "== ready at $(( $(date +%s) - start ))s"
export HF_HUB_OFFLINE=1 PYTHONUNBUFFERED=1
run_for=$(( limit - ($(date +%s) - start) - 15 ))
timeout -s INT -k 10 "$run_for" python3 benchmarks/gpu_check.py --output "$OUT/gpu_check.json" --budget-s $(( run_for - 10 )) "$@"
echo "== gpu_check exit $? at $(( $(date +%s) - start ))s"
ls -la "$OUT"
nvidia-smi --query-gpu=memory.used,clocks.sm --format=csv
echo "== end at $(( $(date +%s) - start ))s"
