"""``slam2d map-server`` and ``slam2d drone``: the fleet's map server and one drone, as separate processes that talk
ZeroMQ (see :mod:`slam2d.fleet`)."""

from __future__ import annotations

import argparse
import socket
import sys
from typing import Any

from slam2d.cli.common import check_number, check_outputs, write_json
from slam2d.io.atomic import exclusive


def register(sub: Any) -> None:
    p = sub.add_parser("map-server", help="the fleet's map server (ZeroMQ; state in an SQLite file)",
                       description="Serve the joint map of a drone fleet: drones send deltas (keyframes, edges, "
                                   "compact scan descriptors), the server commits each to MAP.db (SQLite, WAL) "
                                   "before acknowledging it, finds inter-robot loop closures, optimises the joint "
                                   "graph and answers with corrected poses and changed map tiles. Stop with "
                                   "Ctrl-C or SIGTERM; a restart on the same file resumes.")
    p.add_argument("--db", required=True, metavar="MAP.db", help="the server's SQLite file (created if missing)")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=int, default=5555, help="TCP port (default 5555; 0: any free port, printed)")
    p.add_argument("--marker-survey", default=None, metavar="FILE.csv",
                   help="surveyed floor-marker positions, lines id,x,y (m, warehouse frame): each becomes a prior "
                        "on its marker, anchoring every drone that reads it (read again at every start)")
    p.add_argument("--survey-sigma", type=float, default=None, metavar="M",
                   help="with --marker-survey: standard deviation of a surveyed position per axis (m; default 0.01)")
    p.add_argument("--durable", action="store_true",
                   help="fsync every commit (survives a power cut, not only a crash of the server; slower)")
    p.set_defaults(func=cmd_server)

    d = sub.add_parser("drone", help="one simulated drone of the fleet, talking to a map server",
                       description="Fly one simulated drone (its own lidar front end) and send its map deltas to a "
                                   "map server; resends what the server has not acknowledged after a reconnect.")
    d.add_argument("--server", required=True, metavar="ADDR",
                   help="the map server, tcp://HOST:PORT (or HOST:PORT)")
    d.add_argument("--scenario", default="warehouse", help="simulated world (default warehouse)")
    d.add_argument("--drone", type=int, required=True, metavar="K", help="this drone's id (0..65535), unique")
    d.add_argument("--minutes", type=float, default=2.0, help="simulated flight time in minutes (default 2)")
    d.add_argument("--seed", type=int, default=0, help="fleet seed (drone K simulates with seed*1000+K)")
    d.add_argument("--rate", type=float, default=0.0,
                   help="simulated seconds per wall second (default 0: as fast as it computes)")
    d.add_argument("--blackout", default=None, metavar="START:SECONDS",
                   help="no link to the server from START for SECONDS (simulated time), e.g. 60:60")
    d.add_argument("--floor-markers", action="store_true",
                   help="fly with the scenario's floor markers (front end and deltas use them)")
    d.add_argument("--json", default=None, metavar="OUT", help="write the drone's record (bytes, poses) as JSON")
    d.set_defaults(func=cmd_drone)


def _need_fleet_extra(command: str) -> None:
    try:
        import msgpack  # noqa: F401
        import zmq  # noqa: F401
    except ImportError as e:
        raise ValueError(f"slam2d {command} needs pyzmq and msgpack ({e.name} is missing): "
                         "pip install 'slam2d[fleet]'") from None


