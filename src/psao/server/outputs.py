"""Output files: the path is checked before any work starts, the content is written to a temporary file
in the same folder and renamed into place, so a failure (full disk, read-only folder) leaves nothing
partial behind and is reported as one line (ConfigError)."""
from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

from psao.server.errors import ConfigError


def check_output_path(path: Path | str, suffix: str) -> Path:
    """The real path `path` names, after checking that a file with this suffix can be created there (its
    folder is created if missing). Raises ConfigError naming the problem."""
    path = Path(path)
    real = path.resolve()
    if real.exists() and not real.is_file():
        raise ConfigError(f"output {path}: {'is a folder' if real.is_dir() else 'is not a regular file'}")
    if path.suffix.lower() != suffix:  # (numpy would append it and write another file than the one named)
        raise ConfigError(f"output {path}: the name must end in {suffix}")
    folder = real.parent
    for above in (folder, *folder.parents):
        if above.exists():
            if not above.is_dir():
                raise ConfigError(f"output {path}: {above} is not a folder")
            break
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=f".{real.name}.", suffix=".probe"):
            pass
    except OSError as exc:
        raise ConfigError(f"output {path}: cannot write in {folder}: {exc.strerror or exc}") from None
    return real


def write_atomically(path: Path, write: Callable[[BinaryIO], None]) -> Path:
    """`write(file)` into a temporary file beside `path`, flushed to disk, then renamed to `path`."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        raise ConfigError(f"cannot write {path}: {exc.strerror or exc}") from None
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path
