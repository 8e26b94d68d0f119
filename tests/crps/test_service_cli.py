"""``skyfix serve`` refuses bad arguments with one line (exit 2); ``skyfix swarm status`` lists the
drones it hears; the live Foxglove WebSocket view advertises the log's topics."""

from __future__ import annotations

import asyncio
import json
import socket
import threading
import time

import pytest
from test_swarm_transport import free_ports

from skyfix.cli import main
from skyfix.crps.messages import FusedEstimate, Heartbeat, SwarmCodec
from skyfix.crps.transport import Endpoints, ZenohTransport
from skyfix.errors import InputError

KEY = b"0123456789abcdef0123456789abcdef"


@pytest.fixture
def key_file(tmp_path):
    path = tmp_path / "swarm.key"
    path.write_bytes(KEY)
    return path


def serve(*extra: str, key_file, url="udpin:127.0.0.1:14999", swarm=None) -> list[str]:
    swarm = swarm or f"listen:tcp/127.0.0.1:{free_ports(1)[0]}"
    return ["serve", "--id", "d1", "--mavlink", url, "--swarm", swarm, "--swarm-key-file", str(key_file), *extra]


@pytest.mark.parametrize("change, expected", [
    ({"url": "bogus://x"}, "MAVLink url"),
    ({"swarm": "127.0.0.1:7451"}, "--swarm: '127.0.0.1:7451' is not an endpoint"),
    ({"key": "missing"}, "--swarm-key-file"),
    ({"key": "short"}, "at least 16 bytes"),
    ({"extra": ("--roster", "d2,d3")}, "must include this drone's --id"),
    ({"extra": ("--log", "out.txt")}, "--log must name an .mcap file"),
    ({"extra": ("--id", "bad id!")}, "--id must be 1-32 letters"),
    ({"extra": ("--fence", "missing.geojson")}, "--fence missing.geojson: not a readable GeoJSON"),
    ({"extra": ("--gnss-common-share", "1")}, "--gnss-common-share must be in [0, 1), got 1.0"),
])
def test_bad_arguments_one_line_exit_2(tmp_path, key_file, capsys, change, expected):
    if change.get("key") == "missing":
        key_file = tmp_path / "nope.key"
    elif change.get("key") == "short":
        key_file.write_bytes(b"short")
    argv = serve(*change.get("extra", ()), key_file=key_file, url=change.get("url", "udpin:127.0.0.1:14999"),
                 swarm=change.get("swarm"))
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("skyfix serve: error:") and expected in err[0], err


def test_busy_swarm_endpoint_is_one_line(key_file, capsys):
    (port,) = free_ports(1)
    holder = socket.socket()
    holder.bind(("127.0.0.1", port))
    holder.listen()
    try:
        assert main(serve(key_file=key_file, swarm=f"listen:tcp/127.0.0.1:{port}")) == 2
    finally:
        holder.close()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "zenoh cannot open" in err[0]


def test_swarm_status_lists_the_drones_heard(key_file, capsys):
    (port,) = free_ports(1)
    drone = ZenohTransport("skyfix", "d7", Endpoints.parse(f"listen:tcp/127.0.0.1:{port}"))
    codec = SwarmCodec("d7", KEY)
    stop = threading.Event()

    def talk() -> None:
        while not stop.wait(0.1):
            drone.publish("heartbeat", codec.encode(Heartbeat("ok", "gnss", 0.9, True, 2)))
            drone.publish("estimate", codec.encode(FusedEstimate(time.time(), 46.5, 6.6, 420.0,
                                                                 (1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0), (0.0, 0.0, 0.0))))
    talker = threading.Thread(target=talk, daemon=True)
    talker.start()
    try:
        assert main(["swarm", "status", "--swarm", f"tcp/127.0.0.1:{port}", "--swarm-key-file", str(key_file),
                     "--listen-s", "2.5"]) == 0
        table = capsys.readouterr().out.splitlines()
        assert table[0].split()[:5] == ["id", "state", "fix", "health", "sigma_m"]
        row = table[1].split()
        assert row[:5] == ["d7", "ok", "gnss", "ok", "0.90"] and row[7] == "46.5000000"
        key_file.write_bytes(b"another key of at least 16 bytes")
        assert main(["swarm", "status", "--swarm", f"tcp/127.0.0.1:{port}", "--swarm-key-file", str(key_file),
                     "--listen-s", "1.5"]) == 1  # wrong key: nothing is believed
        out = capsys.readouterr().out
        assert "no drone heard" in out and "forged" in out
    finally:
        stop.set()
        talker.join()
        drone.close()


