"""Run a script while the CUDA extensions build in the background (run.sh beside this starts them).

gsplat's JIT path deletes its build folder when no built library is there yet, so a second process must not
import gsplat.cuda._backend while the background build runs: this waits for it (flag file holding the build's exit
code). nerfacc's patched kernels are waited for too, so a failed background build fails fast instead of compiling
again. Usage: python3 waiting.py SCRIPT ARGS...
"""

import importlib.abc
import os
import runpy
import sys
import time

FLAGS = {"gsplat": "/tmp/gsplat_built", "nerfacc": "/tmp/nerfacc_built"}


def wait_for(kind: str) -> None:
    flag, start = FLAGS[kind], time.time()
    while not os.path.exists(flag):
        time.sleep(0.5)
    code = open(flag).read().strip()
    waited = time.time() - start
    print(f"[waiting.py] {kind} build finished with exit code {code}; waited {waited:.1f} s for it", flush=True)
    if code != "0":
        raise ImportError(f"the background {kind} build failed (exit code {code}); see builds.txt")


class WaitForGsplat(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "gsplat.cuda._backend":
            wait_for("gsplat")
        return None


sys.meta_path.insert(0, WaitForGsplat())

import sked_ns.models.nerf.nerfacc_kernels as kernels  # noqa: E402

_build_patched = kernels.build_patched


def build_patched():
    wait_for("nerfacc")
    return _build_patched()


kernels.build_patched = build_patched
sys.argv = sys.argv[1:]
runpy.run_path(sys.argv[0], run_name="__main__")
