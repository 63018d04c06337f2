"""The live feed: the rows of `mocap live` as JSON lines over TCP on a loopback address,
for another program on the machine (an operator's display, a machine controller).

``--feed tcp://127.0.0.1:PORT``: connect to the port; every row from then on arrives as
one JSON object (the poses file's columns, null where unknown) and a newline. A reader
that does not keep up (its socket buffer full for a second) is dropped; the rows and the
other readers go on.
"""

from __future__ import annotations

import json
import logging
import math
import socket
import threading
from ipaddress import ip_address
from urllib.parse import urlsplit

from mocap.errors import InputError

log = logging.getLogger(__name__)

_SEND_TIMEOUT_S = 1.0


def parse_feed(text: str) -> tuple[str, int]:
    """tcp://HOST:PORT -> (host, port); the host must be a loopback address."""
    parts = urlsplit(text)
    try:
        port = parts.port
    except ValueError:
        port = None
    if parts.scheme != "tcp" or not parts.hostname or port is None:
        raise InputError(f"--feed {text!r}: expected tcp://127.0.0.1:PORT")
    host = parts.hostname
    try:
        loopback = host == "localhost" or ip_address(host).is_loopback
    except ValueError:
        loopback = False
    if not loopback:
        raise InputError(f"--feed {text!r}: only a loopback address (127.0.0.1, ::1, localhost) is served; "
                         "forward the port if another machine must read it")
    return ("127.0.0.1" if host == "localhost" else host), port


class Feed:
    """A TCP server on (host, port) that sends each row to every connected reader."""

    def __init__(self, host: str, port: int):
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self.server = socket.socket(family, socket.SOCK_STREAM)
        self.server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self.server.bind((host, port))
        except OSError as exc:
            self.server.close()
            raise InputError(f"--feed tcp://{host}:{port}: cannot listen there ({exc.strerror or exc}); "
                             "choose another port") from None
        self.server.listen(8)
        self.server.settimeout(0.2)
        self.address = self.server.getsockname()[:2]
        self.readers: list[socket.socket] = []
        self.lock = threading.Lock()
        self.closing = threading.Event()
        self.thread = threading.Thread(target=self._accept, name="feed", daemon=True)
        self.thread.start()

    @property
    def url(self) -> str:
        host, port = self.address
        return f"tcp://{host}:{port}" if ":" not in host else f"tcp://[{host}]:{port}"

    def _accept(self) -> None:
        while not self.closing.is_set():
            try:
                reader, _ = self.server.accept()
            except (TimeoutError, socket.timeout):
                continue
            except OSError:
                return
            reader.settimeout(_SEND_TIMEOUT_S)
            with self.lock:
                self.readers.append(reader)

    def send(self, values: dict) -> None:
        line = (json.dumps({k: _plain(v) for k, v in values.items()}) + "\n").encode()
        with self.lock:
            for reader in list(self.readers):
                try:
                    reader.sendall(line)
                except OSError:
                    log.info("feed: a reader left or fell behind; dropped")
                    reader.close()
                    self.readers.remove(reader)

    def close(self) -> None:
        self.closing.set()
        self.thread.join()
        self.server.close()
        with self.lock:
            for reader in self.readers:
                reader.close()
            self.readers.clear()


def _plain(value):
    return None if isinstance(value, float) and not math.isfinite(value) else value
