"""The mapper's state directory: the graph state file and the version lease, both written atomically.

Two files, each replaced whole (write a temp file, fsync it, ``os.replace``, fsync the directory):

* ``mapper_state.msgpack``: everything a restart needs to resume the graph (node ids, version, node
  clouds, point map), saved at most once per ``save_period_s``. A msgpack map starting with a magic
  string, checked on load; a corrupt file is moved aside (``.corrupt``) and the mapper starts empty.
* ``mapper_lease.json``: a few bytes, the **version lease** (:class:`Lease`): the epoch, and a ceiling on
  the versions and node ids the mapper may use. It is extended by a block *before* a version or id
  beyond it is committed, so a mapper killed at any moment (between saves, during a write) has never
  published anything beyond the lease on disk. A restart after such a kill resumes the last saved graph
  at a version above the lease and allocates ids above it: versions never go back and an id never
  names another object, within the epoch (see :func:`resume`).

Temp files left by a kill during a write (``.mapper_state.*.tmp``, ``.mapper_lease.*.tmp``) are removed
at start (:func:`remove_stale_temps`). One mapper per state directory.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import secrets
import tempfile
from pathlib import Path
from typing import Any

import msgpack

log = logging.getLogger(__name__)

MAGIC = "ARGUS-MAPPER-STATE"
FILE_NAME = "mapper_state.msgpack"
LEASE_NAME = "mapper_lease.json"
LEASE_MAGIC = "ARGUS-MAPPER-LEASE"
TEMP_PATTERNS = (".mapper_state.*.tmp", ".mapper_lease.*.tmp")
VERSION_BLOCK = 1000
"""Versions reserved per lease write (a delta is one version: at 10 per second, one small write per 100 s)."""
ID_BLOCK = 1000
"""Node ids reserved per lease write. An unclean restart skips at most one block of each."""


def new_epoch() -> str:
    """A fresh random epoch: 16 hex digits."""
    return secrets.token_hex(8)


@dataclasses.dataclass(frozen=True)
class Lease:
    """What the mapper may use without writing again: versions ``<= version`` and node id numbers
    ``< next_id`` of ``epoch``. ``clean``: written at a clean stop right after the final state save, so
    the state holds exactly the last version published (a restart resumes it without a jump)."""

    epoch: str
    version: int
    next_id: int
    clean: bool = False

    def covers(self, version: int, next_id: int) -> bool:
        """Whether committing ``version`` with ids below ``next_id`` stays within the lease."""
        return version <= self.version and next_id <= self.next_id

    def extended(self, version: int, next_id: int) -> Lease:
        """The next lease: one block beyond ``version`` and ``next_id``."""
        return Lease(self.epoch, version + VERSION_BLOCK, next_id + ID_BLOCK)


@dataclasses.dataclass(frozen=True)
class Resume:
    """Where a starting mapper goes on: its epoch, the version of its first graph and its next node id."""

    epoch: str
    version: int
    next_id: int
    why: str


def resume(state_version: int | None, state_next_id: int | None, lease: Lease | None) -> Resume:
    """Where to go on from a loaded state (None: none) and lease (None: none or unreadable). Pure.

    * no lease: a new epoch (nothing says which versions and ids the last life used), the state as saved;
    * a clean lease whose version is the state's: the same epoch and version (nothing was lost);
    * otherwise (a kill, a lost state file): the same epoch, one version beyond the lease and ids from its
      ceiling; the restored graph is published as a version no one has seen.
    """
    version, next_id = state_version or 0, state_next_id or 1
    if lease is None:
        return Resume(new_epoch(), version, next_id, "no version lease: a new epoch")
    if lease.clean and state_version == lease.version:
        return Resume(lease.epoch, version, max(next_id, lease.next_id), "clean stop: resumed exactly")
    return Resume(
        lease.epoch, max(version, lease.version) + 1, max(next_id, lease.next_id),
        "unclean stop or lost state: versions and ids continue above the lease",
    )


def state_path(state_dir: Path) -> Path:
    return Path(state_dir) / FILE_NAME


def lease_path(state_dir: Path) -> Path:
    return Path(state_dir) / LEASE_NAME


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return  # not every platform opens directories; the rename itself is still atomic
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _write_atomic(target: Path, data: bytes, prefix: str) -> None:
    """Replace ``target`` by ``data`` all at once; on any failure the old file is left as it was."""
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=prefix, suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    _fsync_dir(target.parent)


def save_state(state_dir: Path, state: dict[str, Any]) -> Path:
    """Write ``state`` to ``state_dir`` atomically; returns the file's path."""
    target = state_path(Path(state_dir))
    _write_atomic(target, msgpack.packb({"magic": MAGIC, **state}, use_bin_type=True), ".mapper_state.")
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
        try:
            os.replace(path, aside)
        except OSError as e2:
            log.error("cannot move %s aside: %s", path, e2)
        return None


def write_lease(state_dir: Path, lease: Lease) -> None:
    """Persist ``lease`` (atomic, fsynced) before anything it allows is used; raises OSError."""
    body = {"magic": LEASE_MAGIC, **dataclasses.asdict(lease)}
    _write_atomic(lease_path(Path(state_dir)), json.dumps(body).encode(), ".mapper_lease.")


def read_lease(state_dir: Path) -> Lease | None:
    """The lease on disk, or None when there is none or it is unreadable (logged)."""
    path = lease_path(Path(state_dir))
    if not path.is_file():
        return None
    try:
        d = json.loads(path.read_bytes())
        if not isinstance(d, dict) or d.get("magic") != LEASE_MAGIC:
            raise ValueError("not an Argus mapper lease")
        epoch, version, next_id, clean = d["epoch"], d["version"], d["next_id"], d.get("clean", False)
        if not (isinstance(epoch, str) and 0 < len(epoch) <= 64 and isinstance(version, int) and version >= 0
                and isinstance(next_id, int) and next_id >= 1 and isinstance(clean, bool)):
            raise ValueError(f"bad lease fields {d!r}")
        return Lease(epoch, version, next_id, clean)
    except Exception as e:  # noqa: BLE001 - an unreadable lease means a new epoch, never a crash
        log.error("version lease %s is unreadable (%s); the mapper starts a new epoch", path, e)
        return None


def remove_stale_temps(state_dir: Path) -> int:
    """Remove temp files a killed mapper left in ``state_dir``; returns how many were removed."""
    state_dir = Path(state_dir)
    removed = 0
    if not state_dir.is_dir():
        return 0
    for pattern in TEMP_PATTERNS:
        for p in state_dir.glob(pattern):
            try:
                p.unlink()
                removed += 1
            except OSError as e:
                log.warning("cannot remove stale temp file %s: %s", p, e)
    if removed:
        log.info("removed %d temp file(s) left in %s by an interrupted save", removed, state_dir)
    return removed
