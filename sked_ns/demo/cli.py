"""`sked-demo`'s command line, parsed before the demo's renderers and trainers are imported."""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path
from typing import List, Optional

from sked_ns.demo import BASES
from sked_ns.errors import ArgumentParser, DefaultsHelpFormatter


def demo_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="sked-demo", formatter_class=DefaultsHelpFormatter,
                            description="A real SKED edit of the embedded demo scene (a sphere gets a hat from two "
                                        "sketches), end to end, on the CPU or a GPU; reports the paper's metrics. "
                                        "Run again with the same --output, it reuses the fitted base and continues "
                                        "an interrupted edit.")
    parser.add_argument("--output", type=Path, default=Path("demo_output"), help="folder for everything the demo writes")
    parser.add_argument("--beta", type=float, default=0.025, help="preservation falloff, image widths")
    parser.add_argument("--size", type=int, default=128, help="size of the rendered images, pixels")
    parser.add_argument("--iterations", type=int, default=100, help="edit iterations (a rerun with more continues the "
                                                                    "edit)")
    parser.add_argument("--base-steps", type=int, default=None,
                        help="the base's fitting steps (default: 600 for nerfacto, 200 for splatfacto); a rerun "
                             "reuses a base fitted with the same")
    parser.add_argument("--prompt", default=None, help="text for Stable Diffusion guidance (needs its weights; "
                                                       "without it the demo uses reference guidance)")
    parser.add_argument("--diffusion-model", default="CompVis/stable-diffusion-v1-4",
                        help="Stable Diffusion hub id or local folder, for --prompt")
    parser.add_argument("--base", choices=BASES, default="nerfacto",
                        help="the base edited: a tiny nerfacto, or a splatfacto (Gaussian splats) fitted on the CPU")
    parser.add_argument("--device", default=None, help="torch device (default: cuda where available, else cpu)")
    return parser


def entrypoint(argv: Optional[List[str]] = None) -> None:
    from sked_ns.compat import quiet_third_party_warnings

    quiet_third_party_warnings()  # before nerfstudio is imported: its import warns
    args = demo_parser().parse_args(argv)
    import torch

    from sked_ns.demo.rerun import DemoInterrupted
    from sked_ns.demo.run import report, run

    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    try:
        summary = run(args.output, args.beta, args.size, args.iterations, args.base_steps, prompt=args.prompt,
                      diffusion_model=args.diffusion_model, device=device, base=args.base)
    except DemoInterrupted as stop:
        # Plain print: the command may hold brackets that rich would read as markup.
        again = shlex.join(["sked-demo", *(sys.argv[1:] if argv is None else argv)])
        print(f"interrupted: sked-demo stopped by Ctrl-C {stop}. Run the same command ({again}) to pick up "
              "where it stopped.", file=sys.stderr, flush=True)
        raise SystemExit(INTERRUPTED_STATUS) from None
    print(report(summary))


INTERRUPTED_STATUS = 130
"""A shell's status for a command stopped by Ctrl-C (128 + SIGINT)."""


if __name__ == "__main__":
    entrypoint()
