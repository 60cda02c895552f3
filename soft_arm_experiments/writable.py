"""Whether a command may write where it was told to, checked before anything runs."""
from __future__ import annotations

import os
import tempfile


def writable_directory(path: str) -> str | None:
    """Create ``path`` (and its parents) if needed and check that files can be written in it; what
    is wrong, or None."""
    try:
        os.makedirs(path, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path):
            pass
    except OSError as exc:
        return f"cannot write there ({exc.strerror or exc})"
    return None
