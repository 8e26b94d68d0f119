"""A loopback MAVLink UDP link that can be broken: the simulator's faults for ground stations and tests.

The ground station connects to :attr:`UdpRelay.url`; every datagram goes on to the vehicle's address and
back. ``blocked()`` True: everything dropped both ways (a link outage). ``drop_from_vehicle(data)`` True:
that datagram from the vehicle is dropped (e.g. every COMMAND_ACK). Dropped datagrams are counted.
"""

from __future__ import annotations

import select
import socket
import threading
from collections.abc import Callable


class UdpRelay:
    """Forwards datagrams between one ground station and the vehicle at ``vehicle_addr`` (host, port)."""

    def __init__(self, vehicle_addr: tuple[str, int], blocked: Callable[[], bool] | None = None,
                 drop_from_vehicle: Callable[[bytes], bool] | None = None) -> None:
        self.vehicle_addr = vehicle_addr
        self.blocked = blocked or (lambda: False)
        self.drop_from_vehicle = drop_from_vehicle
        self.gcs_side = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.gcs_side.bind(("127.0.0.1", 0))
        self.vehicle_side = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.vehicle_side.bind(("127.0.0.1", 0))
        self._gcs_addr: tuple[str, int] | None = None
        self.dropped = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="skyfix-mavlink-relay")
        self._thread.start()

    @property
    def url(self) -> str:
        """The pymavlink URL a ground station connects to."""
        return f"udpout:127.0.0.1:{self.gcs_side.getsockname()[1]}"

    def _run(self) -> None:
        socks = [self.gcs_side, self.vehicle_side]
        while not self._stop.is_set():
            ready, _, _ = select.select(socks, [], [], 0.1)
            for sock in ready:
                try:
                    data, addr = sock.recvfrom(65535)
                except OSError:
                    return
                if sock is self.gcs_side:
                    self._gcs_addr = addr  # a reconnecting ground station comes from a new port
                if self.blocked() or (sock is self.vehicle_side and self.drop_from_vehicle is not None
                                      and self.drop_from_vehicle(data)):
                    self.dropped += 1
                    continue
                if sock is self.gcs_side:
                    self.vehicle_side.sendto(data, self.vehicle_addr)
                elif self._gcs_addr is not None:
                    self.gcs_side.sendto(data, self._gcs_addr)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.gcs_side.close()
        self.vehicle_side.close()
