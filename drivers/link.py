"""One MAVLink link (pymavlink connection) shared by every vehicle heard on it.

A reader thread parses incoming packets and hands each to the :class:`Vehicle` of its
source system id; malformed packets are counted and dropped. A monitor thread sends the
ground-station HEARTBEAT at 1 Hz, detects heartbeat loss per vehicle, and the reader
reopens the connection after an I/O error (serial unplugged, TCP reset).
"""

from __future__ import annotations

import logging
import re
import select
import socket
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from skyfix.drivers.mav import mavlink, mavutil
from skyfix.errors import InputError, LinkError

if TYPE_CHECKING:
    from skyfix.drivers.vehicle import Vehicle

log = logging.getLogger(__name__)

_URL = re.compile(r"^(udp|udpin|udpout|udpbcast|tcp|tcpin):[^:]+:\d+$|^(serial:)?(/dev/|COM)\S+(:\d+)?$")


def check_url(url: str) -> str:
    """Raise InputError unless ``url`` is a pymavlink URL skyfix supports."""
    if not isinstance(url, str) or not _URL.match(url):
        raise InputError(
            f"MAVLink url must look like 'udpin:127.0.0.1:14550', 'udpout:HOST:PORT', "
            f"'tcp:HOST:PORT' or a serial device '/dev/ttyACM0[:BAUD]', got {url!r}")
    return url


def _open(url: str, source_system: int, source_component: int) -> mavutil.mavfile:
    device, baud = url, 115200
    if url.startswith("serial:"):
        device = url[len("serial:"):]
    if device.startswith(("/dev/", "COM")) and device.count(":") == 1:
        device, baud_s = device.split(":")
        baud = int(baud_s)
    try:
        conn = mavutil.mavlink_connection(device, baud=baud, source_system=source_system,
                                          source_component=source_component, robust_parsing=True,
                                          autoreconnect=False, retries=0, dialect="ardupilotmega")
    except Exception as exc:  # pymavlink raises bare OSError/SerialException/socket errors
        raise LinkError(f"cannot open MAVLink link {url!r}: {exc}") from exc
    conn.mav.robust_parsing = True
    return conn


def _raise_on_tcp_eof(conn) -> None:
    """pymavlink without autoreconnect spins on a closed TCP socket; turn EOF into an error."""
    try:
        if conn.port.recv(1, socket.MSG_PEEK) == b"":
            raise ConnectionResetError("TCP peer closed the connection")
    except (BlockingIOError, InterruptedError):
        pass


