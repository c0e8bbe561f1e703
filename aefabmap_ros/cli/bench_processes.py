"""CPU time and threads of the node processes a launcher started, read from Linux's /proc.

The benchmark samples the launcher's child processes while the nodes run: CPU seconds (user +
system, every thread) between two marks, divided by the images processed, is each node's cost
per image however the processes share the cores; the largest thread count seen shows whether
torch, OpenBLAS or numba started pools of their own.
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass, field
from pathlib import Path

_CLOCK_TICKS = os.sysconf("SC_CLK_TCK")
_NODE_MODULE = "aefabmap_ros.nodes."
_VIEW_MODULE = "aefabmap_ros.cli.view"  # aefabmap_launch --view's server, sampled like a node


@dataclass
class ProcessUsage:
    name: str
    cpu_at_mark_s: float = 0.0
    cpu_latest_s: float = 0.0
    max_threads: int = 0
    marked: bool = False

    def cpu_since_mark_s(self) -> float:
        return self.cpu_latest_s - self.cpu_at_mark_s


def _stat(pid: int) -> tuple[float, int] | None:
    """(CPU seconds, threads) of a live process, None once it is gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text[text.rindex(")") + 2:].split()  # after "pid (comm) ": state is fields[0]
    return (int(fields[11]) + int(fields[12])) / _CLOCK_TICKS, int(fields[17])


def _children(pid: int) -> list[int]:
    try:
        tasks = list(Path(f"/proc/{pid}/task").iterdir())
    except OSError:
        return []
    children: list[int] = []
    for task in tasks:
        try:
            children += [int(child) for child in (task / "children").read_text().split()]
        except OSError:
            continue
    return children


def _node_name(pid: int) -> str | None:
    try:
        arguments = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return None
    for argument in arguments:
        text = argument.decode(errors="replace")
        if text.startswith(_NODE_MODULE):
            return text.removeprefix(_NODE_MODULE)
        if text == _VIEW_MODULE:
            return "view"
    return None


@dataclass
class NodeProcessSampler:
    """Polls the node processes under ``launcher_pid`` in a background thread until ``stop``."""

    launcher_pid: int
    period_s: float = 0.2
    usage: dict[int, ProcessUsage] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _stop: threading.Event = field(default_factory=threading.Event)
    _thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def sample(self) -> None:
        with self._lock:
            for pid in _children(self.launcher_pid):
                stat = _stat(pid)
                if stat is None:
                    continue
                if pid not in self.usage:
                    name = _node_name(pid)
                    if name is None:
                        continue
                    self.usage[pid] = ProcessUsage(name)
                entry = self.usage[pid]
                entry.cpu_latest_s = stat[0]
                entry.max_threads = max(entry.max_threads, stat[1])

    def mark(self) -> None:
        """Start counting CPU time here (start-up and model loading are left out)."""
        self.sample()
        with self._lock:
            for entry in self.usage.values():
                entry.cpu_at_mark_s, entry.marked = entry.cpu_latest_s, True

    def stop(self) -> list[ProcessUsage]:
        self.sample()
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        with self._lock:
            return sorted(self.usage.values(), key=lambda entry: entry.name)

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            self.sample()
