"""Where the user commands find the repository's own files (config, docs, scripts) and the shared
data next to it: one definition for every tool."""

from __future__ import annotations

import os
import subprocess

# The real path: catkin's workspace reaches the package through a symlink.
REPO = os.path.normpath(os.path.join(os.path.dirname(os.path.realpath(__file__)), "..", "..", ".."))
CONFIG_DIR = os.path.join(REPO, "config")
SHARED_DATA = os.path.normpath(os.path.join(REPO, "..", "shared", "data"))


def git_commit() -> str | None:
    """The code's git commit (with ``+`` when the working tree has changes), when known."""
    try:
        head = subprocess.run(
            ["git", "-C", REPO, "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            timeout=10,
        )
        dirty = subprocess.run(
            ["git", "-C", REPO, "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=10,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    if head.returncode != 0:
        return None
    return head.stdout.strip() + ("+" if dirty.stdout.strip() else "")