def test_live_view_advertises_the_topics():
    """A Foxglove WebSocket client (websockets, subprotocol foxglove.sdk.v1) sees the LocationFix
    and JSON channels the service writes."""
    websockets = pytest.importorskip("websockets")
    from skyfix.crps.outputs import Outputs

    (port,) = free_ports(1)
    outputs = Outputs(None, live=f"127.0.0.1:{port}")
    try:
        outputs.location_fix("d1", time.time(), 46.5, 6.6, 420.0, [1.0, 0, 0, 0, 1.0, 0, 0, 0, 2.0])
        outputs.json("/swarm/peers", {"event": "joined", "drone": "d2", "time_s": time.time()})
        sink = outputs.fusion_sink({"origin": [46.5, 6.6, 420.0], "lag_s": 2.0, "config": {}})
        sink.record("velocity", {"drone_id": "d1", "time_s": time.time(), "vel_enu_mps": [1.0, 0.0, float("nan")],
                                 "sigma_mps": 0.2})

        async def advertised() -> dict[str, str]:
            async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"]) as ws:
                channels: dict[str, str] = {}
                deadline = time.monotonic() + 5.0
                while len(channels) < 3 and time.monotonic() < deadline:
                    msg = await asyncio.wait_for(ws.recv(), timeout=5.0)
                    if isinstance(msg, str) and json.loads(msg).get("op") == "advertise":
                        channels.update({c["topic"]: c["schemaName"] for c in json.loads(msg)["channels"]})
                return channels

        channels = asyncio.run(advertised())
    finally:
        outputs.close()
    assert channels["/fix/d1"] == "foxglove.LocationFix"
    assert channels["/swarm/peers"] == "skyfix.swarm.peers"
    assert channels["/fusion/velocity"] == "skyfix.fusion.velocity"  # the engine's inputs too


def test_fence_file_becomes_the_safety_gate(tmp_path):
    from skyfix.crps.serve_cli import safety_gate

    ring = [[149.16, -35.36], [149.17, -35.36], [149.17, -35.37], [149.16, -35.36]]  # GeoJSON: lon, lat
    path = tmp_path / "fence.geojson"
    path.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {}, "geometry": {"type": "Polygon", "coordinates": [ring]}}]}))
    gate = safety_gate(path, 40.0, 12.0, "land")
    assert gate.fence.polygons[0].tolist() == [[-35.36, 149.16], [-35.36, 149.17], [-35.37, 149.17]]
    assert gate.max_alt_rel_m == 40.0 and gate.max_speed_mps == 12.0 and gate.action == "land"
    assert safety_gate(None, None, None, "rtl") is None
    path.write_text(json.dumps({"type": "Point", "coordinates": [149.16, -35.36]}))
    with pytest.raises(InputError, match="Point is not a polygon"):
        safety_gate(path, None, None, "rtl")


def test_gnss_common_share_reaches_the_fusion(key_file):
    import argparse

    from skyfix.crps.serve_cli import config_from_args, register
    from skyfix.crps.service import GNSS_COMMON_SHARE, fusion_config

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    default = config_from_args(parser.parse_args(serve(key_file=key_file)))
    chosen = config_from_args(parser.parse_args(serve("--gnss-common-share", "0", key_file=key_file)))
    assert default.gnss_common_share == GNSS_COMMON_SHARE == 0.9 and chosen.gnss_common_share == 0.0
    assert fusion_config(None, 2.0, chosen.gnss_common_share).gnss_common_share == 0.0
    assert fusion_config(None, 2.0).gnss_common_share == GNSS_COMMON_SHARE
