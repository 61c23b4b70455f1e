"""The speed/accuracy trade, measured: presets, a sweep over the main knobs, and the ablations.

    python benchmarks/speed_accuracy.py            # about 2.5 hours on a 2-core CPU (100-iteration edits, ~2 s a step)
    python benchmarks/speed_accuracy.py --quick    # one scene, a few iterations (a smoke run)

Every run is a real `ns-train sked` edit of a tiny nerfacto base of the demo sphere with
reference guidance towards a known target (demo_scene.SCENES: hat, handle, antenna), so
quality is measured, not judged: Intersection-over-Sketch and PSNR outside the sketches
(against the base) and PSNR inside the sketches against the known target, on every sketch
view. Each run is its own process so its peak memory (max RSS; CUDA: max allocated) is its own.

On a CPU the paper's protocol (10,000 iterations at 128 px) would take days, so the CPU
protocol divides iterations by 100 and render sizes by 4; the table says which protocol ran.
Writes benchmarks/results/speed_accuracy.json and speed_accuracy.png (time vs quality,
Pareto front marked).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import harness
import numpy as np
from harness import commit, sync

ITERATION_DIVISOR = {"cpu": 100, "cuda": 1}
RESOLUTION_DIVISOR = {"cpu": 4, "cuda": 1}
EVAL_SIZE = 48
SCENE_NAMES = ("hat", "handle", "antenna")


def plan(device: str, quick: bool) -> list[dict]:
    """Every run: a name, its group, scene, knob values and base (hash-grid size)."""
    from sked_ns.engine.presets import PRESETS, read_preset

    divide_iterations, divide_resolution = ITERATION_DIVISOR[device], RESOLUTION_DIVISOR[device]

    def knobs(preset_name: str, **changes) -> dict:
        preset = read_preset(preset_name)
        values = {
            "iterations": max(1, preset["iterations"] // divide_iterations),
            "guidance_resolution": preset["model"]["guidance_resolution"] // divide_resolution,
            "silhouette_resolution": preset["model"]["silhouette_resolution"] // divide_resolution,
            "samples_per_ray_scale": preset["model"]["samples_per_ray_scale"],
            "edit_box_warmup": max(1, preset["model"]["edit_box_warmup"] // divide_iterations),
            "mixed_precision": device == "cuda" and preset["mixed_precision"],
            "ablation": "none",
            "log2_hashmap_size": 15,
        }
        values.update(changes)
        return values

    if quick:
        return [{"name": "sked-fast", "group": "preset", "scene": "hat", **knobs("sked-fast", iterations=4)}]
    runs = [{"name": name, "group": "preset", "scene": scene, **knobs(name)} for name in PRESETS for scene in SCENE_NAMES]
    runs += [{"name": ablation, "group": "ablation", "scene": scene, **knobs("sked", ablation=ablation)}
             for ablation in ("no-preserve", "no-silhouette", "text-only") for scene in SCENE_NAMES]
    default = knobs("sked")
    sweep = {
        "guidance_resolution": [default["guidance_resolution"] // 2, default["guidance_resolution"] * 2],
        "samples_per_ray_scale": [0.5, 2.0],
        "iterations": [default["iterations"] // 2, default["iterations"] * 2],
        "mixed_precision": [not default["mixed_precision"]],
        "log2_hashmap_size": [13, 17],
    }
    for knob, values in sweep.items():
        for value in values:
            changes = {knob: value}
            if knob == "guidance_resolution":
                changes["silhouette_resolution"] = value
            if knob == "iterations":
                changes["edit_box_warmup"] = max(1, value // 10)
            runs.append({"name": f"{knob}={value}", "group": "sweep", "scene": "hat", **knobs("sked", **changes)})
    return runs


def prepare(workdir: Path, hash_sizes, base_steps: int = 400) -> dict:
    """The demo dataset, one tiny base per hash-grid size, and the three scenes' sketch sets."""
    from sked_ns.demo.base import TinyNerfacto, build_demo_base
    from sked_ns.demo.scenes import sphere as demo_scene
    from sked_ns.sketches.sketch_set import save_sketch_set

    data = workdir / "data"
    if not (data / "transforms.json").exists():
        demo_scene.write_demo_dataset(data)
    bases = {}
    for size in sorted(set(hash_sizes)):
        runs = workdir / f"base-{size}"
        existing = list(runs.rglob("config.yml"))
        bases[size] = existing[0].parent if existing else build_demo_base(
            data, runs, steps=base_steps, tiny=TinyNerfacto(log2_hashmap_size=size)
        )
    for name in SCENE_NAMES:
        if not (workdir / "sketches" / name / "sketches.json").exists():
            save_sketch_set(demo_scene.SCENES[name].sketch_set(size=64), workdir / "sketches" / name)
    return {"data": data, "bases": {str(k): str(v) for k, v in bases.items()}}


