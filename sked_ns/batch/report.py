"""One table of results (CSV and JSON, a row per job) and one contact sheet (a row per job) for a plan.

The metrics are sked-eval's (its `sked_eval.json` in each run folder: the sketch-view means, and the novel-view
means as `novel_*`); the sheet puts each job's sketch-view rows of sked-eval's own contact sheet side by side.
"""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from typing import Dict, List, Optional

from sked_ns.atomic import publish_atomically, write_text_atomically
from sked_ns.batch.plan import Plan
from sked_ns.batch.state import JobStatus, plan_status
from sked_ns.run_lock import writing

ROW_HEIGHT = 128
"""Contact-sheet row height in pixels (each job's renders are scaled to it)."""
LABEL_WIDTH = 260
SHEET_ROWS = 500
"""Jobs on the contact sheet at most (a sweep's would be an image too tall to open); the table has them all."""


def eval_metrics(run_dir: Path) -> Dict[str, object]:
    """sked-eval's means, flat: the sketch views' as named, the novel views' prefixed `novel_`."""
    try:
        result = json.loads((run_dir / "sked_eval.json").read_text())
    except (OSError, ValueError):
        return {}
    metrics = dict(result.get("mean", {}))
    for key in ("clip_similarity", "clip_similarity_base"):
        if isinstance(result.get(key), (int, float)):
            metrics[key] = result[key]
    for key, value in result.get("novel_views", {}).get("mean", {}).items():
        metrics[f"novel_{key}"] = value
    return metrics


def result_rows(plan: Plan, statuses: List[JobStatus]) -> List[Dict[str, object]]:
    rows = []
    for status in statuses:
        job = status.job
        metrics = eval_metrics(job.run_dir) if status.state == "done" else {}
        rows.append({"plan": plan.name, "edit": job.edit, "job": job.name, "prompt": job.prompt or "", "seed": job.seed,
                     "preset": job.preset, "status": status.state, "steps": status.step, "total": status.total,
                     "run": str(job.run_dir), "log": str(job.log), **metrics})
    return rows


def write_report(plan: Plan, statuses: Optional[List[JobStatus]] = None) -> Dict[str, Path]:
    """results.csv, results.json and contact_sheet.png in the plan's output folder."""
    paths = {"csv": plan.output / "results.csv", "json": plan.output / "results.json",
             "sheet": plan.output / "contact_sheet.png"}
    # One report at a time (the Slurm report job, a --local run, `sked-batch report`): the three files from one table.
    with writing(paths["csv"], "Its report is being written.", wait=True):
        statuses = plan_status(plan.jobs) if statuses is None else statuses
        rows = result_rows(plan, statuses)
        columns = list(dict.fromkeys(key for row in rows for key in row))
        table = io.StringIO()
        writer = csv.DictWriter(table, fieldnames=columns, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
        write_text_atomically(paths["csv"], table.getvalue())
        write_text_atomically(paths["json"], json.dumps({"plan": plan.name, "plan_file": str(plan.path), "jobs": rows},
                                                        indent=2))
        partial = paths["sheet"].with_name(f".{paths['sheet'].name}.partial")
        contact_sheet(statuses).save(partial, format="PNG")
        publish_atomically(partial, paths["sheet"])
    return paths


def _view_heights(result: dict) -> List[int]:
    """The height of each sketch-view row of sked-eval's sheet: each view rendered with its longer side at
    `resolution` (sked_ns.sketches.sketch_set.sketch_view_at), the rows stacked in the set's order."""
    resolution = int(result["resolution"])
    views = json.loads((Path(result["sketches"]) / "sketches.json").read_text())["views"]
    return [max(1, round(v["h"] * resolution / max(v["w"], v["h"]))) for v in views]


def _sketch_rows(run_dir: Path):
    """sked-eval's contact sheet cut to its sketch-view rows (base | edit | overlay each), side by side."""
    from PIL import Image

    try:
        heights = _view_heights(json.loads((run_dir / "sked_eval.json").read_text()))
        sheet = Image.open(run_dir / "sked_eval.png").convert("RGB")
    except (OSError, ValueError, KeyError, TypeError, ZeroDivisionError):
        return None
    if not heights or sum(heights) > sheet.height:
        return None
    strips, top = [], 0
    for height in heights:
        strip = sheet.crop((0, top, sheet.width, top + height))
        strips.append(strip.resize((max(1, round(strip.width * ROW_HEIGHT / height)), ROW_HEIGHT)))
        top += height
    row = Image.new("RGB", (sum(s.width for s in strips), ROW_HEIGHT))
    left = 0
    for strip in strips:
        row.paste(strip, (left, 0))
        left += strip.width
    return row


def _label(status: JobStatus, metrics: Dict[str, object]):
    from PIL import Image, ImageDraw

    tile = Image.new("RGB", (LABEL_WIDTH, ROW_HEIGHT), (255, 255, 255))
    lines = [status.job.name, f"{status.state}, {status.step}/{status.total or '?'} steps"]
    if status.job.prompt:
        lines.append(f'"{status.job.prompt[:36]}"')
    for key, label in (("ios", "IoS"), ("psnr_outside", "PSNR out"), ("novel_psnr_keep", "PSNR kept")):
        if isinstance(metrics.get(key), (int, float)):
            lines.append(f"{label} {metrics[key]:.3g}")
    ImageDraw.Draw(tile).multiline_text((6, 6), "\n".join(lines), fill=(0, 0, 0), spacing=4)
    return tile


def _note(text: str):
    from PIL import Image, ImageDraw

    tile = Image.new("RGB", (LABEL_WIDTH, ROW_HEIGHT), (255, 255, 255))
    ImageDraw.Draw(tile).multiline_text((6, 6), text.replace(" (", "\n("), fill=(0, 0, 0), spacing=4)
    return tile


def contact_sheet(statuses: List[JobStatus]):
    """A row per job: its name, state and metrics, then its sketch views (base | edit | overlay)."""
    from PIL import Image

    rows = []
    for status in statuses[:SHEET_ROWS]:
        renders = _sketch_rows(status.job.run_dir) if status.state == "done" else None
        label = _label(status, eval_metrics(status.job.run_dir) if renders is not None else {})
        width = LABEL_WIDTH + (renders.width if renders is not None else 0)
        row = Image.new("RGB", (width, ROW_HEIGHT), (200, 200, 200))
        row.paste(label, (0, 0))
        if renders is not None:
            row.paste(renders, (LABEL_WIDTH, 0))
        rows.append(row)
    if len(statuses) > SHEET_ROWS:
        rows.append(_note(f"... {len(statuses) - SHEET_ROWS} more jobs (results.csv lists them all)"))
    sheet = Image.new("RGB", (max(r.width for r in rows), ROW_HEIGHT * len(rows)), (200, 200, 200))
    for i, row in enumerate(rows):
        sheet.paste(row, (0, i * ROW_HEIGHT))
    return sheet
