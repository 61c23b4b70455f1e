"""What a splat edit's checkpoint holds: the demo's edit of the demo's splatfacto base, as this version saves it
(what the edit changed: its editable Gaussians, their L_pres targets once refinement moved them, and which of the
base's Gaussians it keeps; a finished edit saves no Adam moments) against the layout earlier versions saved (the
same, the kept Gaussians again, every target, and Adam's moments).

    python benchmarks/splat_edit_size.py [--workdir DIR] [--output benchmarks/results/splat_edit_size.json]

The base and the edit are sked-demo's with `--base splatfacto`: the demo sphere's photos fitted on the CPU, its
sketches, reference guidance, 100 iterations at beta 0.025. The earlier layout is the same checkpoint written with the
kept Gaussians and L_pres's targets under their keys (`kept.*`, `reference.*`), without the kept rows and with the
moments the optimisers held when the edit ended: what the model saved before; both files are loaded back (the earlier one as an edit saved whole) and must render the
edit as trained, bit for bit. Prints a table of bytes per part and writes JSON.
"""

from __future__ import annotations

import argparse
import copy
from pathlib import Path
from typing import Dict

import harness
import torch

ITERATIONS = 100
BETA = 0.025
"""sked-demo's defaults."""


def parts(checkpoint: Dict) -> Dict[str, int]:
    """Bytes of the checkpoint's tensors by what they are."""
    sizes = {"kept Gaussians": 0, "editable Gaussians": 0, "L_pres targets": 0, "kept rows": 0, "Adam state": 0,
             "other": 0}
    for key, value in checkpoint["pipeline"].items():
        if not torch.is_tensor(value):
            continue
        name = key[len("_model."):]
        part = ("kept Gaussians" if name.startswith("kept.") else "editable Gaussians" if name.startswith("gauss_params.")
                else "L_pres targets" if name.startswith("reference.") else "kept rows" if name == "kept_in_base"
                else "other")
        sizes[part] += value.numel() * value.element_size()
    for optimizer in checkpoint["optimizers"].values():
        for state in optimizer["state"].values():
            sizes["Adam state"] += sum(value.numel() * value.element_size() for value in state.values()
                                       if torch.is_tensor(value))
    return sizes


def stored_gaussians(checkpoint: Dict) -> int:
    pipeline = checkpoint["pipeline"]
    return sum(len(pipeline[key]) for key in ("_model.kept.means", "_model.gauss_params.means") if key in pipeline)


def whole_layout(checkpoint: Dict, model, moments: Dict) -> Dict:
    """The checkpoint as earlier versions wrote it: the kept Gaussians and L_pres's targets saved with the edit, no
    kept rows, and Adam's moments as the optimisers held them when the edit ended."""
    earlier = copy.copy(checkpoint)
    earlier["optimizers"] = moments
    pipeline = {key: value for key, value in checkpoint["pipeline"].items() if key != "_model.kept_in_base"}
    whole = {f"_model.{prefix}{name}": value.clone() for prefix, held in (("kept.", model.kept),
                                                                          ("reference.", model.reference))
             for name, value in held.tensors().items()}
    earlier["pipeline"] = {**whole, **pipeline}
    return earlier


def renders_as_trained(trained, run: Path, checkpoint_file: Path, camera) -> bool:
    """The edit loaded from `checkpoint_file` as ns-render loads it renders as the trained model did, bit for bit,
    and keeps the base's Gaussians bit for bit."""
    from nerfstudio.utils.eval_utils import eval_setup

    from sked_ns.models.splat.gaussians import GAUSSIAN_PARAMS

    _, pipeline, _, _ = eval_setup(run / "config.yml", test_mode="inference")
    state = torch.load(checkpoint_file, map_location="cpu")
    pipeline.load_pipeline(state["pipeline"], state["step"])
    model = pipeline.model
    base = model._base_in_its_order()
    kept = all(torch.equal(model.kept[name], base[name][model.kept_in_base]) for name in GAUSSIAN_PARAMS)
    trained.eval()
    model.eval()
    with torch.no_grad():
        before, after = trained.get_outputs(camera), model.get_outputs(camera)
    return kept and all(torch.equal(before[key], after[key]) for key in ("rgb", "accumulation", "depth"))