def run_one(run: dict, workdir: Path, prepared: dict, device: str) -> dict:
    """One edit and its measurements (called in a fresh process)."""
    import torch

    from sked_ns.demo.scenes import sphere as demo_scene
    from sked_ns.engine.edit_run import edit_config
    from sked_ns.evaluation.metrics import intersection_over_sketch, psnr_inside, psnr_outside
    from sked_ns.evaluation.render import render_at, render_base_at, resized_mask
    from sked_ns.sketches.sketch_set import load_sketch_set

    sketches = workdir / "sketches" / run["scene"]
    config = edit_config(Path(prepared["bases"][str(run["log2_hashmap_size"])]), Path(prepared["data"]), sketches,
                         workdir / "edits" / run["name"] / run["scene"], iterations=run["iterations"],
                         guidance_resolution=run["guidance_resolution"],
                         silhouette_resolution=run["silhouette_resolution"], device=device,
                         steps_per_save=10**9)
    model_config = config.pipeline.model
    model_config.guidance.target = run["scene"]
    model_config.samples_per_ray_scale = run["samples_per_ray_scale"]
    model_config.edit_box_warmup = run["edit_box_warmup"]
    model_config.ablation = run["ablation"]
    config.mixed_precision = run["mixed_precision"]
    config.set_timestamp()
    config.save_config()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    if run["mixed_precision"] and device == "cpu":
        trainer.mixed_precision = True  # nerfstudio turns autocast off on a CPU; bf16 is what a CPU has
    trainer.pipeline.prepare_guidance()  # outside the timing: loading the guidance is set-up
    sync(device)
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    start = time.perf_counter()
    trainer.train()
    sync(device)
    seconds = time.perf_counter() - start

    model = trainer.pipeline.model
    scene = demo_scene.SCENES[run["scene"]]
    data_views = load_sketch_set(sketches).views
    model_views = load_sketch_set(sketches).in_model_frame(trainer.pipeline.datamanager.dataparser_transform).views
    views = []
    for data_view, view in zip(data_views, model_views):
        edit, base, mask = render_at(model, view, EVAL_SIZE), render_base_at(model, view, EVAL_SIZE), resized_mask(view, EVAL_SIZE)
        scale = EVAL_SIZE / max(view.width, view.height)
        target = scene.render_target(data_view.camera_to_world, data_view.fl_x * scale, mask.shape[1], mask.shape[0])["rgb"]
        views.append({
            "ios": intersection_over_sketch(edit["accumulation"], mask),
            "ios_base": intersection_over_sketch(base["accumulation"], mask),
            "psnr_outside": psnr_outside(edit["rgb"], base["rgb"], mask),
            "psnr_target_inside": psnr_inside(edit["rgb"], target, mask),
        })
    peak = torch.cuda.max_memory_allocated() / 2**20 if device == "cuda" else harness.peak_rss_gb() * 1024
    return {
        **run,
        "seconds_total": seconds,
        "ms_per_iteration": 1000 * seconds / run["iterations"],
        "peak_memory_mb": peak,
        "skipped_steps": trainer.skipped_steps,
        **{key: float(np.mean([v[key] for v in views])) for key in views[0]},
        "views": views,
    }


def pareto(points: list[tuple[float, float]]) -> list[bool]:
    """Which (time, quality) points no other point beats on both (less time, more quality)."""
    return [not any(t2 <= t and q2 >= q and (t2, q2) != (t, q) for t2, q2 in points) for t, q in points]


