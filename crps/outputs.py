"""Where the service's topics go: the MCAP log and, with ``--live``, a Foxglove WebSocket view.

Topics (one per stream, each with a schema):

- ``/fusion/<op>``: every engine input and smoother update (the replayable measurement log);
- ``/mavlink/state``: the autopilot link and GNSS state as the service saw them;
- ``/swarm/in/<type>`` and ``/swarm/out/<type>``: every peer message received and sent;
- ``/swarm/peers``: joined / lost / rejoined events; ``/swarm/dropped``: dropped-message counts;
- ``/estimate/<drone>``: fused estimates (JSON) and ``/fix/<drone>``: the same as Foxglove's
  ``LocationFix`` (protobuf from foxglove-sdk), so a map panel shows the whole swarm;
- ``/action``: what the service asked of the autopilot (position injection on/off).
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path

import numpy as np

from skyfix.errors import InputError
from skyfix.fusion.log import _plain
from skyfix.fusion.log_mcap import McapLog
from skyfix.jsonfile import json_safe

log = logging.getLogger(__name__)

_OBJECT = {"type": "object"}
LOCATION_FIX = "foxglove.LocationFix"


class Outputs:
    """Fan-out of topics to an MCAP log (``log_path``) and a live Foxglove server (``live``: port or
    ``HOST:PORT``); either may be absent. The node records into the same file
    (:meth:`fusion_sink`)."""

    def __init__(self, log_path: str | Path | None, live: str | None = None, name: str = "skyfix") -> None:
        self.log_path = None if log_path is None else Path(log_path)
        if self.log_path is not None and self.log_path.suffix != ".mcap":
            raise InputError(f"--log must name an .mcap file, got {str(log_path)!r}")
        if self.log_path is not None and self.log_path.exists() and self.log_path.stat().st_size > 0:
            raise InputError(f"--log {self.log_path} already exists; the log is never overwritten, choose a new file")
        self._live_channels: dict[str, object] = {}
        self._lock = threading.Lock()
        self._server = None if live is None else _start_live(live, name)
        self.mcap = McapLog(self.log_path, None) if self.log_path is not None else None

    def fusion_sink(self, header: dict) -> FusionTee:
        """The node's measurement-log sink: the MCAP log (``header`` written) and the live view."""
        if self.mcap is not None:
            self.mcap.set_header(header)
        return FusionTee(self)

    def json(self, topic: str, obj: dict, time_s: float | None = None) -> None:
        """One JSON message on ``topic`` (schema: a JSON object named after the topic)."""
        if self.mcap is not None:
            self.mcap.channel(topic, "skyfix" + topic.replace("/", "."), _OBJECT)
            self.mcap.write(topic, obj, time_s)
        if self._server is not None:
            self.live_json(topic, obj)

    def live_json(self, topic: str, obj: dict) -> None:
        """``obj`` on ``topic`` of the live view only (when there is one)."""
        if self._server is not None:
            self._live(topic, lambda: _json_channel(topic)).log(json_safe(obj))

    def location_fix(self, drone_id: str, time_s: float, lat_deg: float, lon_deg: float, alt_m: float,
                     cov_enu_m2) -> None:
        """``drone_id``'s fused position as Foxglove's LocationFix on ``/fix/<drone_id>`` (WGS84, ellipsoidal
        m, ENU covariance m^2)."""
        from foxglove.messages import LocationFix, LocationFixPositionCovarianceType, Timestamp

        sec = int(time_s)
        msg = LocationFix(timestamp=Timestamp(sec=sec, nsec=int((time_s - sec) * 1e9)), frame_id=f"drone_{drone_id}",
                          latitude=float(lat_deg), longitude=float(lon_deg), altitude=float(alt_m),
                          position_covariance=[float(c) for c in np.asarray(cov_enu_m2).reshape(9)],
                          position_covariance_type=LocationFixPositionCovarianceType.Known)
        topic = f"/fix/{drone_id}"
        if self.mcap is not None:
            schema = LocationFix.get_schema()
            self.mcap.channel(topic, LOCATION_FIX, schema.data, encoding="protobuf", schema_encoding="protobuf")
            self.mcap.write(topic, msg.encode(), time_s)
        if self._server is not None:
            self._live(topic, lambda: _fix_channel(topic)).log(msg)

    def close(self) -> None:
        """Finish the log and stop the live server."""
        if self.mcap is not None:
            self.mcap.close()
        if self._server is not None:
            self._server.stop()
            self._server = None

    def _live(self, topic: str, make):
        with self._lock:
            ch = self._live_channels.get(topic)
            if ch is None:
                ch = self._live_channels[topic] = make()
            return ch


class FusionTee:
    """The node's measurement-log sink: engine records to the MCAP log and to the live view."""

    def __init__(self, outputs: Outputs) -> None:
        self.outputs = outputs

    def record(self, op: str, args: dict | None = None) -> None:
        if self.outputs.mcap is not None:
            self.outputs.mcap.record(op, args)
        if self.outputs._server is not None:
            plain = {"op": op} if args is None else {"op": op, "args": {k: _plain(v) for k, v in args.items()}}
            self.outputs.live_json(f"/fusion/{op}", plain)

    def truth(self, drone_id: str, time_s: float, lat_deg: float, lon_deg: float, alt_m: float) -> None:
        if self.outputs.mcap is not None:
            self.outputs.mcap.truth(drone_id, time_s, lat_deg, lon_deg, alt_m)

    def close(self) -> None:
        if self.outputs.mcap is not None:
            self.outputs.mcap.close()


def _start_live(spec: str, name: str):
    import foxglove

    host, _, port_s = str(spec).rpartition(":")
    try:
        port = int(port_s)
    except ValueError:
        port = -1
    if not 0 < port < 65536:
        raise InputError(f"--live must be a port or HOST:PORT, got {spec!r}")
    try:
        server = foxglove.start_server(name=name, host=host or "127.0.0.1", port=port)
    except Exception as exc:  # the SDK raises its own RuntimeError subclasses for a busy port
        raise InputError(f"--live {spec}: cannot start the Foxglove WebSocket server ({exc})") from None
    log.info("live view: Foxglove WebSocket on ws://%s:%d", host or "127.0.0.1", server.port)
    return server


def _json_channel(topic: str):
    import json

    import foxglove

    schema = foxglove.Schema(name="skyfix" + topic.replace("/", "."), encoding="jsonschema",
                             data=json.dumps(_OBJECT).encode())
    return foxglove.Channel(topic, schema=schema, message_encoding="json")


def _fix_channel(topic: str):
    from foxglove.channels import LocationFixChannel

    return LocationFixChannel(topic)

