"""The drone fleet over the network: N drone processes, one map-server process, a kill -9 of the server mid-run,
one drone cut off for a while; then the server's cost per update as the fleet grows (in one process).

    # the issue's run (docs/fleet_30min.json: 461 s wall here; the kill must come before the end to be mid-run)
    python benchmarks/fleet.py --drones 5 --minutes 30 --rate 4 --kill-after 240 --cut-drone 1 --cut-at 600 \
        --cut-seconds 60 --scaling '' --floor-markers --surveyed-markers --timeout 4800 --out fleet_30min.json
    python benchmarks/fleet.py --drones 5 --minutes 4 --out fleet.json           # a short run

Network part (real processes, ZeroMQ on 127.0.0.1): bytes per simulated second per drone (up = drone -> server,
down = server -> drone; mean and p99 over the flight's seconds), inter-robot loops found, each drone's ATE of its
keyframes in the merged frame (the server's final poses against the truth, no alignment: every drone starts at a
surveyed dock; also after one rigid alignment of the whole merged map), the same for the drone's own front end
alone, lost acknowledged deltas (a drone notices when a
restarted server reports fewer committed deltas than it had acknowledged), keyframes committed per drone against
keyframes flown, and the cut-off drone's record. Scaling part: ``slam2d.fleet.local.run_local`` with 1, 2, 5 and
10 drones, wall time of every delta's handling (commit, merge, loop search, solve) and of every whole-graph solve:
p50/p99 and the fitted exponent of cost against fleet size, and each drone's merged-frame ATE.

``--floor-markers``: the warehouse's floor markers; drones read them (their front end uses them and their deltas
carry each keyframe's readings) and the server joins them into shared marker nodes. ``--surveyed-markers`` (both
parts): the server also knows every marker's position from a survey of the floor: the true positions plus a normal
error of ``--survey-sigma`` (1 cm) per axis, drawn once (``World.marker_survey``); the network part hands it to
``slam2d map-server --marker-survey FILE.csv``, at the first start and at the restart after the kill.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _env() -> dict[str, str]:
    env = dict(os.environ)
    src = str(Path(__file__).resolve().parents[1] / "src")
    env["PYTHONPATH"] = src + os.pathsep + env.get("PYTHONPATH", "")
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    return env


def start_server(db: Path, port: int, log: Path, survey: Path | None = None) -> subprocess.Popen[bytes]:
    f = open(log, "ab")
    extra = [] if survey is None else ["--marker-survey", str(survey)]
    p = subprocess.Popen([sys.executable, "-m", "slam2d", "map-server", "--db", str(db), "--port", str(port)] + extra,
                         stdout=f, stderr=subprocess.STDOUT, env=_env())
    from slam2d.fleet.client import ServerUnavailable, status

    for _ in range(100):
        try:
            status(f"tcp://127.0.0.1:{port}", timeout_s=1.0)
            return p
        except ServerUnavailable:
            if p.poll() is not None:
                raise RuntimeError(f"map-server exited: {log.read_text()[-500:]}") from None
    raise RuntimeError("map-server did not answer")


def network_run(args: argparse.Namespace, work: Path) -> dict[str, Any]:
    from slam2d.fleet.client import status
    from slam2d.fleet.local import merged_ate

    port = _free_port()
    ep = f"tcp://127.0.0.1:{port}"
    db = work / "fleet.db"
    survey_csv = None
    if args.surveyed_markers:
        from slam2d.io.survey import write_marker_survey

        survey_csv = work / "survey.csv"
        write_marker_survey(survey_csv, marker_survey(args.scenario, args.survey_sigma, args.seed))
    server = start_server(db, port, work / "server.log", survey_csv)
    drones = []
    for k in range(args.drones):
        cmd = [sys.executable, "-m", "slam2d", "drone", "--server", ep, "--drone", str(k), "--scenario",
               args.scenario, "--minutes", str(args.minutes), "--seed", str(args.seed), "--json",
               str(work / f"drone{k}.json"), "--rate", str(args.rate)] + (["--floor-markers"] if args.floor_markers
                                                                          else [])
        if k == args.cut_drone:
            cmd += ["--blackout", f"{args.cut_at}:{args.cut_seconds}"]
        drones.append(subprocess.Popen(cmd, stdout=open(work / f"drone{k}.log", "wb"),
                                       stderr=subprocess.STDOUT, env=_env()))
    t0 = time.monotonic()
    kill: dict[str, Any] = {}
    while time.monotonic() - t0 < args.kill_after and all(d.poll() is None for d in drones):
        time.sleep(0.5)
    before = status(ep)
    kill["committed_before"] = {d["drone"]: d["keyframes"] for d in before["drones"]}
    server.send_signal(signal.SIGKILL)
    server.wait()
    kill["killed_at_wall_s"] = round(time.monotonic() - t0, 1)
    time.sleep(args.down_seconds)
    t_restart = time.monotonic()
    server = start_server(db, port, work / "server.log", survey_csv)
    kill["restart_s"] = round(time.monotonic() - t_restart, 2)
    after = status(ep)
    kill["committed_after_restart"] = {d["drone"]: d["keyframes"] for d in after["drones"]}
    kill["none_lost_at_restart"] = all(kill["committed_after_restart"].get(d, 0) >= n
                                       for d, n in kill["committed_before"].items())
    for d in drones:
        d.wait(timeout=args.timeout)
    wall = time.monotonic() - t0
    final = status(ep, full=True)
    server.send_signal(signal.SIGTERM)
    server.wait(timeout=30)
    rows = []
    merged_all, truth_all = [], []
    by_drone = {d["drone"]: d for d in final["drones"]}
    failed = {}
    for k in range(args.drones):
        if not (work / f"drone{k}.json").exists():  # the drone exited with an error: keep its last words
            failed[k] = (work / f"drone{k}.log").read_text()[-400:]
            continue
        rec = json.loads((work / f"drone{k}.json").read_text())
        truth = np.asarray(rec["truth"], float)
        local = np.asarray(rec["local"], float)
        merged = np.frombuffer(by_drone[k]["poses"], "<f8").reshape(-1, 3)
        up, down = np.asarray(rec["up_bytes"], float), np.asarray(rec["down_bytes"], float)
        merged_all.append(merged[: len(truth)])
        truth_all.append(truth)
        rows.append({"drone": k, "keyframes_flown": len(truth), "keyframes_committed": len(merged),
                     "ate_merged_m": merged_ate(truth, merged[: len(truth)]), "ate_own_front_end_m":
                     merged_ate(truth, local), "up_kBps_mean": up.mean() / 1024,
                     "up_kBps_p99": float(np.percentile(up, 99)) / 1024, "down_kBps_mean": down.mean() / 1024,
                     "down_kBps_p99": float(np.percentile(down, 99)) / 1024,
                     "total_kBps_p99": float(np.percentile(up + down, 99)) / 1024, "reconnects": rec["reconnects"],
                     "lost_acked": rec["lost_acked"], "errors": len(rec["errors"]), "tiles": rec["tiles"],
                     "marker_sightings_sent": rec.get("marker_sightings", 0),
                     "own_marker_resightings": rec.get("marker_resightings", 0),
                     "cut_off": k == args.cut_drone})
    # the whole merged map aligned to the truth by ONE rigid transform (all drones together), for comparison
    from slam2d.eval.trajectory import align_se2
    from slam2d.geometry import se2

    est_all = np.vstack([m for m in merged_all]) if merged_all else np.zeros((0, 3))
    ref_all = np.vstack(truth_all) if truth_all else np.zeros((0, 3))
    t_align = align_se2(est_all, ref_all)
    if failed:
        return {"drones": rows, "failed": failed, "kill": kill, "wall_s": round(wall, 1)}
    for row, m, t in zip(rows, merged_all, truth_all, strict=True):
        row["ate_merged_fleet_aligned_m"] = merged_ate(t, se2.compose(np.broadcast_to(t_align, m.shape), m))
    np.savez(work / "final_poses.npz", **{f"merged{k}": m for k, m in enumerate(merged_all)},
             **{f"truth{k}": t for k, t in enumerate(truth_all)})
    loops = final["loops"]
    pairs: dict[str, int] = {}
    for lp in loops:
        key = f"{min(lp['a'][0], lp['b'][0])}-{max(lp['a'][0], lp['b'][0])}"
        pairs[key] = pairs.get(key, 0) + 1
    return {"drones": rows, "inter_robot_loops": len(loops), "loops_by_pair": pairs, "kill": kill,
            "wall_s": round(wall, 1), "server_errors": final["errors"],
            "server_errors_by_code": final.get("errors_by_code"), "markers": final.get("markers")}


def marker_survey(scenario: str, sigma_m: float, seed: int) -> tuple[tuple[int, float, float], ...]:
    """The scenario's floor markers as a survey gives them (each position off by N(0, sigma_m) per axis)."""
    from slam2d.sim.scenarios import ScenarioConfig
    from slam2d.sim.simulator import Simulator
    from slam2d.sim.warehouse import WarehouseConfig

    world = Simulator(ScenarioConfig(name=scenario, warehouse=WarehouseConfig(floor_markers=True))).world
    return world.marker_survey(sigma_m, np.random.default_rng([seed, 17]))