def summarise(results: list[dict]) -> list[dict]:
    """Mean over scenes per configuration; the sweep (hat only) gets the default preset on hat as its centre."""
    rows = {}
    for result in results:
        rows.setdefault((result["group"], result["name"]), []).append(result)
    if any(group == "sweep" for group, _ in rows):
        rows[("sweep", "sked @ hat (sweep centre)")] = [
            r for r in results if r["group"] == "preset" and r["name"] == "sked" and r["scene"] == "hat"]
    summary = []
    for (group, name), runs in rows.items():
        summary.append({
            "group": group, "name": name, "scenes": [r["scene"] for r in runs],
            **{key: runs[0][key] for key in ("iterations", "guidance_resolution", "samples_per_ray_scale",
                                             "mixed_precision", "log2_hashmap_size", "ablation")},
            **({"note": runs[0]["note"]} if "note" in runs[0] else {}),
            **{key: float(np.mean([r[key] for r in runs])) for key in
               ("seconds_total", "ms_per_iteration", "peak_memory_mb", "ios", "ios_base", "psnr_outside",
                "psnr_target_inside")},
        })
    # Quality for the front: IoS (the edit happened) x PSNR outside (nothing else changed) would mix
    # units; the target PSNR inside the sketch measures both shape and colour of the edit.
    # Rows carried over from an older commit (a note) are not compared: that code ran at another speed.
    current = [row for row in summary if "note" not in row]
    for row in summary:
        row["pareto"] = False
    for row, on_front in zip(current, pareto([(r["seconds_total"], r["psnr_target_inside"]) for r in current])):
        row["pareto"] = on_front
    return summary


def plot(summary: list[dict], path: Path, label: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(7, 4.5))
    colours = {"preset": "tab:blue", "sweep": "tab:gray", "ablation": "tab:red"}
    for row in summary:
        axis.scatter(row["seconds_total"], row["psnr_target_inside"], color=colours[row["group"]],
                     edgecolor="black" if row["pareto"] else "none", s=60 if row["group"] == "preset" else 30, zorder=3)
        axis.annotate(row["name"], (row["seconds_total"], row["psnr_target_inside"]), fontsize=7,
                      xytext=(4, 3), textcoords="offset points")
    front = sorted((r["seconds_total"], r["psnr_target_inside"]) for r in summary if r["pareto"])
    axis.plot(*zip(*front), color="black", linewidth=0.8, zorder=2, label="Pareto front")
    for group, colour in colours.items():
        axis.scatter([], [], color=colour, label=group)
    axis.set_xscale("log")
    axis.set_xlabel("edit time (s, log scale)")
    axis.set_ylabel("PSNR inside the sketches vs the known target (dB)")
    axis.set_title(label, fontsize=9)
    axis.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=120)


def table(summary: list[dict]) -> str:
    return harness.markdown_table(
        ["run", "group", "its", "px", "spr", "mp", "hash", "s total", "ms/it", "peak MB", "IoS", "PSNR out",
         "PSNR target", "front"],
        [[r["name"] + (f" ({r['note']})" if "note" in r else ""), r["group"], r["iterations"], r["guidance_resolution"],
          f"{r['samples_per_ray_scale']:g}", "on" if r["mixed_precision"] else "off", f"2^{r['log2_hashmap_size']}",
          f"{r['seconds_total']:.1f}", f"{r['ms_per_iteration']:.0f}", f"{r['peak_memory_mb']:.0f}", f"{r['ios']:.3f}",
          f"{r['psnr_outside']:.1f}", f"{r['psnr_target_inside']:.1f}", "*" if r["pareto"] else ""] for r in summary])


def write_partial(output: Path, results: list[dict]) -> None:
    harness.write_results(output.with_suffix(".partial.json"), {"commit": commit(), "runs": results})


