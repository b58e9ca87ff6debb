"""A real LeAP Studio server in a subprocess on 127.0.0.1 (for the kill -9 and browser tests)."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx

SMALL_DEMO: dict[str, Any] = {
    "shadows": False,
    "lidar": {"beams": 32, "azimuth_step_deg": 0.4},
    "camera": {"width": 621, "height": 187, "fx": 360.77, "fy": 360.77, "cx": 304.78, "cy": 86.43},
}
"""A reduced demo street: 32 beams, 0.4° azimuth steps (~26k points per scan), a half-size camera."""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def make_small_street(root: Path, frames: int) -> Path:
    """Generate the reduced demo street into ``root/sequences/00``; returns the sequence folder."""
    from synthcache import synth_copy

    from app.core.demo_synth import synth_config

    return synth_copy(root, synth_config({**SMALL_DEMO, "frames": frames}), force=True).path


class Server:
    """``python -m app.main`` with LEAP_* settings; stdout/stderr go to ``log``."""

    def __init__(
        self,
        data_root: Path,
        *,
        port: int | None = None,
        extra_env: dict[str, str] | None = None,
        log: Path | None = None,
        cwd: Path | None = None,
    ) -> None:
        self.port = port or free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        self.log = log or data_root / "server.log"
        self.env = {
            **os.environ,
            "LEAP_DATA_ROOTS": json.dumps([str(data_root)]),
            "LEAP_WORK_DIR": str(data_root / "studio"),
            "LEAP_PORT": str(self.port),
            "LEAP_SEED_DEMO": "false",
            "LEAP_PROGRESS_INTERVAL_S": "0.01",
            # A spare worker imports the pipeline (about 1 s of CPU) and most of these servers end before
            # using it; the in-process apps of the browser tests keep the default, so it stays exercised.
            "LEAP_PREWARM_WORKERS": "false",
            **(extra_env or {}),
        }
        self.proc: subprocess.Popen[bytes] | None = None
        self.cwd = cwd
        """Current folder of the server process (default: the test's); started with ``python -P`` then,
        so that folder is not on the server's own import path either."""

    def start(self, timeout: float = 60.0) -> Server:
        return self.start_with_token(None, timeout)

    def start_with_token(self, token: str | None, timeout: float = 60.0) -> Server:
        """Start and wait until ``/health`` answers (with ``token`` when the server needs one)."""
        headers = {"X-Leap-Token": token} if token else {}
        self.proc = self.launch()
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"server exited with {self.proc.returncode}; see {self.log}")
            try:
                if httpx.get(f"{self.base}/api/v1/health", headers=headers, timeout=1.0).status_code == 200:
                    return self
            except httpx.HTTPError:
                pass
            time.sleep(0.1)
        raise RuntimeError(f"server did not answer within {timeout} s; see {self.log}")

    def launch(self) -> subprocess.Popen[bytes]:
        """Start the process without waiting for it (see :meth:`refused` for one expected to exit)."""
        python = [sys.executable] if self.cwd is None else [sys.executable, "-P"]
        with open(self.log, "ab") as out:
            return subprocess.Popen(
                [*python, "-m", "app.main"], env=self.env, stdout=out, stderr=out, cwd=self.cwd
            )

    def refused(self, timeout: float = 60.0) -> tuple[int | None, str]:
        """Start a server expected to refuse to run: ``(exit status, its output)``; a server still running
        after ``timeout`` is stopped and gives ``(None, output)``."""
        start = self.log.stat().st_size if self.log.exists() else 0
        proc = self.launch()
        try:
            code: int | None = proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)
            code = None
        return code, self.log.read_bytes()[start:].decode("utf-8", "replace")

    def kill9(self) -> None:
        assert self.proc is not None
        os.kill(self.proc.pid, signal.SIGKILL)
        self.proc.wait(10)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)

    def client(self) -> httpx.Client:
        return httpx.Client(base_url=f"{self.base}/api/v1", timeout=30.0)


def process_gone(pid: int, timeout: float = 10.0) -> bool:
    """True once ``pid`` no longer runs (exited, or a zombie waiting for its new parent to reap it)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0]
        except (FileNotFoundError, ProcessLookupError):
            return True
        if state in ("Z", "X"):
            return True
        time.sleep(0.05)
    return False
