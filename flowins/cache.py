"""Where flowins keeps what it computes once: simulated recordings, flow pairs."""
from __future__ import annotations

import os
from pathlib import Path


def cache_root() -> Path:
    """``$FLOWINS_CACHE``, default ``~/.cache/flowins``."""
    return Path(os.environ.get("FLOWINS_CACHE", Path.home() / ".cache" / "flowins"))
