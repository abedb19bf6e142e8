"""Safe file output: every file the tool writes goes through here.

Outputs are written to a temporary file in the destination folder and renamed into
place, so a crash or an error never leaves a half-written file; ``backup`` keeps a
copy of a user's file before it is changed (profiles).
"""
from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import time
from pathlib import Path


@contextlib.contextmanager
def _temp_beside(path: Path):
    """(fd, tmp path) of a new file next to ``path``; removed again if the block fails."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        yield fd, tmp
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def atomic_write(path, writer, binary: bool = True) -> Path:
    """Call ``writer(fileobj)`` on a temp file next to ``path``, then rename onto ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with _temp_beside(path) as (fd, tmp):
        with os.fdopen(fd, "wb" if binary else "w", **({} if binary else {"encoding": "utf-8"})) as f:
            writer(f)
        # mkstemp makes 0600 files; give the result the mode a plain open() would (or keep
        # the mode of the file being replaced) so users' outputs stay readable by others.
        os.chmod(tmp, path.stat().st_mode & 0o7777 if path.exists() else 0o666 & ~_umask())
        os.replace(tmp, path)
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


def replace_user_file(path, data: bytes) -> Path | None:
    """Replace the contents of a user's file (a profile) safely; returns the backup's path,
    or None when ``data`` equals what is there (nothing is written, no backup).

    A symlink is followed: its target is updated and the link stays a link (printer.cfg is
    often a link into a config repository). Mode and, where allowed, owner and group are
    kept; the new bytes are fsynced before the rename and the folder after it, so a power
    cut leaves either the old file or the new one. The backup sits next to the target."""
    link = Path(path)
    target = Path(os.path.realpath(link))
    old = target.read_bytes()
    if old == data:
        return None
    st = target.stat()
    bak = backup(target)
    with _temp_beside(target) as (fd, tmp):
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, st.st_mode & 0o7777)
        try:
            os.chown(tmp, st.st_uid, st.st_gid)
        except (PermissionError, AttributeError):   # not root: the file becomes the user's own
            pass
        os.replace(tmp, target)
    try:
        dfd = os.open(target.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError:
        pass
    return bak


def json_default(o):
    """``json.dumps(default=...)`` for numpy scalars/arrays and paths."""
    import numpy as np

    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")


def write_json(path, doc, indent: int = 1) -> Path:
    """Write ``doc`` as JSON atomically (numpy values allowed)."""
    import json

    return atomic_write_text(path, json.dumps(doc, indent=indent, default=json_default, allow_nan=True))


def read_json_doc(path, schema_prefix: str, kind: str, make_hint: str,
                  near: dict[str, str] | None = None) -> dict:
    """Read a calib JSON file whose ``schema`` starts with ``schema_prefix``.

    Every failure is one UserError line: missing file, unreadable JSON, or a JSON file of
    another kind (``make_hint`` says how to make the right one, e.g. "run `calib fit`";
    ``near`` maps the schema prefix of a kind a user may mistake for this one to what to
    say of it instead).
    """
    import json

    from calib.errors import UserError

    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise UserError(f"{kind} file {path} does not exist; {make_hint}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UserError(f"{path} is not a readable {kind} JSON file ({exc})") from None
    schema = str(doc.get("schema", "")) if isinstance(doc, dict) else ""
    for prefix, said in (near or {}).items():
        if schema.startswith(prefix):
            raise UserError(f"{path} {said}")
    if not isinstance(doc, dict) or not schema.startswith(schema_prefix):
        want = f"'schema: {schema_prefix}N'" if schema_prefix.endswith("/") else "calib 'schema'"
        raise UserError(f"{path} is not a calib {kind} file (no {want} key); {make_hint}")
    return doc