def measure(work: Path) -> Dict:
    from sked_ns.engine.edit_run import edit_config, run_edit
    from sked_ns.engine.trainer import SkedTrainer
    from sked_ns.method.options import without_lpips

    harness.demo_scene(work, rewrite=False)
    base = harness.demo_base(work, "splatfacto", steps=0)
    config = edit_config(base / "nerfstudio_models", work / "data", work / "sketches", work / "edits",
                         iterations=ITERATIONS)
    config.pipeline.model.beta = BETA
    moments: Dict = {}
    finish = SkedTrainer._after_train

    def after_train(trainer) -> None:  # Adam's moments as earlier versions saved them with the finished edit
        moments.update(copy.deepcopy({name: optimizer.state_dict()
                                      for name, optimizer in trainer.optimizers.optimizers.items()}))
        finish(trainer)

    SkedTrainer._after_train = after_train
    try:
        with without_lpips():
            trainer = run_edit(config)
    finally:
        SkedTrainer._after_train = finish
    model = trainer.pipeline.model
    saved = sorted((trainer.base_dir / "nerfstudio_models").glob("step-*.ckpt"))[-1]
    checkpoint = torch.load(saved, map_location="cpu")
    earlier_file = work / "whole-layout" / saved.name
    earlier_file.parent.mkdir(exist_ok=True)
    earlier = whole_layout(checkpoint, model, moments)
    torch.save(earlier, earlier_file)
    camera = trainer.pipeline.datamanager.train_dataset.cameras[0:1]
    with without_lpips():
        exact = {layout: renders_as_trained(model, trainer.base_dir, path, camera)
                 for layout, path in (("changes", saved), ("whole", earlier_file))}
    kept_copy = Path(model.config.base_kept)
    layouts = {
        "whole scene (earlier versions)": {"checkpoint_bytes": earlier_file.stat().st_size,
                                           "gaussians_stored": stored_gaussians(earlier), "parts": parts(earlier),
                                           "loads_bit_identical": exact["whole"]},
        "changes (this version)": {"checkpoint_bytes": saved.stat().st_size,
                                   "gaussians_stored": stored_gaussians(checkpoint), "parts": parts(checkpoint),
                                   "loads_bit_identical": exact["changes"]},
    }
    old, new = (layout["checkpoint_bytes"] for layout in layouts.values())
    return {
        "base": str(base), "edit": str(trainer.base_dir), "iterations": ITERATIONS, "beta": BETA,
        "base_gaussians": len(model.kept_in_base), "kept_gaussians": len(model.kept["means"]),
        "editable_gaussians": len(model.gauss_params["means"]),
        "seeded_gaussians": int((~model.reference.from_base).sum()),
        "base_copy_bytes": kept_copy.stat().st_size, "layouts": layouts, "ratio": new / old,
    }


def table(result: Dict) -> str:
    names = list(next(iter(result["layouts"].values()))["parts"])
    rows = [[layout, f"{figures['checkpoint_bytes'] / 1e6:.2f}", figures["gaussians_stored"],
             *(f"{figures['parts'][name] / 1e6:.2f}" for name in names), "yes" if figures["loads_bit_identical"] else "NO"]
            for layout, figures in result["layouts"].items()]
    return harness.markdown_table(["layout", "checkpoint (MB)", "Gaussians stored", *(f"{name} (MB)" for name in names),
                                   "loads bit-identical"], rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--workdir", type=Path, default=None, help="kept, so a rerun reuses its base")
    parser.add_argument("--output", type=Path, default=harness.RESULTS / "splat_edit_size.json")
    args = parser.parse_args()
    harness.claim("splat_edit_size.py", args.output, args.workdir)
    with harness.work_folder(args.workdir) as work:
        result = measure(work)
    result["environment"] = harness.environment("cpu")
    harness.write_results(args.output, result)
    summary = (f"\n{result['base_gaussians']} base Gaussians ({result['kept_gaussians']} kept), "
               f"{result['editable_gaussians']} editable ({result['seeded_gaussians']} seeded); the edit's copy of its "
               f"base {result['base_copy_bytes'] / 1e6:.2f} MB; checkpoint {result['ratio']:.2f}x the earlier layout's")
    harness.report(table(result) + summary, args.output)


if __name__ == "__main__":
    main()
