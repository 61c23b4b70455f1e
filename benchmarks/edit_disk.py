"""What edits cost on disk: N edits of one base made into one output folder, as `ns-train sked` makes them.

    python benchmarks/edit_disk.py [--edits 10] [--bases nerfacto-default,instant-ngp,splatfacto] [--fields local] [--workdir DIR]

Each base is the demo scene fitted briefly at the method's own default size (nerfacto's hash table 2^19, as
`ns-train nerfacto` builds it; instant-ngp's; the demo's splatfacto fit), since what an edit stores follows the
base's architecture, not how well it is trained. Every edit is a 2-iteration reference edit with the demo sketches,
saved once at its end. Per edit: its checkpoint, its run folder (its copy of the base included, as `du
--apparent-size` counts a folder alone) and what it added to the output folder's disk (each file counted once however
many hard links name it, as a file system stores it). NeRF bases are edited both ways the edit can train
(`--pipeline.model.nerf-edit-field`): "full-copy" (a trainable copy of the whole field, what earlier versions did)
and "local" (the residual over the edit box). "without sharing" is the output folder with every link counted as its
own file: what earlier versions wrote, each edit holding its own copy of the base's weights. A run over some of the
bases keeps the other bases' rows already in the output file.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import Dict, List, Optional

import harness

ITERATIONS = 2
BASE_STEPS = 2
"""A base's fit: its architecture sets what an edit stores, not its training."""
BASES = {"nerfacto-default": "nerfacto", "instant-ngp": "instant-ngp", "splatfacto": "splatfacto"}


def disk(folder: Path, shared: bool = True) -> int:
    """Bytes of the files under `folder`; `shared`: a file with several hard links counted once."""
    seen, total = set(), 0
    for path in folder.rglob("*"):
        if not path.is_file() or path.is_symlink():
            continue
        stat = path.stat()
        if shared and (stat.st_dev, stat.st_ino) in seen:
            continue
        seen.add((stat.st_dev, stat.st_ino))
        total += stat.st_size
    return total


def edit(base: Path, work: Path, output: Path, field: Optional[str]) -> Path:
    from sked_ns.engine.edit_run import edit_config, run_edit
    from sked_ns.method.options import without_lpips

    config = edit_config(base, work / "data", work / "sketches", output, iterations=ITERATIONS,
                         steps_per_save=ITERATIONS, guidance_resolution=16, silhouette_resolution=16)
    if field is not None:
        config.pipeline.model.nerf_edit_field = field
    with without_lpips():
        return run_edit(config).base_dir


def measure_base(name: str, work: Path, edits: int, fields: List[str]) -> List[Dict]:
    method = BASES[name]
    base = harness.demo_base(work, method, steps=BASE_STEPS, grid_passes=1)
    rows = []
    for field in (fields if method != "splatfacto" else (None,)):
        output = work / "edits" / name / (field or "splat")
        runs, added, before = [], [], 0
        for _ in range(edits):
            runs.append(edit(base, work, output, field))
            now = disk(output)
            added.append(now - before)
            before = now
        checkpoint = sorted((runs[0] / "nerfstudio_models").glob("step-*.ckpt"))[-1]
        rows.append({
            "base": name, "edit_field": field or "splat changes", "edits": edits,
            "base_checkpoint_bytes": sorted((base / "nerfstudio_models").glob("*.ckpt"))[-1].stat().st_size,
            "checkpoint_bytes": checkpoint.stat().st_size, "run_folder_bytes": disk(runs[0], shared=False),
            "first_edit_adds_bytes": added[0], "next_edit_adds_bytes": max(added[1:] or [0]),
            "all_edits_bytes": disk(output), "all_edits_without_sharing_bytes": disk(output, shared=False),
        })
        print(table(rows[-1:]), flush=True)
    return rows


def table(rows: List[Dict]) -> str:
    mb = lambda value: f"{value / 1e6:.1f}"  # noqa: E731
    return harness.markdown_table(
        ["base", "edit trains", "base ckpt (MB)", "edit ckpt (MB)", "run folder (MB)", "1st edit adds (MB)",
         "next edit adds (MB)", "N edits (MB)", "N edits without sharing (MB)", "N"],
        [[row["base"], row["edit_field"], mb(row["base_checkpoint_bytes"]), mb(row["checkpoint_bytes"]),
          mb(row["run_folder_bytes"]), mb(row["first_edit_adds_bytes"]), mb(row["next_edit_adds_bytes"]),
          mb(row["all_edits_bytes"]), mb(row["all_edits_without_sharing_bytes"]), row["edits"]] for row in rows])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--edits", type=int, default=10, help="edits of each base into one output folder")
    parser.add_argument("--bases", default=",".join(BASES), help=f"comma-separated, of {', '.join(BASES)}")
    parser.add_argument("--workdir", type=Path, default=None, help="kept, so a rerun reuses its bases")
    parser.add_argument("--fields", default="full-copy,local", help="how NeRF edits train, comma-separated")
    parser.add_argument("--output", type=Path, default=harness.RESULTS / "edit_disk.json")
    args = parser.parse_args()
    unknown = set(args.bases.split(",")) - set(BASES)
    if unknown or args.edits < 1:
        parser.error(f"--bases: one or more of {', '.join(BASES)}; --edits: at least 1")
    harness.claim("edit_disk.py", args.output, args.workdir)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    measured = args.bases.split(",")
    earlier = json.loads(args.output.read_text())["rows"] if args.output.exists() else []
    rows = [row for row in earlier if row["base"] not in measured]
    with harness.work_folder(args.workdir) as work:
        harness.demo_scene(work, rewrite=False)
        for name in measured:
            rows += measure_base(name, work, args.edits, args.fields.split(","))
    harness.write_results(args.output, {"iterations": ITERATIONS, "base_steps": BASE_STEPS, "rows": rows,
                                        "environment": harness.environment("cpu")})
    harness.report(table(rows), args.output)


if __name__ == "__main__":
    main()
