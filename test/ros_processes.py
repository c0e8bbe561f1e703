"""Run helper Python programs as separate OS processes for ROS tests, and always reap them."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path


def write_script(directory: Path, name: str, source: str) -> Path:
    path = directory / name
    path.write_text(textwrap.dedent(source))
    return path


@contextmanager
def running(*argv: str | Path) -> Iterator[subprocess.Popen[str]]:
    """Start ``python argv...`` (the venv's own interpreter); on exit terminate, then kill, and reap."""
    process = subprocess.Popen(
        [sys.executable, *map(str, argv)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        yield process
    finally:
        if process.poll() is None:
            process.terminate()
            try:
                process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(timeout=10)
        for stream in (process.stdout, process.stderr):
            if stream is not None:
                stream.close()


class LoggedProcess:
    """``python -m module args...`` with output to a log file; always stopped and reaped on exit."""

    def __init__(self, log_path: Path, module: str, *args: str | Path, prefix: Sequence[str] = (),
                 env: Mapping[str, str] | None = None) -> None:
        """``prefix``: a command the program runs under (``ip netns exec NS``: it execs, so the pid is ours);
        ``env``: the environment instead of this process's."""
        self.log_path = log_path
        self._log = log_path.open("w")
        self.process = subprocess.Popen(
            [*prefix, sys.executable, "-m", module, *map(str, args)], stdout=self._log, stderr=subprocess.STDOUT,
            text=True, env=env,
        )

    def log(self) -> str:
        return self.log_path.read_text()

    def wait_for_log(self, text: str, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while text not in self.log():
            if self.process.poll() is not None or time.monotonic() > deadline:
                raise AssertionError(f"{text!r} not in log of {self.process.args!r} (exit {self.process.poll()}):\n"
                                     f"{self.log()[-3000:]}")
            time.sleep(0.1)

    def wait(self, timeout_s: float) -> int:
        return self.process.wait(timeout=timeout_s)

    def stop(self, sig: int = signal.SIGINT, timeout_s: float = 20.0) -> int:
        if self.process.poll() is None:
            self.process.send_signal(sig)
            try:
                self.process.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout=10)
        return self.process.returncode

    def __enter__(self) -> LoggedProcess:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.stop(signal.SIGKILL)
        self._log.close()
