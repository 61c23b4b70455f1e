"""Where a user reads a page of the guide (docs/): the copy installed with the package, else the source tree's.

Messages and --help name the page by a path that exists on the user's machine, not a path inside a repository
an installed user may not have.
"""

from __future__ import annotations

from pathlib import Path

PACKAGE = Path(__file__).resolve().parent


def guide(page: str) -> str:
    """The readable path of docs/`page` (e.g. "batch.md") here."""
    for folder in (PACKAGE / "docs", PACKAGE.parent / "docs"):  # installed (package data), or a source checkout
        if (folder / page).is_file():
            return str(folder / page)
    return f"docs/{page} of the sked_ns sources"
