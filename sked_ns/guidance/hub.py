"""The Hugging Face hub as a user reaches it: the download command their huggingface_hub installs.

Recent huggingface_hub releases install `hf`, older ones `huggingface-cli`, so advice naming either may name a
command the user's environment lacks; the installed distribution's own console scripts say which it has.
"""

from __future__ import annotations

import importlib.metadata
import shlex
from typing import Optional

CLIS = ("hf", "huggingface-cli")
"""The hub's command-line tools, newest first; both take `download <repo id> [--local-dir DIR]`."""


def hub_cli() -> str:
    """The hub command this environment's huggingface_hub installs (`hf` where it cannot be told)."""
    try:
        scripts = {entry.name for entry in importlib.metadata.distribution("huggingface_hub").entry_points
                   if entry.group == "console_scripts"}
    except importlib.metadata.PackageNotFoundError:
        return CLIS[0]
    return next((name for name in CLIS if name in scripts), CLIS[0])


def download_command(repo_id: str, local_dir: Optional[str] = None) -> str:
    """The shell command that downloads `repo_id` once (into the hub cache, or `local_dir`)."""
    words = [hub_cli(), "download", repo_id] + (["--local-dir", local_dir] if local_dir else [])
    return shlex.join(words)
