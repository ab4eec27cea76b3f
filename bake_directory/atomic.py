"""Atomic file output for the bake directory: write a temporary file beside the target, rename it over the
target only when writing succeeded, so a reader never sees a half-written file (pure Python)."""
from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_output(path, suffix: str = ".tmp"):
    """Yield a temporary path beside `path` (parents created); on success it replaces `path`, on any
    failure it is removed. `suffix` keeps the extension writers that look at it need (".tmp.exr")."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    os.close(fd)
    os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes it private; the result gets the usual permissions
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
