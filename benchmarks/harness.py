"""What the benchmarks share: their results file and work folder, the environment they record, the demo scene and
its bases, the `ns-train sked` edits they set up, and the timing and naming of a step's phases.

A benchmark claims its results file (and work folder) before it measures anything (`claim`), records the machine
it ran on with `environment`, writes its results with `write_results` and prints them with `markdown_table`.
"""

from __future__ import annotations

import contextlib
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable, Dict, Iterable, Iterator, List, Optional, Sequence

import torch
from sole_writer import claim  # noqa: F401  (the benchmarks claim their files through here)

from sked_ns.atomic import write_text_atomically

BENCHMARKS = Path(__file__).resolve().parent
RESULTS = BENCHMARKS / "results"
PROMPT = "a red chef hat"


# ---- results -----------------------------------------------------------------------------------
@contextlib.contextmanager
def work_folder(workdir: Optional[Path]) -> Iterator[Path]:
    """`--workdir` (kept, so a rerun reuses its bases), or a scratch folder removed at the end."""
    if workdir is not None:
        workdir.mkdir(parents=True, exist_ok=True)
        yield workdir
        return
    with tempfile.TemporaryDirectory() as scratch:
        yield Path(scratch)


def commit() -> str:
    """The measured code's commit (the checkout these scripts run from)."""
    try:
        result = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=BENCHMARKS)
    except OSError:  # no git where the copy runs (a lent machine)
        return "unknown"
    return result.stdout.strip() or "unknown"


def environment(device: str) -> Dict:
    """The machine and the versions a result was measured with, recorded the same way by every benchmark."""
    info = {"python": platform.python_version(), "torch": torch.__version__, "cuda": torch.version.cuda,
            "device": torch.cuda.get_device_name() if device == "cuda" else f"{platform.machine()} CPU",
            "machine": platform.processor() or platform.machine(), "platform": platform.platform(),
            "cpu_count": os.cpu_count(),
            "torch_threads": torch.get_num_threads(), "commit": commit()}
    try:
        from importlib.metadata import version

        import nerfacc

        info["nerfstudio"] = version("nerfstudio")
        info["nerfacc"] = nerfacc.__version__
        try:
            from nerfacc import csrc  # noqa: F401

            info["nerfacc_kernels"] = "prebuilt extension (nerfacc.csrc)"
        except ImportError:
            from sked_ns.models.nerf.nerfacc_kernels import needs_patched_build

            # How the first kernel call will get them (sked_ns/models/nerf/nerfacc_kernels.py).
            info["nerfacc_kernels"] = ("sked_ns's patched copy, built once per content" if needs_patched_build()
                                       else "nerfacc's own JIT build on first use")
    except Exception as error:  # reported, not fatal
        info["import_error"] = repr(error)
    return info


def write_results(path: Path, data) -> None:
    """The results JSON, replaced whole (a kill mid-write leaves the previous one)."""
    write_text_atomically(path, json.dumps(data, indent=2, default=str))


def publish(result: Dict, output: Optional[Path], device: str = "cpu") -> None:
    """A JSON result printed and, given `output` (claimed before measuring), written whole there, with the environment
    it was measured in: for scripts whose figures are a record, not a table."""
    result = {**result, "environment": environment(device)}
    print(json.dumps(result, indent=2, default=str))
    if output is not None:
        write_results(output, result)


def report(table: str, *written: Path) -> None:
    """A benchmark's last words: its table and the files it wrote."""
    print(table)
    print(f"wrote {' and '.join(map(str, written))}")


def markdown_table(header: Sequence[str], rows: Iterable[Sequence]) -> str:
    """A Markdown table: one header cell per column, each row's cells already formatted."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows])


# ---- timing ------------------------------------------------------------------------------------
def sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def peak_rss_gb() -> float:
    """The process's peak resident memory so far (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def timed_calls(function: Callable[[], object], repeats: int, device: str, warmup: int = 1) -> List[float]:
    """Wall times of REPEATS calls of FUNCTION, each between device synchronisations, after WARMUP untimed ones
    (compilation out of the figures)."""
    times = []
    for repeat in range(warmup + repeats):
        sync(device)
        start = time.perf_counter()
        function()
        sync(device)
        if repeat >= warmup:
            times.append(time.perf_counter() - start)
    return times


