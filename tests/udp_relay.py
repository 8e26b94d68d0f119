"""A MAVLink UDP link a test can break (used by tests/crps and tests/drivers; tests/ is on the path
through tests/conftest.py).

The client connects to ``udpout:127.0.0.1:<port>``; every datagram goes on to the autopilot's
address and back. ``cut`` set: everything dropped both ways. ``drop_from_autopilot(data)``:
datagrams from the autopilot it returns True for are dropped (counted in ``dropped``).
"""

from __future__ import annotations

import select
import socket
import threading
from collections.abc import Callable


class UdpRelay:
    """Forwards datagrams between one client and the autopilot at ``autopilot`` (host, port)."""

    def __init__(self, autopilot: tuple[str, int], drop_from_autopilot: Callable[[bytes], bool] | None = None) -> None:
        self.autopilot = autopilot
        self.drop_from_autopilot = drop_from_autopilot
        self.front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.front.bind(("127.0.0.1", 0))
        self.back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.back.bind(("127.0.0.1", 0))
        self.port = self.front.getsockname()[1]
        self.cut = threading.Event()
        self.dropped = 0
        self._stop = threading.Event()
        self._client = None
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self.front, self.back], [], [], 0.05)
            for sock in ready:
                data, addr = sock.recvfrom(65535)
                if self.cut.is_set():
                    continue
                if sock is self.front:
                    self._client = addr  # a reconnecting client comes from a new port
                    self.back.sendto(data, self.autopilot)
                elif self.drop_from_autopilot is not None and self.drop_from_autopilot(data):
                    self.dropped += 1
                elif self._client is not None:
                    self.front.sendto(data, self._client)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        self.front.close()
        self.back.close()
