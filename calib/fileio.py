"""Safe file output: every file the tool writes goes through here.

Outputs are written to a temporary file in the destination folder and renamed into
place, so a crash or an error never leaves a half-written file; ``backup`` keeps a
copy of a user's file before it is changed (profiles).
"""
from __future__ import annotations

import os
import shutil
import tempfile
import time
from pathlib import Path


def atomic_write(path, writer, binary: bool = True) -> Path:
    """Call ``writer(fileobj)`` on a temp file next to ``path``, then rename onto ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb" if binary else "w", **({} if binary else {"encoding": "utf-8"})) as f:
            writer(f)
        # mkstemp makes 0600 files; give the result the mode a plain open() would (or keep
        # the mode of the file being replaced) so users' outputs stay readable by others.
        os.chmod(tmp, path.stat().st_mode & 0o7777 if path.exists() else 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return path


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write_text(path, text: str) -> Path:
    return atomic_write(path, lambda f: f.write(text.encode("utf-8")), binary=True)


def atomic_write_bytes(path, data: bytes) -> Path:
    return atomic_write(path, lambda f: f.write(data), binary=True)


def backup(path) -> Path | None:
    """Copy ``path`` to ``path.bak-YYYYmmdd-HHMMSS`` (if it exists) and return the copy's path."""
    path = Path(path)
    if not path.exists():
        return None
    dest = path.with_name(f"{path.name}.bak-{time.strftime('%Y%m%d-%H%M%S')}")
    n = 1
    while dest.exists():
        dest = path.with_name(f"{path.name}.bak-{time.strftime('%Y%m%d-%H%M%S')}-{n}")
        n += 1
    shutil.copy2(path, dest)
    return dest