def timed_steps(trainer, steps: Iterable[int], device: str) -> List[float]:
    """Each training iteration's wall time, between device synchronisations."""
    steps = list(steps)
    queue = iter(steps)
    return timed_calls(lambda: trainer.train_iteration(next(queue)), len(steps), device, warmup=0)


class StageTimer:
    """Synchronised wall time per stage (costs a little: the split, not the iteration time)."""

    def __init__(self, device: str) -> None:
        self.device, self.totals, self.enabled = device, {}, True

    @contextlib.contextmanager
    def stage(self, name: str):
        if not self.enabled:
            yield
            return
        sync(self.device)
        start = time.perf_counter()
        try:
            yield
        finally:
            sync(self.device)
            self.totals[name] = self.totals.get(name, 0.0) + time.perf_counter() - start

    def wrap(self, owner, attribute: str, name: str) -> Callable[[], None]:
        """owner.attribute timed as the stage `name`; returns a function that unwraps it."""
        return wrap(owner, attribute, lambda: self.stage(name))


# ---- naming a step's phases --------------------------------------------------------------------
def wrap(owner, attribute: str, context: Callable[[], contextlib.AbstractContextManager],
         before: Optional[Callable] = None) -> Callable[[], None]:
    """owner.attribute run inside context() (`before(*args)` first, when given); returns a function that unwraps it."""
    original = getattr(owner, attribute)

    def wrapped(*args, **kwargs):
        if before is not None:
            before(*args)
        with context():
            return original(*args, **kwargs)

    setattr(owner, attribute, wrapped)
    return lambda: setattr(owner, attribute, original)


def marked(owner, attribute: str, names: List[str], context: Callable) -> Callable[[], None]:
    """Wrap owner.attribute so that its n-th call in a step runs inside context(names[n]) (the last name after that):
    a memory part, a census phase. Returns a function that restarts the count."""
    calls: List[str] = []

    def named():
        calls.append(names[min(len(calls), len(names) - 1)])
        return context(calls[-1])

    wrap(owner, attribute, named)
    return calls.clear


def mark_backward(scaler, context: Callable) -> None:
    """nerfstudio's `grad_scaler.scale(loss).backward()` runs inside context("backward")."""
    original_scale = scaler.scale

    class Backward:
        def __init__(self, loss):
            self.loss = loss

        def backward(self, *args, **kwargs):
            with context("backward"):
                return self.loss.backward(*args, **kwargs)

    scaler.scale = lambda outputs: Backward(original_scale(outputs))


class ImageGradient:
    """Guidance stand-in: a fixed random gradient on the rendered image, as score distillation hands the render
    (SDS's loss has no graph of its own past the image), run inside context("guidance"). `cached`: one gradient per
    image shape, made once (a census counts the step, not the stand-in's inputs); else a new one each step."""

    needs_base_render = False

    def __init__(self, context: Callable = lambda name: contextlib.nullcontext(), cached: bool = False) -> None:
        self.context, self.cached, self.gradients = context, cached, {}

    def __call__(self, view, step: int) -> Dict[str, torch.Tensor]:
        with self.context("guidance"):
            key = tuple(view.image.shape)
            gradient = self.gradients.get(key)
            if gradient is None:
                seed = 0 if self.cached else step
                gradient = torch.randn(key, generator=torch.Generator().manual_seed(seed)).to(view.image)
                if self.cached:
                    self.gradients[key] = gradient
            return {"image_gradient": (view.image * gradient).sum() * 1e-3}


# ---- the demo scene, its bases, and edits of them ----------------------------------------------
def demo_scene(work: Path, rewrite: bool = True) -> None:
    """The demo sphere's photos (work/data) and sketches (work/sketches); `rewrite` False keeps ones already there."""
    from sked_ns.demo.scenes import sphere
    from sked_ns.sketches.sketch_set import save_sketch_set

    if rewrite or not (work / "data").exists():
        sphere.write_demo_dataset(work / "data")
        save_sketch_set(sphere.demo_sketch_set(), work / "sketches", overwrite=True)