def cmd_server(args: argparse.Namespace) -> int:
    _need_fleet_extra("map-server")
    from slam2d.fleet.joint import JointConfig
    from slam2d.fleet.server import MapServer
    from slam2d.io.survey import read_marker_survey

    check_number("--port", args.port, low=0, high=65535)
    if args.survey_sigma is not None and args.marker_survey is None:
        raise ValueError("--survey-sigma needs --marker-survey (the positions it is the uncertainty of)")
    args.survey_sigma = 0.01 if args.survey_sigma is None else args.survey_sigma
    check_number("--survey-sigma", args.survey_sigma, low=0, low_open=True, high=10.0)
    survey = () if args.marker_survey is None else read_marker_survey(args.marker_survey)  # before the db is touched
    server = MapServer(args.db, JointConfig(surveyed_markers=survey, survey_sigma_m=args.survey_sigma),
                       durable=args.durable)  # a path that is not a fleet database fails here, before the lock

    def ready(endpoint: str) -> None:
        print(f"map-server: listening on {endpoint} (db {args.db}, {len(server.drones)} drones, "
              f"{len(server.joint.poses)} keyframes, {len(survey)} surveyed markers)", flush=True)

    import zmq

    try:
        # one server per database: a second one would hand out the same drone ids and keyframe keys
        with exclusive(f"{args.db}.lock", f"another map-server has {args.db} open"):
            server.serve(args.host, args.port, ready=ready)
    except zmq.ZMQError as e:
        raise OSError(e.errno, f"cannot bind tcp://{args.host}:{args.port}: {e.strerror}") from None
    finally:
        server.close()
    print("map-server: stopped", flush=True)
    return 0


def parse_blackout(text: str | None) -> tuple[float, float] | None:
    if text is None:
        return None
    try:
        a, b = (float(x) for x in text.split(":"))
    except ValueError:
        raise ValueError(f"--blackout must be START:SECONDS, e.g. 60:60 (got {text!r})") from None
    check_number("--blackout start", a, low=0)
    check_number("--blackout seconds", b, low=0, low_open=True)
    return a, b


def parse_server(text: str) -> str:
    """``tcp://HOST:PORT`` or ``HOST:PORT`` -> a ZeroMQ endpoint; anything else names --server."""
    addr = text if "://" in text else f"tcp://{text}"
    scheme, _, rest = addr.partition("://")
    host, _, port = rest.rpartition(":")
    if scheme != "tcp" or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"--server: expected tcp://HOST:PORT or HOST:PORT with a port in 1..65535, got {text!r}")
    try:  # a name that does not resolve fails now; a server that is down is waited for (it may be restarting)
        socket.getaddrinfo(host.strip("[]"), int(port), type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError) as e:
        raise ValueError(f"--server: cannot resolve host {host!r} ({getattr(e, 'strerror', None) or e})") from None
    return addr


def cmd_drone(args: argparse.Namespace) -> int:
    _need_fleet_extra("drone")
    from slam2d.fleet.drone import Drone, DroneConfig
    from slam2d.sim.scenarios import SCENARIOS

    check_number("--drone", args.drone, low=0, high=65535)
    check_number("--minutes", args.minutes, low=0, low_open=True, high=24 * 60)
    check_number("--rate", args.rate, low=0)
    check_number("--seed", args.seed, low=0, high=(2**63 - 1 - 65535) // 1000)  # drone K simulates seed*1000+K
    if args.scenario not in SCENARIOS:
        raise ValueError(f"--scenario: unknown scenario {args.scenario!r}; valid: {sorted(SCENARIOS)}")
    check_outputs(args, [], [("--json", args.json)])
    server = parse_server(args.server)
    cfg = DroneConfig(scenario=args.scenario, minutes=args.minutes, seed=args.seed, rate=args.rate,
                      blackout=parse_blackout(args.blackout), floor_markers=args.floor_markers)
    drone = Drone(server, args.drone, cfg, log=lambda s: print(s, file=sys.stderr, flush=True))
    result = drone.run()
    up = result.up_bytes
    print(f"drone {args.drone}: {result.steps} steps, {result.keyframes} keyframes, {result.deltas} deltas, "
          f"{result.reconnects} reconnects, up {up.mean() / 1024:.2f} KB/s mean, "
          f"down {result.down_bytes.mean() / 1024:.2f} KB/s mean, errors {len(result.errors)}", flush=True)
    if args.json:
        write_json(args.json, result.as_dict())
    if result.errors:
        raise ValueError(f"the server refused part of drone {args.drone}'s data: {result.errors[0]}")
    return 0
