"""The mapper's state directory at run time: resume, version lease, periodic saves and their failures.

:class:`StateKeeper` is what ``argus mapper`` does with ``--state-dir`` (file formats and the pure
resume rule are in :mod:`mapper.persistence`):

* **start**: remove temp files a kill left, load the state and the lease, go on where
  :func:`~mapper.persistence.resume` says, and write a lease ahead of the first version served;
* **before every commit** (:meth:`reserve`, the core's hook): when the version or the next node id
  would leave the lease, extend it (one small fsynced write per block) *first*;
* **saves** at most once per ``save_period_s``; a failed save (read-only directory, disk full) leaves
  the last good file untouched, counts ``save_errors``, sets the status' last error and ``degraded``,
  and is retried once per period while the mapper keeps mapping and serving from memory;
* a lease that cannot be extended (same causes) would let a later restart reuse versions, so the mapper
  goes on in a **new epoch** kept in memory only (``epoch_switches``) and tries to persist it once per
  period; consumers adopt the new epoch's snapshot (protocol.graph.GraphFollower);
* **clean stop**: a last save, then a ``clean`` lease, so the next start resumes without a version jump.

Without a state directory every start is a new epoch from version 0.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING

from mapper.persistence import (
    Lease,
    load_state,
    new_epoch,
    read_lease,
    remove_stale_temps,
    resume,
    save_state,
    write_lease,
)

if TYPE_CHECKING:
    from mapper.core import MapperCore
    from protocol.transport import Counters

log = logging.getLogger(__name__)
MIN_RETRY_S = 1.0
"""Failed writes are retried at most this often (and at most once per ``save_period_s``)."""


class StateKeeper:
    """Owns one mapper's state directory (or none). Methods run on the mapper's ingest thread."""

    def __init__(self, state_dir: Path | None, save_period_s: float, counters: Counters) -> None:
        self.state_dir = None if state_dir is None else Path(state_dir)
        self.save_period_s = save_period_s
        self.counters = counters
        self.lease: Lease | None = None  # the lease on disk for the current epoch; None: epoch not persisted
        self.last_error: str | None = None  # the newest write error (kept after recovery, for the status)
        self._failing: dict[str, str] = {}  # what is failing now ("save", "lease") -> its error
        self._saved_version: int | None = None
        self._last_save = -float("inf")  # monotonic time of the last save attempt
        self._last_lease_try = -float("inf")

    @property
    def retry_s(self) -> float:
        return max(MIN_RETRY_S, self.save_period_s)

    # -- start ---------------------------------------------------------------------------------------
    def start(self, core: MapperCore) -> str:
        """Resume ``core`` from the state directory and lease ahead; returns a line for the log."""
        if self.state_dir is None:
            core.restart_at(new_epoch(), core.version, 1)
            return f"no state directory: epoch {core.epoch} from version {core.version}"
        self.counters.add("state_temps_removed", remove_stale_temps(self.state_dir))
        state = load_state(self.state_dir)
        state_version = state_next_id = None
        if state is not None:
            try:
                core.load_state(state)
                state_version, state_next_id = core.version, core.objects.next_id
                self._saved_version = core.version
            except ValueError as e:
                log.error("cannot resume from %s: %s; starting empty", self.state_dir, e)
        r = resume(state_version, state_next_id, read_lease(self.state_dir))
        core.restart_at(r.epoch, r.version, r.next_id)
        self.lease = Lease(r.epoch, -1, 0)  # nothing reserved yet: the next reserve() writes one
        self.reserve_now(core)
        return (f"{r.why}: epoch {core.epoch}, graph version {core.version} with {len(core.store.nodes)} nodes, "
                f"next node id {core.objects.next_id}")

    def reserve_now(self, core: MapperCore) -> None:
        self.reserve(core.version + 1, core.objects.next_id, core)

    # -- lease -----------------------------------------------------------------------------------------
    def reserve(self, version: int, next_id: int, core: MapperCore) -> None:
        """Make sure ``version`` and ids below ``next_id`` are covered by a persisted lease, or else that the
        mapper is in an epoch nobody persisted (so no restart can reuse them)."""
        if self.state_dir is None:
            return
        lease = self.lease
        if lease is not None and lease.epoch == core.epoch and lease.covers(version, next_id):
            return
        now = time.monotonic()
        if lease is None and now - self._last_lease_try < self.retry_s:
            return  # in a memory-only epoch; retried once per period
        self._last_lease_try = now
        nxt = Lease(core.epoch, version, next_id).extended(version, next_id)
        try:
            write_lease(self.state_dir, nxt)
        except Exception as e:  # noqa: BLE001 - never stop mapping for the disk
            self.counters.add("lease_errors")
            self._failed("lease", f"writing the version lease to {self.state_dir} failed: {e}")
            if lease is not None:
                epoch = new_epoch()
                core.switch_epoch(epoch)
                self.lease = None
                self.counters.add("epoch_switches")
                log.error("version lease not extended: going on in epoch %s, kept in memory only, from version %d",
                          epoch, core.version)
            return
        self.lease = nxt
        self.counters.add("lease_writes")
        self._recovered("lease")

    # -- saves -----------------------------------------------------------------------------------------
    def save(self, core: MapperCore, force: bool = False) -> bool:
        """Save the state when it changed and the period is over (``force``: now); True when saved."""
        if self.state_dir is None:
            return False
        if self.lease is None:
            self.reserve_now(core)  # retry persisting the memory-only epoch first
        now = time.monotonic()
        if core.version == self._saved_version:
            return False
        period = self.retry_s if "save" in self._failing else self.save_period_s
        if not force and now - self._last_save < period:
            return False
        self._last_save = now
        version = core.version  # saves run on the ingest thread: nothing commits meanwhile
        try:
            save_state(self.state_dir, core.state())
        except Exception as e:  # noqa: BLE001 - keep serving the graph from memory, retry later
            self.counters.add("save_errors")
            self._failed("save", f"saving the graph to {self.state_dir} failed: {e}")
            return False
        self._saved_version = version
        self.counters.add("saves")
        self._recovered("save")
        return True

    def close(self, core: MapperCore) -> None:
        """A clean stop: a last save and, when it holds the last version, a clean lease (no jump next start)."""
        if self.state_dir is None:
            return
        self.save(core, force=True)
        if self.failing or self.lease is None or self._saved_version != core.version:
            return
        clean = Lease(core.epoch, core.version, core.objects.next_id, clean=True)
        try:
            write_lease(self.state_dir, clean)
            self.lease = clean
        except Exception as e:  # noqa: BLE001 - the reserved lease stays: the next start jumps, nothing lost
            self.counters.add("lease_errors")
            log.error("clean-stop lease not written (%s); the next start skips one block of versions", e)

    # -- health ----------------------------------------------------------------------------------------
    @property
    def failing(self) -> bool:
        """Whether the last save or lease write failed (the mapper reports itself ``degraded``)."""
        return bool(self._failing)

    def _failed(self, what: str, message: str) -> None:
        if what not in self._failing:
            log.error("%s; serving from memory, retrying every %.0f s", message, self.retry_s)
        self._failing[what] = self.last_error = message
        self.counters.set("state_failing", 1)

    def _recovered(self, what: str) -> None:
        if self._failing.pop(what, None) is not None:
            log.warning("%s to %s works again", what, self.state_dir)
        self.counters.set("state_failing", float(self.failing))

