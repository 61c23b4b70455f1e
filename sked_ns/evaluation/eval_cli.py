"""`sked-eval`'s command line, parsed before the renderers are imported (so --help is quick and quiet).

The paper's protocol on an edited run's sketch views, and the same edit from other views (evaluate.py).
"""

from __future__ import annotations

import argparse
import sys
from typing import List, Optional

from sked_ns.evaluation.eval_args import eval_parser


def parse(argv: Optional[List[str]] = None) -> argparse.Namespace:
    parser = eval_parser()
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    if (args.config is None) == (args.load_config is None):
        parser.error("give the edited run once: its config.yml (or run folder), or --load-config config.yml")
    args.config = args.config if args.config is not None else args.load_config
    if args.device is None:
        import torch

        args.device = "cuda" if torch.cuda.is_available() else "cpu"
    return args


def entrypoint(argv: Optional[List[str]] = None) -> None:
    from sked_ns.compat import quiet_third_party_warnings
    from sked_ns.errors import show_warnings_as_lines

    quiet_third_party_warnings()  # before nerfstudio is imported: its import warns
    show_warnings_as_lines()
    args = parse(argv)
    from sked_ns.evaluation.exhaustion import MEMORY_HINT, exhaustion_as_error

    with exhaustion_as_error(f"sked-eval {args.config}", memory_fix=f"{MEMORY_HINT}, or lower --resolution, "
                             "--novel-resolution and --clip-resolution (or --clip-views and --max-novel-views)",
                             disk_fix="free space there, or pass --output and --sheet on another disk"):
        from sked_ns.evaluation.evaluate import main

        main(args)


if __name__ == "__main__":
    entrypoint()