class MavlinkLink:
    """A pymavlink connection with a reader thread; vehicles appear as their heartbeats arrive.

    ``heartbeat_timeout_s``: a vehicle whose HEARTBEAT has not been heard for this long is
    marked ``link_ok = False`` and a ``link_lost`` event is raised.
    """

    def __init__(self, url: str, *, source_system: int = 255, source_component: int = 190,
                 heartbeat_timeout_s: float = 3.0) -> None:
        self.url = check_url(url)
        self.source_system = int(source_system)
        self.source_component = int(source_component)
        self.heartbeat_timeout_s = float(heartbeat_timeout_s)
        self._conn = _open(url, self.source_system, self.source_component)
        self._send_lock = threading.Lock()
        self._vehicles_lock = threading.Condition()
        self.vehicles: dict[int, Vehicle] = {}
        self.vehicle_factory: Callable[[MavlinkLink, int, int, int], Vehicle] | None = None
        #: callables ``tap(msg, t_mono)`` seeing every valid incoming message (logging, recording)
        self.taps: list[Callable] = []
        self.bad_packets = 0
        self.packets_in = 0
        self.reconnects = 0
        self._closed = threading.Event()
        self._reader = threading.Thread(target=self._read_loop, name=f"skyfix-mav-reader {url}",
                                        daemon=True)
        self._monitor = threading.Thread(target=self._monitor_loop, name=f"skyfix-mav-monitor {url}",
                                         daemon=True)
        self.send_heartbeat()  # a udpout peer only learns our address from our first packet
        self._reader.start()
        self._monitor.start()

    # ------------------------------------------------------------------ sending
    @property
    def mav(self) -> mavlink.MAVLink:
        """The pymavlink encoder (use :meth:`send` to transmit)."""
        return self._conn.mav

    def send(self, msg) -> None:
        """Send one MAVLink message object; thread-safe."""
        if self._closed.is_set():
            raise LinkError(f"MAVLink link {self.url} is closed")
        with self._send_lock:
            try:
                self._conn.mav.send(msg)
            except OSError as exc:
                log.warning("send on %s failed: %s", self.url, exc)

    def send_heartbeat(self) -> None:
        self.send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID,
                                                    0, 0, mavlink.MAV_STATE_ACTIVE, 3))

    # ------------------------------------------------------------------ vehicles
    def wait_vehicle(self, system_id: int | None, timeout_s: float) -> Vehicle:
        """The vehicle with ``system_id`` (or the first one heard), once its heartbeat arrives."""
        deadline = time.monotonic() + timeout_s
        with self._vehicles_lock:
            while True:
                if system_id is None and self.vehicles:
                    return next(iter(self.vehicles.values()))
                if system_id is not None and system_id in self.vehicles:
                    return self.vehicles[system_id]
                left = deadline - time.monotonic()
                if left <= 0:
                    heard = sorted(self.vehicles)
                    who = f"system id {system_id}" if system_id is not None else "any autopilot"
                    raise LinkError(
                        f"no HEARTBEAT from {who} on {self.url} within {timeout_s:.1f} s "
                        f"(heard system ids {heard}); check the URL, that the autopilot is "
                        f"running, and that it sends to this address")
                self._vehicles_lock.wait(min(left, 0.1))

    def wait_vehicles(self, count: int, timeout_s: float) -> list[Vehicle]:
        """At least ``count`` vehicles, sorted by system id."""
        deadline = time.monotonic() + timeout_s
        with self._vehicles_lock:
            while len(self.vehicles) < count:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise LinkError(f"heard {len(self.vehicles)} of {count} vehicles on {self.url} "
                                    f"within {timeout_s:.1f} s (system ids {sorted(self.vehicles)})")
                self._vehicles_lock.wait(min(left, 0.1))
            return [self.vehicles[k] for k in sorted(self.vehicles)]

    def close(self) -> None:
        """Stop the threads and close the connection."""
        if self._closed.is_set():
            return
        self._closed.set()
        for t in (self._reader, self._monitor):
            if t is not threading.current_thread():
                t.join(timeout=2.0)
        try:
            self._conn.close()
        except OSError:
            pass

    @property
    def closed(self) -> bool:
        return self._closed.is_set()

    # ------------------------------------------------------------------ threads
    def _dispatch(self, msg, t_mono: float) -> None:
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            self.bad_packets += 1
            return
        self.packets_in += 1
        for tap in list(self.taps):
            tap(msg, t_mono)
        sysid = msg.get_srcSystem()
        vehicle = self.vehicles.get(sysid)
        if vehicle is None:
            if mtype != "HEARTBEAT" or msg.type == mavlink.MAV_TYPE_GCS \
                    or msg.autopilot == mavlink.MAV_AUTOPILOT_INVALID or msg.get_srcComponent() != 1:
                return
            if self.vehicle_factory is None:
                return
            vehicle = self.vehicle_factory(self, sysid, msg.get_srcComponent(), msg.autopilot)
            with self._vehicles_lock:
                self.vehicles[sysid] = vehicle
                self._vehicles_lock.notify_all()
            log.info("vehicle %d (%s) on %s", sysid, vehicle.autopilot, self.url)
        vehicle._on_message(msg, t_mono)

    def _read_loop(self) -> None:
        while not self._closed.is_set():
            conn = self._conn
            try:
                fd = getattr(conn, "fd", None)
                if fd is not None:
                    ready, _, _ = select.select([fd], [], [], 0.05)
                    if ready and isinstance(conn, mavutil.mavtcp):
                        _raise_on_tcp_eof(conn)
                else:
                    time.sleep(0.002)
                for _ in range(1000):
                    msg = conn.recv_msg()
                    if msg is None:
                        break
                    t_mono = time.monotonic()
                    try:
                        self._dispatch(msg, t_mono)
                    except Exception:  # one bad message must not kill the reader
                        self.bad_packets += 1
                        log.exception("dropped a %s message that could not be handled", msg.get_type())
            except (OSError, ValueError) as exc:
                if self._closed.is_set():
                    return
                self._reconnect(exc)
            except Exception as exc:  # pymavlink parser errors on malformed bytes
                self.bad_packets += 1
                log.debug("malformed data on %s: %s", self.url, exc)

    def _reconnect(self, exc: Exception) -> None:
        log.warning("MAVLink link %s failed (%s); reconnecting", self.url, exc)
        delay = 0.2
        while not self._closed.is_set():
            try:
                self._conn.close()
            except Exception:  # already broken
                pass
            try:
                conn = _open(self.url, self.source_system, self.source_component)
            except LinkError as err:
                log.debug("reconnect to %s failed: %s", self.url, err)
                self._closed.wait(delay)
                delay = min(delay * 2, 2.0)
                continue
            with self._send_lock:
                self._conn = conn
            self.reconnects += 1
            self.send_heartbeat()
            log.info("MAVLink link %s reopened", self.url)
            for vehicle in list(self.vehicles.values()):
                vehicle.request_streams()  # a rebooted autopilot forgot our rates
            return

    def _monitor_loop(self) -> None:
        next_hb = time.monotonic() + 1.0
        while not self._closed.wait(0.05):
            now = time.monotonic()
            if now >= next_hb:
                next_hb = now + 1.0
                try:
                    self.send_heartbeat()
                except LinkError:
                    return
            for vehicle in list(self.vehicles.values()):
                vehicle._check_heartbeat(now, self.heartbeat_timeout_s)
