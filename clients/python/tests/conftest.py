"""Fixtures: a real `bgkmap serve` on free loopback ports in a temporary data directory."""

from __future__ import annotations

import os
import queue
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Iterator, List, Literal, Optional, Sequence

import pytest

# Before grpc is imported: on Python < 3.10 subprocess forks (no vfork), and grpcio's fork handlers
# then abort about 1 child in 5 ("epoll_wait error: Bad file descriptor", SIGABRT) once a channel
# has been used; the grpcurl and curl tests start subprocesses.
os.environ.setdefault("GRPC_ENABLE_FORK_SUPPORT", "false")

from bgkmap_client import Client  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[3]
START_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 30.0


def server_binary() -> Path:
    """`$BGKMAP_BIN`, else `$CARGO_TARGET_DIR/debug/bgkmap`, else `<repo>/target/debug/bgkmap`."""
    if os.environ.get("BGKMAP_BIN"):
        return Path(os.environ["BGKMAP_BIN"])
    target = os.environ.get("CARGO_TARGET_DIR")
    if target:
        return Path(target) / "debug" / "bgkmap"
    return REPO_ROOT / "target" / "debug" / "bgkmap"


def require_tool(name: str) -> str:
    """Path of a command-line tool next to this Python (a venv's bin/) or on PATH.

    Missing: skipped, unless BGKMAP_REQUIRE_TOOLS=1 (set by tests/python.sh), then failed.
    """
    here = Path(sys.executable).parent / name
    path = str(here) if here.exists() else shutil.which(name)
    if path is None:
        msg = f"{name} not found (next to {sys.executable} or on PATH)"
        if os.environ.get("BGKMAP_REQUIRE_TOOLS") == "1":
            pytest.fail(msg)
        pytest.skip(msg)
    return path


@dataclass
class Server:
    """One running `bgkmap serve`."""

    data_dir: Path
    process: subprocess.Popen
    grpc_address: str
    http_address: str
    stdout_lines: List[str] = field(default_factory=list)
    stderr_path: Optional[Path] = None
    stdout_pump: Optional[threading.Thread] = None
    zenoh_locators: List[str] = field(default_factory=list)

    def client(self, transport: Literal["grpc", "http"] = "grpc") -> Client:
        return Client(self.grpc_address, http_address=self.http_address, transport=transport)

    def stderr(self) -> str:
        if self.stderr_path is None or not self.stderr_path.exists():
            return ""
        return self.stderr_path.read_text(errors="replace")

    def stop(self) -> int:
        """SIGTERM, then wait for the drain; returns the exit code (kills after a timeout)."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
                raise AssertionError(f"server did not exit {STOP_TIMEOUT_S}s after SIGTERM") from None
            finally:
                self._close_stdout()
        self._close_stdout()
        return self.process.returncode

    def _close_stdout(self) -> None:
        if self.stdout_pump is not None:
            self.stdout_pump.join(timeout=5)
        if self.process.stdout is not None and not self.process.stdout.closed:
            self.process.stdout.close()


def start_server(data_dir: Path, extra_args: Sequence[str] = ()) -> Server:
    """`bgkmap serve` on free loopback ports; `extra_args` are appended (e.g. zenoh flags)."""
    binary = server_binary()
    if not binary.exists():
        pytest.fail(
            f"server binary {binary} not found: build it first (cargo build) or set BGKMAP_BIN", pytrace=False
        )
    data_dir.mkdir(parents=True, exist_ok=True)
    # Only the flags configure it: no BGKMAP_* settings (config file, queue size…) from outside.
    env = {k: v for k, v in os.environ.items() if not k.startswith("BGKMAP_")}
    env.setdefault("RUST_BACKTRACE", "1")
    stderr_path = data_dir.parent / f"{data_dir.name}.stderr.log"
    stderr = open(stderr_path, "wb")
    proc = subprocess.Popen(
        [
            str(binary),
            "serve",
            "--data-dir",
            str(data_dir),
            "--grpc-listen",
            "127.0.0.1:0",
            "--http-listen",
            "127.0.0.1:0",
            *extra_args,
        ],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=stderr,
        env=env,
        text=True,
    )
    stderr.close()
    lines: "queue.Queue[Optional[str]]" = queue.Queue()
    seen: List[str] = []

    def pump() -> None:  # reads stdout to the end, so the server never blocks on a full pipe
        assert proc.stdout is not None
        for line in proc.stdout:
            seen.append(line.rstrip("\n"))
            lines.put(line)
        lines.put(None)

    pump_thread = threading.Thread(target=pump, daemon=True)
    pump_thread.start()
    addrs: Dict[str, str] = {}
    zenoh_locators: List[str] = []
    deadline = time.monotonic() + START_TIMEOUT_S
    while len(addrs) < 2:
        try:
            line = lines.get(timeout=max(0.0, deadline - time.monotonic()))
        except queue.Empty:
            line = None
        if line is None:
            proc.kill()
            proc.wait()
            pump_thread.join(timeout=5)
            if proc.stdout is not None:
                proc.stdout.close()
            err = stderr_path.read_text(errors="replace")
            pytest.fail(f"server did not print its addresses; stdout {seen!r}; stderr:\n{err}", pytrace=False)
        m = re.match(r"(grpc|http|zenoh) listening on (\S+)", line.strip())
        if m and m.group(1) == "zenoh":
            zenoh_locators.append(m.group(2))  # printed before the gRPC and HTTP lines
        elif m:
            addrs[m.group(1)] = m.group(2)
    server = Server(data_dir, proc, addrs["grpc"], addrs["http"], seen, stderr_path, pump_thread, zenoh_locators)
    for transport in ("grpc", "http"):
        with server.client(transport) as c:
            c.wait_ready(timeout=START_TIMEOUT_S)
    return server


@pytest.fixture(scope="session")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    s = start_server(tmp_path_factory.mktemp("bgkmap") / "data")
    yield s
    code = s.stop()
    assert code == 0, f"server exited {code} after SIGTERM; stderr:\n{s.stderr()}"


@pytest.fixture(scope="session")
def grpc_client(server: Server) -> Iterator[Client]:
    with server.client("grpc") as c:
        yield c


@pytest.fixture(scope="session")
def http_client(server: Server) -> Iterator[Client]:
    with server.client("http") as c:
        yield c
