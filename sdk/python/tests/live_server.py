"""A live `kairos serve` (the repository's debug build) in a data directory: the server the
pytest suite (conftest.py) and the benchmark (benches/round_latency.py) run against.

KAIROS_BIN names the binary (default: target/debug/kairos at the repository root). The server is
the real one, with its built-in model; nothing is mocked.
"""

import os
import pathlib
import re
import signal
import subprocess
import threading
import time

ROOT = pathlib.Path(__file__).resolve().parents[3]
BIN = pathlib.Path(os.environ.get("KAIROS_BIN", ROOT / "target" / "debug" / "kairos"))
LISTENING = re.compile(r"listening on\s+(\S+)")
START_LIMIT_S = 120


class Server:
    """A `kairos serve` process; `restart()` keeps its data directory and port."""

    def __init__(self, data_dir: pathlib.Path, extra_args=()):
        self.data_dir = data_dir
        self.extra_args = list(extra_args)  # more `kairos serve` flags, e.g. --openpi-listen
        self.address = "127.0.0.1:0"
        self.process = None
        self.output = []

    def start(self) -> None:
        if not BIN.exists():
            raise RuntimeError(f"{BIN} is missing: build it with `cargo build -p kairos-server`")
        self.process = subprocess.Popen(
            [str(BIN), "serve", "--listen", self.address, "--data-dir", str(self.data_dir), *self.extra_args],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        found = threading.Event()

        def read(process=self.process):
            for line in process.stdout:
                self.output.append(line)
                match = LISTENING.search(line)
                if match:
                    self.address = match.group(1)
                    found.set()

        threading.Thread(target=read, daemon=True).start()
        deadline = time.monotonic() + START_LIMIT_S
        while not found.wait(0.1):
            if self.process.poll() is not None or time.monotonic() > deadline:
                self.stop()
                raise RuntimeError("kairos serve did not start:\n" + "".join(self.output))

    def stop(self) -> None:
        if self.process and self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)  # what Ctrl-C sends: a graceful shutdown
            try:
                self.process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.process = None

    def restart(self) -> None:
        self.stop()
        self.start()

    @property
    def fingerprint(self) -> str:
        return (self.data_dir / "fingerprint.txt").read_text().strip()

    @property
    def token(self) -> str:
        match = re.search(r'token = "([^"]+)"', (self.data_dir / "tokens.toml").read_text())
        assert match, "no token in tokens.toml"
        return match.group(1)
