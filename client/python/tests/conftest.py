"""Fixtures: the real ``helmholtz-server`` binary on 127.0.0.1 port 0, with tokens made by the
real ``helmholtz-server token create``. No mocks.

- The binary: ``$HELMHOLTZ_SERVER_BIN``, else ``target/debug/helmholtz-server`` of this
  repository (build it with ``cargo build -p helmholtz-server --bins``).
- The database: a SQLite file in a temporary data directory, or, when
  ``$HELMHOLTZ_PYTEST_DATABASE_URL`` names a PostgreSQL database (the Rust wrapper
  ``tests/tests/e2e/python.rs`` makes a fresh one on the postgres backend), that database.

The server is started once for the whole run and stopped (SIGTERM) at the end.
"""

from __future__ import annotations

import os
import queue
import signal
import socket
import subprocess
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Optional

import pytest

import helmholtz as hz

REPO_ROOT = Path(__file__).resolve().parents[3]
PACKAGE_ROOT = Path(__file__).resolve().parents[1]
DATABASE_ENV = "HELMHOLTZ_PYTEST_DATABASE_URL"


def server_binary() -> Path:
    explicit = os.environ.get("HELMHOLTZ_SERVER_BIN")
    path = Path(explicit) if explicit else REPO_ROOT / "target" / "debug" / "helmholtz-server"
    if not path.is_file():
        pytest.fail(
            f"the server binary {path} is missing: build it with "
            "`cargo build -p helmholtz-server --bins` or set HELMHOLTZ_SERVER_BIN",
            pytrace=False,
        )
    return path


def _clean_env() -> dict[str, str]:
    """The environment without HELMHOLTZ_* settings (the server reads e.g.
    HELMHOLTZ_DATABASE_URL and HELMHOLTZ_LISTEN from it)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("HELMHOLTZ_")}
    env["RUST_LOG"] = "warn"
    env["NO_COLOR"] = "1"
    return env


@dataclass
class Server:
    """A running server: its address, the store it uses, and a token of lab ``py`` with roles
    rig and reader."""

    binary: Path
    data_dir: Path
    database_url: Optional[str]
    address: str = ""
    token: str = ""
    process: Optional[subprocess.Popen] = None
    log_path: Optional[Path] = None
    banner: str = ""
    _lines: "queue.Queue[str]" = field(default_factory=queue.Queue)

    def store_args(self) -> list[str]:
        args = ["--data-dir", str(self.data_dir)]
        if self.database_url:
            args += ["--database-url", self.database_url]
        return args

    def create_token(self, lab: str, roles: str) -> str:
        """A new token made by the real ``helmholtz-server token create``."""
        out = subprocess.run(
            [str(self.binary), "token", "create", "--lab", lab, "--role", roles, *self.store_args()],
            env=_clean_env(),
            capture_output=True,
            text=True,
            timeout=60,
        )
        if out.returncode != 0:
            raise RuntimeError(f"token create failed: {out.stderr}")
        token = out.stdout.strip()
        assert token.startswith("hz_"), f"unexpected token output {token!r}"
        return token

    def start(self) -> None:
        self.token = self.create_token("py", "rig,reader")
        self.log_path = self.data_dir / "server.log"
        log = open(self.log_path, "wb")
        self.process = subprocess.Popen(
            [str(self.binary), "serve", "--listen", "127.0.0.1:0", *self.store_args()],
            env=_clean_env(),
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=log,
            text=True,
        )
        log.close()

        def read() -> None:
            assert self.process is not None and self.process.stdout is not None
            for line in self.process.stdout:
                self._lines.put(line)

        threading.Thread(target=read, daemon=True).start()
        try:
            first = self._lines.get(timeout=60)
        except queue.Empty:
            self.stop()
            raise RuntimeError(f"the server printed no address; its log:\n{self.log()}")
        urls = [w for w in first.split() if w.startswith(("http://", "https://"))]
        if not urls:
            self.stop()
            raise RuntimeError(f"no address in {first!r}; log:\n{self.log()}")
        self.address = urls[0].rstrip(",")
        self.banner = first.strip()

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path else ""

    def stop(self) -> None:
        if self.process is None or self.process.poll() is not None:
            return
        self.process.send_signal(signal.SIGTERM)
        try:
            self.process.wait(timeout=15)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()


@pytest.fixture(scope="session")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    s = Server(
        binary=server_binary(),
        data_dir=tmp_path_factory.mktemp("helmholtz-data"),
        database_url=os.environ.get(DATABASE_ENV) or None,
    )
    s.start()
    try:
        yield s
    finally:
        s.stop()
        code = s.process.returncode if s.process else 0
        assert code == 0, f"the server exited with {code}; its log:\n{s.log()}"


@pytest.fixture(scope="session")
def client(server: Server) -> Iterator[hz.Client]:
    """A client with the rig + reader token (the default retry policy)."""
    with hz.Client(server.address, server.token) as c:
        yield c


@pytest.fixture
def session_id(request: pytest.FixtureRequest) -> str:
    """A fresh session id named after the test."""
    name = "".join(ch if ch.isalnum() else "-" for ch in request.node.name)[:60]
    return f"{name}-{uuid.uuid4().hex[:8]}"


class CuttingProxy:
    """A TCP proxy on 127.0.0.1 port 0 in front of the real server that can cut every open
    connection at once (both sockets closed): a real network failure, no mock of either end."""

    def __init__(self, target: str):
        host, port = target.rsplit(":", 1)
        self.target = (host, int(port))
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.address = f"http://127.0.0.1:{self.port}"
        self._pairs: list[tuple[socket.socket, socket.socket]] = []
        self._lock = threading.Lock()
        self.cuts = 0
        self._closed = False
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while not self._closed:
            try:
                inbound, _ = self.listener.accept()
            except OSError:
                return
            try:
                outbound = socket.create_connection(self.target)
            except OSError:
                inbound.close()
                continue
            with self._lock:
                self._pairs.append((inbound, outbound))
            for a, b in ((inbound, outbound), (outbound, inbound)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    @staticmethod
    def _pump(src: socket.socket, dst: socket.socket) -> None:
        try:
            while True:
                data = src.recv(65536)
                if not data:
                    break
                dst.sendall(data)
        except OSError:
            pass
        for s in (src, dst):
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def cut_all(self) -> int:
        """Closes both sockets of every open connection; returns how many."""
        with self._lock:
            pairs, self._pairs = self._pairs, []
        for pair in pairs:
            for s in pair:
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                s.close()
        self.cuts += len(pairs)
        return len(pairs)

    def close(self) -> None:
        self._closed = True
        self.listener.close()
        self.cut_all()


def wait_until(predicate, timeout: float = 20.0, what: str = "condition") -> None:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.02)