def demo_base(work: Path, method: str, steps: int, tiny=None, device: str = "cpu", splat_fit=None,
              grid_passes: Optional[int] = None, reuse: bool = True) -> Path:
    """A base of the demo scene under work/bases, fitted with METHOD's architecture (`tiny`: the tests' sizes);
    `reuse`: one already there is taken. Splat bases are fitted with `splat_fit` on the CPU (the torch rasterizer),
    instant-ngp's with at most `grid_passes` full-grid occupancy passes."""
    from sked_ns.demo.base import build_demo_base
    from sked_ns.demo.splat_base import SplatFit, fit_demo_splat_base

    built = sorted((work / "bases").glob(f"*/{method}/*/config.yml"))
    if built and reuse:
        return built[-1].parent
    if method == "splatfacto":
        return fit_demo_splat_base(work / "data", work / "bases", splat_fit or SplatFit())
    with few_grid_passes(grid_passes if method != "nerfacto" else None):
        return build_demo_base(work / "data", work / "bases", steps=steps, tiny=tiny, method=method, device=device)


@contextlib.contextmanager
def few_grid_passes(passes: Optional[int]):
    """At most PASSES of the demo base's full-grid occupancy passes: at instant-ngp's size each costs minutes in
    torch, and after the first the static scene's occupied cells hardly change (the step's samples follow them)."""
    if passes is None:
        yield
        return
    from nerfacc import OccGridEstimator

    original, calls = OccGridEstimator._update, []

    def update(self, *args, **kwargs):
        calls.append(1)
        if len(calls) <= passes:
            return original(self, *args, **kwargs)

    OccGridEstimator._update = update
    try:
        yield
    finally:
        OccGridEstimator._update = original


def sked_flags(base: Path, work: Path, name: str, device: str, iterations: int = 100, output: str = "edits",
               prompt: Optional[str] = PROMPT) -> List[str]:
    """The head of a user's `ns-train sked` command line for an edit of BASE with the demo sketches: no checkpoints
    during the run; the model's flags, then the guidance's and the dataparser's subcommands follow."""
    return ["--load-dir", str(base), "--sketches", str(work / "sketches"), "--max-num-iterations", str(iterations),
            "--output-dir", str(work / output), "--experiment-name", name, "--vis", "tensorboard",
            "--machine.device-type", device, "--steps-per-save", str(10**9),
            *(["--prompt", prompt] if prompt else [])]


def reference_edit_tail(work: Path) -> List[str]:
    """The subcommands of an edit guided by the reference stand-in, on the demo photos."""
    return ["pipeline.model.guidance:reference", "nerfstudio-data", "--data", str(work / "data")]


def ns_train_sked(arguments: List[str]):
    """`ns-train sked ARGUMENTS` parsed by nerfstudio's own command line, prepared as its `main` does."""
    import tyro
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    config = tyro.cli(AnnotatedBaseConfigUnion, args=["sked", *arguments])
    if config.data:
        config.pipeline.datamanager.data = config.data
    if config.prompt:
        config.pipeline.model.prompt = config.prompt
    config.set_timestamp()
    config.save_config()
    return config


def set_up_edit(arguments: List[str], guidance=None):
    """The trainer of `ns-train sked ARGUMENTS`, set up and its guidance prepared (then replaced by `guidance`)."""
    trainer = ns_train_sked(arguments).setup(local_rank=0, world_size=1)
    trainer.setup()
    trainer.pipeline.prepare_guidance()
    if guidance is not None:
        trainer.pipeline.model.guidance = guidance
    return trainer


def ns_train_command(arguments: List[str], setup: str = "") -> List[str]:
    """`ns-train ARGUMENTS` as a fresh process (SETUP: Python run first), without nerfstudio's LPIPS metric (it
    downloads AlexNet weights)."""
    code = setup + ("import sys; from sked_ns.method.options import without_lpips; "
                    "from nerfstudio.scripts.train import entrypoint; "
                    "sys.argv = ['ns-train'] + sys.argv[1:]\nwith without_lpips(): entrypoint()")
    return [sys.executable, "-c", code, *arguments]
