"""Saving and loading the mapper's state file, atomically (write a temp file, fsync, ``os.replace``).

The file is a msgpack map starting with a magic string and a format number, checked on load, so a
restarted mapper resumes the same graph (node ids, version, node clouds, point map). A corrupt file is
moved aside (``.corrupt``) and the mapper starts empty rather than crash.
"""

from __future__ import annotations

import logging
import os
import tempfile
from pathlib import Path
from typing import Any

import msgpack

log = logging.getLogger(__name__)

MAGIC = "ARGUS-MAPPER-STATE"
FILE_NAME = "mapper_state.msgpack"


def state_path(state_dir: Path) -> Path:
    return Path(state_dir) / FILE_NAME


def save_state(state_dir: Path, state: dict[str, Any]) -> Path:
    """Write ``state`` to ``state_dir`` atomically; returns the file's path."""
    state_dir = Path(state_dir)
    state_dir.mkdir(parents=True, exist_ok=True)
    target = state_path(state_dir)
    data = msgpack.packb({"magic": MAGIC, **state}, use_bin_type=True)
    fd, tmp = tempfile.mkstemp(prefix=".mapper_state.", suffix=".tmp", dir=state_dir)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return target


def load_state(state_dir: Path) -> dict[str, Any] | None:
    """The saved state, or None when there is none or it is unreadable (then moved aside)."""
    path = state_path(Path(state_dir))
    if not path.is_file():
        return None
    try:
        state = msgpack.unpackb(path.read_bytes(), raw=False, strict_map_key=False)
        if not isinstance(state, dict) or state.get("magic") != MAGIC:
            raise ValueError("not an Argus mapper state file")
        state.pop("magic")
        return state
    except Exception as e:  # noqa: BLE001 - any unreadable file: keep it for inspection, start afresh
        aside = path.with_suffix(".corrupt")
        log.error("state file %s is unreadable (%s); moved to %s, starting empty", path, e, aside)
        os.replace(path, aside)
        return None