def carried_over(older: dict, names: list[str], source: str) -> list[dict]:
    """The older results' runs called `names`, each marked with where it was measured; a row already carried
    over once keeps its own mark (the commit it was measured at, not the file it last passed through)."""
    return [{**run, "note": run.get("note") or f"not re-measured: from {source} ({older.get('commit', 'older run')})"}
            for run in older["runs"] if run["name"] in names]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="one scene, 4 iterations (a smoke run)")
    parser.add_argument("--output", type=Path, default=harness.RESULTS / "speed_accuracy.json")
    parser.add_argument("--workdir", type=Path, default=None, help="keep bases and edits here (default: a temp dir)")
    parser.add_argument("--replot", action="store_true", help="rebuild summary, table and plot from --output's runs")
    parser.add_argument("--skip", action="append", default=[], metavar="NAME",
                        help="leave out the runs called NAME (repeatable); with --keep-from their older rows are kept")
    parser.add_argument("--keep-from", type=Path, default=None,
                        help="an older results JSON: its runs of the --skip names are carried over, marked as older")
    parser.add_argument("--only", action="append", default=[], metavar="NAME", help="run only these runs (repeatable)")
    parser.add_argument("--scene", action="append", default=[], choices=SCENE_NAMES, help="run only on these scenes")
    parser.add_argument("--run", help=argparse.SUPPRESS)  # internal: one run, JSON in and out
    args = parser.parse_args()

    import torch

    if args.replot:
        data = json.loads(args.output.read_text())
        data["summary"] = summarise(data["runs"])
        label = f"{data['protocol']}\n{data['machine']}; reference guidance, tiny demo scenes"
        harness.write_results(args.output, data)
        plot(data["summary"], args.output.with_suffix(".png"), label)
        print(table(data["summary"]))
        return

    device = "cuda" if torch.cuda.is_available() else "cpu"
    if args.run:
        request = json.loads(args.run)
        result = run_one(request["run"], Path(request["workdir"]), request["prepared"], device)
        print("RESULT " + json.dumps(result))
        return
    harness.claim("speed_accuracy.py", args.output, args.workdir)

    runs = [run for run in plan(device, args.quick) if run["name"] not in args.skip
            and (not args.only or run["name"] in args.only) and (not args.scene or run["scene"] in args.scene)]
    kept = []
    if args.keep_from is not None:
        kept = carried_over(json.loads(args.keep_from.read_text()), args.skip, args.keep_from.name)
    with harness.work_folder(args.workdir) as workdir:
        prepared = prepare(workdir, [run["log2_hashmap_size"] for run in runs], base_steps=60 if args.quick else 400)
        prepared = {"data": str(prepared["data"]), "bases": prepared["bases"]}
        results = []
        for index, run in enumerate(runs):
            request = json.dumps({"run": run, "workdir": str(workdir), "prepared": prepared})
            process = subprocess.run([sys.executable, __file__, "--run", request], capture_output=True, text=True)
            lines = [line for line in process.stdout.splitlines() if line.startswith("RESULT ")]
            if process.returncode != 0 or not lines:
                raise RuntimeError(f"run {run['name']} on {run['scene']} failed:\n{process.stderr[-4000:]}")
            results.append(json.loads(lines[-1][len("RESULT "):]))
            r = results[-1]
            write_partial(args.output, results)  # an interrupted benchmark keeps what it measured
            print(f"[{index + 1}/{len(runs)}] {run['name']:>26} {run['scene']:>8}: {r['seconds_total']:6.1f} s, "
                  f"IoS {r['ios']:.3f}, PSNR out {r['psnr_outside']:.1f}, target {r['psnr_target_inside']:.1f}", flush=True)

    results += kept
    summary = summarise(results)
    protocol = (f"{'CPU' if device == 'cpu' else 'GPU'} protocol: iterations / {ITERATION_DIVISOR[device]}, "
                f"render sizes / {RESOLUTION_DIVISOR[device]} of each preset")
    environment = harness.environment(device)
    machine = environment["device"] if device == "cuda" else \
        f"{environment['machine']}, {environment['torch_threads']} threads, no GPU"
    label = f"{protocol}\n{machine}; reference guidance, tiny demo scenes"
    harness.write_results(args.output, {"protocol": protocol, "machine": machine, "device": device, "quick": args.quick,
                                        "commit": environment["commit"], "environment": environment,
                                        "summary": summary, "runs": results})
    plot(summary, args.output.with_suffix(".png"), label)
    args.output.with_suffix(".partial.json").unlink(missing_ok=True)  # superseded by the full results
    print(label.replace("\n", "; "))
    harness.report(table(summary), args.output, args.output.with_suffix(".png"))


if __name__ == "__main__":
    main()