def scaling(sizes: list[int], minutes: float, seed: int, work: Path, floor_markers: bool = False,
            surveyed: bool = False, survey_sigma_m: float = 0.01) -> dict[str, Any]:
    from slam2d.fleet.drone import DroneConfig
    from slam2d.fleet.joint import JointConfig
    from slam2d.fleet.local import merged_ate, run_local

    out: dict[str, Any] = {"sizes": sizes, "minutes": minutes, "rows": []}
    for n in sizes:
        db = work / f"scale{n}.db"
        t0 = time.perf_counter()
        joint = JointConfig()
        if surveyed:
            joint = JointConfig(surveyed_markers=marker_survey("warehouse", survey_sigma_m, seed),
                                survey_sigma_m=survey_sigma_m)
        run = run_local(db, n, DroneConfig(minutes=minutes, seed=seed, floor_markers=floor_markers), joint)
        results = [d.result() for d in run.drones]
        j = run.server.joint
        upd = np.asarray(run.update_s)
        sol = np.asarray([s.seconds for s in run.server.joint.solves])
        out["rows"].append({"drones": n, "nodes": len(run.server.joint.poses), "updates": len(upd),
                            "update_ms_p50": float(np.percentile(upd, 50)) * 1e3,
                            "update_ms_p99": float(np.percentile(upd, 99)) * 1e3,
                            "solves": len(sol), "solve_ms_p50": float(np.percentile(sol, 50)) * 1e3 if len(sol) else 0,
                            "solve_ms_p99": float(np.percentile(sol, 99)) * 1e3 if len(sol) else 0,
                            "loops": len(run.server.joint.loops), "wall_s": round(time.perf_counter() - t0, 1),
                            "ate_merged_m": [merged_ate(r.truth, j.drone_poses(r.drone)[: len(r.truth)])
                                             for r in results],
                            "ate_own_front_end_m": [merged_ate(r.truth, r.local) for r in results],
                            "markers": len(j.marker_ids), "marker_links": j.marker_links,
                            "marker_resightings": j.marker_resightings})
        run.server.close()
    rows = out["rows"]
    x = np.log([r["drones"] for r in rows])
    for key in ("update_ms_p50", "update_ms_p99", "solve_ms_p50"):
        y = np.log([max(r[key], 1e-6) for r in rows])
        out[f"exponent_{key}"] = float(np.polyfit(x, y, 1)[0]) if len(rows) > 1 else float("nan")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--drones", type=int, default=5)
    ap.add_argument("--minutes", type=float, default=30.0, help="simulated minutes per drone")
    ap.add_argument("--scenario", default="warehouse")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rate", type=float, default=4.0,
                    help="drones fly this many simulated seconds per wall second (0: as fast as they compute)")
    ap.add_argument("--kill-after", type=float, default=30.0, help="wall seconds before kill -9 of the server")
    ap.add_argument("--down-seconds", type=float, default=5.0, help="wall seconds the server stays dead")
    ap.add_argument("--cut-drone", type=int, default=1, help="the drone cut off from the server (-1: none)")
    ap.add_argument("--cut-at", type=float, default=60.0, help="simulated second the cut starts")
    ap.add_argument("--cut-seconds", type=float, default=60.0, help="simulated seconds without a link")
    ap.add_argument("--timeout", type=float, default=3600.0, help="wall seconds to wait for the drones")
    ap.add_argument("--scaling", default="1,2,5,10", help="fleet sizes of the cost part ('' skips it)")
    ap.add_argument("--scaling-minutes", type=float, default=1.0)
    ap.add_argument("--skip-network", action="store_true")
    ap.add_argument("--floor-markers", action="store_true",
                    help="the warehouse's floor markers: drones read them, the server joins them (slam2d.fleet.joint)")
    ap.add_argument("--surveyed-markers", action="store_true",
                    help="the server knows every marker's position from a survey (slam2d map-server --marker-survey)")
    ap.add_argument("--survey-sigma", type=float, default=0.01, help="the survey's error per axis (m)")
    ap.add_argument("--out", required=True, help="JSON output file")
    args = ap.parse_args()
    if args.surveyed_markers and not args.floor_markers:
        ap.error("--surveyed-markers needs --floor-markers (the drones must read the markers)")
    if args.drones < 1:
        ap.error(f"--drones must be >= 1 (got {args.drones})")
    # checked before the run, not after it: the fleet sizes and the output file
    try:
        sizes = [int(s) for s in args.scaling.split(",")] if args.scaling else []
    except ValueError:
        ap.error(f"--scaling takes comma-separated fleet sizes, e.g. 1,2,5 (got {args.scaling!r})")
    if any(n < 1 for n in sizes):
        ap.error(f"--scaling: every fleet size must be >= 1 (got {args.scaling!r})")
    result: dict[str, Any] = {"args": vars(args)}
    work = Path(args.out + ".work")  # server/drone logs and records, kept
    try:
        work.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        ap.error(f"--out {args.out}: cannot create {work} ({e.strerror})")
    from slam2d.io.atomic import check_output

    try:
        check_output(args.out, "--out")
    except OSError as e:
        ap.error(f"{e.filename}: {e.strerror}")
    for old in work.glob("*"):
        old.unlink()
    if not args.skip_network:
        result["network"] = network_run(args, work)
        print(json.dumps(result["network"], indent=1, default=str), flush=True)
    if args.scaling:
        result["scaling"] = scaling(sizes, args.scaling_minutes,
                                    args.seed, work, args.floor_markers, args.surveyed_markers, args.survey_sigma)
        print(json.dumps(result["scaling"], indent=1), flush=True)
    Path(args.out).write_text(json.dumps(result, indent=1, default=str) + "\n")


if __name__ == "__main__":
    main()
