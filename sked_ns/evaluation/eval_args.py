"""`sked-eval`'s arguments: light to import (eval_cli.py parses them before the renderers load), and read by
sked-batch to check a plan's eval flags."""

from __future__ import annotations

import argparse
from pathlib import Path

from sked_ns.errors import ArgumentParser, DefaultsHelpFormatter

DEFAULT_CLIP = "openai/clip-vit-base-patch32"


def positive_int(text: str) -> int:
    """argparse type: a whole number >= 1 (a size or a count of views)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value}: must be at least 1")
    return value


def eval_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="sked-eval", formatter_class=DefaultsHelpFormatter,
                            description="Score an edit: the paper's metrics at its sketch views (IoS, PSNR / SSIM / "
                                        "LPIPS outside the sketches, CLIP similarity) and novel views (what it "
                                        "keeps, where it leaks, and against --target). Writes a JSON and a "
                                        "contact sheet.")
    parser.add_argument("config", type=Path, nargs="?", default=None,
                        help="the edited run's config.yml (or its run folder)")
    parser.add_argument("--load-config", type=Path, default=None,
                        help="the same, as nerfstudio's ns-eval / ns-render take it")
    parser.add_argument("--base", type=Path, default=None, help="base run folder (default: the one the edit used)")
    parser.add_argument("--sketches", type=Path, default=None, help="sketch set (default: the one the edit used)")
    parser.add_argument("--output", type=Path, default=None,
                        help="metrics JSON to write (default: sked_eval.json in the edit's run folder)")
    parser.add_argument("--sheet", type=Path, default=None, help="contact sheet PNG (default: next to --output)")
    parser.add_argument("--overwrite", action="store_true", help="replace an earlier --output / --sheet")
    parser.add_argument("--resolution", type=positive_int, default=256, help="longer side of the sketch-view renders")
    parser.add_argument("--device", default=None, help="torch device (default: cuda where available, else cpu)")
    parser.add_argument("--prompt", default=None, help="prompt for CLIP similarity (default: the edit's)")
    parser.add_argument("--clip-model", default=None, help=f"CLIP hub id (cached) or local folder (default {DEFAULT_CLIP})")
    parser.add_argument("--clip-views", type=positive_int, default=40, help="views around the edit for CLIP similarity")
    parser.add_argument("--clip-resolution", type=positive_int, default=128, help="render size of those views")
    parser.add_argument("--cameras", default=None,
                        help="novel views: 'eval' (the base dataset's eval split; the default), 'orbit[:N]' around the "
                             "edit box, a camera file in the base's data frame (nerfstudio-data transforms.json, "
                             "Blender transforms_<split>.json, or their folder), or 'none'")
    parser.add_argument("--target", type=Path, default=None,
                        help="ground truth of the intended result (a camera file as for --cameras, with its images): "
                             "scored at its own cameras (instead of --cameras) inside and outside the changed region")
    parser.add_argument("--novel-resolution", type=positive_int, default=256, help="longer side of the novel-view renders")
    parser.add_argument("--max-novel-views", type=positive_int, default=12, help="at most this many novel views (evenly spread)")
    return parser
