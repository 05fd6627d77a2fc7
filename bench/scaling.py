"""The scaling model of ``argus bench system --workers``: CPU-seconds per keyframe per process role, measured
from ``/proc``, and what they predict for N workers.

Roles: the mapper's main thread (the central work: intake decode, keyframe selection, jobs out, results
decoded and checked, fusion, relations, publishing: serial, one core at most), the mapper's other threads
(Zenoh I/O and its callbacks), the router, the bench process (the simulated cameras and the graph watcher) and
each worker. Each is ``CPU-seconds spent in the phase / keyframes done in the phase``; a worker's is per job it
answered (:func:`role_costs`).

The model (:func:`predict`): a keyframe costs ``w`` CPU-seconds on a worker and ``c`` on the mapper's main
thread, moves ``bytes_per_job`` between them, and the rest of the machine costs ``o`` per keyframe (mapper I/O
threads, router, cameras). Then

- N workers on their own machines (each worker one core; the mapper's machine keeps its cores):
  ``min(N / w, 1 / c, mapper_cores / (c + o), link / bytes_per_job)`` keyframes/s;
- N workers on this machine (``cores`` shared by everything):
  ``min(N / w, 1 / c, cores / (c + o + w))``;

each capped by the keyframes offered. With no worker the mapper's main thread does the work: ``1 / (c + w)``.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

_CLK_TCK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
LINK_BYTES_PER_S = 125e6
"""The link assumed between machines: 1 Gbit/s."""


def stat_cpu_s(path: Path) -> float:
    """User + system CPU seconds in a ``/proc`` ``stat`` file (a process's or one of its threads')."""
    text = path.read_text()
    fields = text[text.rindex(")") + 2 :].split()
    return (int(fields[11]) + int(fields[12])) / _CLK_TCK


def child_pids(pid: int) -> list[int]:
    """The running child processes of ``pid`` in pid order (``/proc/<pid>/task/*/children``; zombies left out),
    e.g. the mapper's local workers (``[workers] local``). Empty when ``pid`` is gone."""
    out: list[int] = []
    try:
        tasks = list(Path(f"/proc/{pid}/task").iterdir())
    except OSError:
        return []
    for task in tasks:
        try:
            out += [int(c) for c in (task / "children").read_text().split()]
        except OSError:  # the thread ended meanwhile
            continue
    return sorted(c for c in set(out) if process_running(c))


def process_running(pid: int) -> bool:
    """Whether ``pid`` is a process that has not exited (a zombie has)."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return text[text.rindex(")") + 2 :].split()[0] not in ("Z", "X")


def thread_cpu_s(pid: int) -> dict[str, float]:
    """User + system CPU seconds of a process split into its main thread (``main``) and all its other threads
    (``threads``), from ``/proc/<pid>/task``; threads that ended are in neither (read both ends of a phase)."""
    main = other = 0.0
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            cpu = stat_cpu_s(task / "stat")
        except (FileNotFoundError, ProcessLookupError):  # the thread ended meanwhile
            continue
        if task.name == str(pid):
            main += cpu
        else:
            other += cpu
    return {"main": main, "threads": other}


def cmdline(pid: int) -> str:
    """The command line of ``pid``, its arguments joined by spaces ("" when it is gone)."""
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
    except OSError:
        return ""


class ChildClock:
    """Cumulative CPU seconds of the children of ``parent`` (those whose command line contains ``match``), named
    ``<prefix><i>`` in the order they were found. They are looked up at every :meth:`sample`, so a child started
    after the clock was made (the mapper starts its local worker only once it serves) is counted from its start;
    a child that ended keeps the CPU seconds of its last sample (a role's clock never runs backwards)."""

    def __init__(self, parent: int, prefix: str, match: str | None = None,
                 children: Callable[[int], list[int]] | None = None,
                 cpu: Callable[[int], float | None] | None = None) -> None:
        self.parent, self.prefix, self.match = parent, prefix, match
        self._children = children or child_pids
        self._cpu = cpu or _cpu_or_none
        self._names: dict[int, str] = {}  # pid -> name, for every child ever found
        self._last: dict[str, float] = {}  # name -> CPU seconds at its last sample

    def sample(self) -> dict[str, float]:
        for pid in self._children(self.parent):
            if pid not in self._names:
                if self.match is not None and self.match not in cmdline(pid):
                    continue
                self._names[pid] = f"{self.prefix}{len(self._names)}"
            cpu = self._cpu(pid)
            if cpu is not None:
                self._last[self._names[pid]] = cpu
        return dict(self._last)


class RoleClock:
    """CPU seconds of each role's process (mapper split into main thread and other threads) at one moment. With
    ``local`` (a :class:`ChildClock` of the mapper's local workers) those are workers too, found when they exist."""

    def __init__(self, mapper: int, router: int | None, workers: dict[str, int], bench: int | None = None,
                 local: ChildClock | None = None) -> None:
        self.mapper, self.router, self.workers, self.local = mapper, router, dict(workers), local
        self.bench = os.getpid() if bench is None else bench

    def sample(self) -> dict[str, float]:
        out: dict[str, float] = {}
        t = thread_cpu_s(self.mapper)
        out["mapper_main"], out["mapper_threads"] = t["main"], t["threads"]
        if self.router is not None:
            out["router"] = _safe_cpu(self.router)
        out["cameras"] = _safe_cpu(self.bench)
        for name, pid in self.workers.items():
            out[f"worker.{name}"] = _safe_cpu(pid)
        if self.local is not None:
            out.update({f"worker.{name}": cpu for name, cpu in self.local.sample().items()})
        return out


def workers_cpu_s(cpu0: dict[str, float], cpu1: dict[str, float]) -> float:
    """CPU seconds all workers spent between two :meth:`RoleClock.sample` s (a worker first seen in ``cpu1``: all of
    its own)."""
    return sum(v - cpu0.get(k, 0.0) for k, v in cpu1.items() if k.startswith("worker."))


def _cpu_or_none(pid: int) -> float | None:
    try:
        t = thread_cpu_s(pid)
    except (FileNotFoundError, ProcessLookupError):  # the process ended
        return None
    return t["main"] + t["threads"]


def _safe_cpu(pid: int) -> float:
    cpu = _cpu_or_none(pid)
    return 0.0 if cpu is None else cpu


def role_costs(cpu0: dict[str, float], cpu1: dict[str, float], keyframes_done: float,
               jobs_by_worker: dict[str, float]) -> dict[str, float | None]:
    """CPU-seconds per keyframe done per role between two :meth:`RoleClock.sample` s (per job for each worker:
    ``jobs_by_worker`` the jobs each answered in between), ``workers`` (all of them) and ``all`` (every role); None
    where nothing was done."""
    out: dict[str, float | None] = {}
    for role in cpu1:
        spent = cpu1[role] - cpu0.get(role, 0.0)
        if role.startswith("worker."):
            jobs = jobs_by_worker.get(role.split(".", 1)[1], 0.0)
            out[f"cpu_s_per_job.{role}"] = spent / jobs if jobs > 0 else None
            out[f"cpu_s_per_kf.{role}"] = spent / keyframes_done if keyframes_done > 0 else None
        else:
            out[f"cpu_s_per_kf.{role}"] = spent / keyframes_done if keyframes_done > 0 else None
    workers = [v for k, v in out.items() if k.startswith("cpu_s_per_kf.worker.") and v is not None]
    out["cpu_s_per_kf.workers"] = sum(workers) if workers else None
    roles = [v for k, v in out.items() if k.startswith("cpu_s_per_kf.") and k != "cpu_s_per_kf.workers"
             and v is not None]
    out["cpu_s_per_kf.all"] = sum(roles) if roles else None  # every role, workers included
    return out


def model_inputs(costs: dict[str, float | None], n_workers: int) -> dict[str, float] | None:
    """``c`` (mapper main thread), ``o`` (everything else but the workers) and ``w`` (a worker's CPU-seconds per
    job, mean over workers; with no worker: the mapper's own main thread does it, so ``w`` is not separable and
    None is returned) from :func:`role_costs` output."""
    c = costs.get("cpu_s_per_kf.mapper_main")
    per_job = [v for k, v in costs.items() if k.startswith("cpu_s_per_job.worker.") and v is not None]
    if c is None or n_workers == 0 or not per_job:
        return None
    o = sum(costs.get(f"cpu_s_per_kf.{r}") or 0.0 for r in ("mapper_threads", "router", "cameras"))
    return {"c": c, "o": o, "w": sum(per_job) / len(per_job)}


def predict(c: float, o: float, w: float, n: int, cores: int, bytes_per_job: float | None = None,
            link_bytes_per_s: float = LINK_BYTES_PER_S, offered: float | None = None,
            mapper_cores: int | None = None) -> dict[str, float]:
    """Keyframes/s the model predicts for ``n`` workers: ``separate`` (each on its own machine) and ``shared``
    (all on this machine's ``cores``); see the module doc. ``offered``: keyframes/s offered (a cap)."""
    cap = float("inf") if offered is None else offered
    if n == 0:
        alone = min(1.0 / (c + w), cores / (c + o + w), cap)
        return {"separate": alone, "shared": alone}
    link = link_bytes_per_s / bytes_per_job if bytes_per_job else float("inf")
    mc = cores if mapper_cores is None else mapper_cores
    separate = min(n / w, 1.0 / c, mc / (c + o), link, cap)
    shared = min(n / w, 1.0 / c, cores / (c + o + w), cap)
    return {"separate": separate, "shared": shared}


def curve(inputs: dict[str, float], cores: int, bytes_per_job: float | None, offered: float | None,
          counts: tuple[int, ...] = (0, 1, 2, 4, 8, 16)) -> list[dict[str, Any]]:
    """:func:`predict` for each worker count (rows for the report)."""
    rows = []
    for n in counts:
        p = predict(inputs["c"], inputs["o"], inputs["w"], n, cores, bytes_per_job, offered=offered)
        rows.append({"workers": n, "model_kf_per_s_separate_machines": p["separate"],
                     "model_kf_per_s_this_machine": p["shared"]})
    return rows
