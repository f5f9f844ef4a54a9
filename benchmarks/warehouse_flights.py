"""Three flights in the warehouse: a cold start that saves its map, then two flights (pallets relocated) that start
from the saved map at random unknown poses and must relocalise.

1. flight 1 (``warehouse.flight=0``): the lidar session from the true start (cold start), the whole lawnmower
   route; its estimated map (keyframes, pose graph, static layer, floor markers it read) is saved;
2. flights 2 and 3 (``warehouse.flight=1, 2``: a fraction of the pallets moved each time): ``--starts`` random start
   steps along each flight's route; from each, the relocaliser gets ``--budget-s`` seconds of motion (odometry,
   lidar, and floor markers or not) against the saved map. Reported: success rate (accepted within the budget and
   right in the map's frame), WRONG acceptances (error > 0.5 m or > 5 deg in the map's frame: must be 0), how many
   accepted poses are > 0.5 m from the truth itself (``off_truth``: a pose right in a map that flight 1 drew with
   drift is off the truth by that drift), time to decide;
3. the whole of flights 2 and 3 as lidar sessions from the previous flight's saved map (relocalise, then localise and
   map): the static layers of consecutive flights compared cell by cell (occupied cells, IoU; also over only the
   cells both flights observed), and against the truth: the pallet faces that differ between the two flights'
   worlds are the moved pallets (carried into the map's frame); the IoU outside them, how many cells differ on
   and off them, and where the cells that joined or left the static layer lie. ``--estimator lidar-lifelong`` runs
   the sessions with map layers (flights 2 and 3 localise against the saved static layer and update it; their maps
   keep the saved one's cell lattice; at the end of each, how many of the new pallet faces' cells the dynamic layer
   holds: changes to the loaded map stay there, :mod:`slam2d.maps.layer_changes`); ``lidar`` re-draws each
   flight's map from its keyframe scans.

Errors of accepted poses are given against the truth and in the map's frame (:func:`map_frame`: flight 1 draws the
map with its own drift, about half a degree here, which no relocaliser can see). ``--markers surveyed`` (lifelong
sessions only) hands the sessions the floor markers' surveyed positions (``World.marker_survey``, 1 cm per axis):
each reading corrects the pose, so the map is drawn in the survey's frame.

Default world (state it with the numbers): 40 x 30 m, 3 aisles, 1 cross-aisle, 40 pallets, 2 forklifts, 10 Hz
(``dt_s=0.1``), the challenge's 360-beam 30 m lidar; the full 100 x 100 m world is ``--full`` (20 forklifts, 600
pallets, 30 Hz stepped with the lidar every 3rd step; hours on this machine, not run here).

Run: OPENBLAS_NUM_THREADS=1 PYTHONPATH=src .venv/bin/python benchmarks/warehouse_flights.py [--full] [--starts 20]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from slam2d.config import with_overrides
from slam2d.frontend.relocalise import RelocaliseConfig, Relocaliser
from slam2d.geometry import se2
from slam2d.graph.lidar import LidarSLAMConfig, LifelongLidarConfig
from slam2d.graph.lidar_session import LidarSession, LidarSessionConfig
from slam2d.lab.runner import run
from slam2d.maps.layer_changes import changed_mask, removed_mask
from slam2d.maps.store import MapSnapshot
from slam2d.sim.scenarios import ScenarioConfig
from slam2d.sim.simulator import Simulator, simulate, spawn_streams

SMALL = {"warehouse.width_m": "40", "warehouse.depth_m": "30", "warehouse.aisles": "3",
         "warehouse.cross_aisles": "1", "warehouse.pallets": "40", "moving_objects": "2", "dt_s": "0.1",
         "steps": "3000"}
FULL = {"lidar.every": "3", "steps": "80000"}
WRONG_M, WRONG_DEG = 0.5, 5.0


def scenario(base: dict[str, str], flight: int) -> ScenarioConfig:
    return with_overrides(ScenarioConfig(name="warehouse-challenge"),
                          {**base, "warehouse.floor_markers": "true", "warehouse.flight": str(flight)})


def occupied_cells(s: MapSnapshot) -> set[tuple[int, int]]:
    """Occupied static-layer cells as global integer cell indices (so maps with different bounds compare)."""
    iy, ix = np.nonzero(s.occupancy_logodds > np.log(0.65 / 0.35))
    res = s.occupancy_resolution_m
    cx = np.floor((s.occupancy_origin[0] + (ix + 0.5) * res) / res).astype(np.int64)
    cy = np.floor((s.occupancy_origin[1] + (iy + 0.5) * res) / res).astype(np.int64)
    return set(zip(cx.tolist(), cy.tolist(), strict=True))


def iou(a: MapSnapshot, b: MapSnapshot) -> tuple[float, float]:
    """Cell IoU of the occupied static cells, exact and with a one-cell tolerance (a cell counts as shared when
    the other map has an occupied cell among its 8 neighbours)."""
    ca, cb = occupied_cells(a), occupied_cells(b)
    exact = len(ca & cb) / max(len(ca | cb), 1)
    near = [(dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1)]
    ma = sum(any((x + dx, y + dy) in cb for dx, dy in near) for x, y in ca)
    mb = sum(any((x + dx, y + dy) in ca for dx, dy in near) for x, y in cb)
    shared = 0.5 * (ma + mb)
    return exact, shared / max(len(ca) + len(cb) - shared, 1)


def segment_cells(walls: np.ndarray, res: float) -> set[tuple[int, int]]:
    """Global integer cells (as :func:`occupied_cells`) that the segments (W,4) pass through (sampled every res/4)."""
    out: set[tuple[int, int]] = set()
    for x0, y0, x1, y1 in walls:
        n = max(int(np.hypot(x1 - x0, y1 - y0) / (res / 4)), 1) + 1
        t = np.linspace(0.0, 1.0, n)
        c = np.floor(np.stack([x0 + t * (x1 - x0), y0 + t * (y1 - y0)], -1) / res).astype(np.int64)
        out.update(map(tuple, c.tolist()))
    return out


def dilate(cells: set[tuple[int, int]], r: int = 1) -> set[tuple[int, int]]:
    return {(x + dx, y + dy) for x, y in cells for dx in range(-r, r + 1) for dy in range(-r, r + 1)}


def observed_cells(s: MapSnapshot) -> set[tuple[int, int]]:
    """Cells (as :func:`occupied_cells`) the map has observed: occupied or known free (log-odds != 0)."""
    iy, ix = np.nonzero(s.occupancy_logodds != 0)
    res = s.occupancy_resolution_m
    cx = np.floor((s.occupancy_origin[0] + (ix + 0.5) * res) / res).astype(np.int64)
    cy = np.floor((s.occupancy_origin[1] + (iy + 0.5) * res) / res).astype(np.int64)
    return set(zip(cx.tolist(), cy.tolist(), strict=True))


def co_observed_iou(a: MapSnapshot, b: MapSnapshot) -> float:
    """IoU of the occupied cells over the cells both maps observed: a cell only one flight saw (ground the other
    never reached) is no disagreement."""
    both = observed_cells(a) & observed_cells(b)
    ca, cb = occupied_cells(a) & both, occupied_cells(b) & both
    return len(ca & cb) / max(len(ca | cb), 1)


def to_map_frame(walls: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """Segments (W,4) in the simulator's frame carried into the map's by ``frame`` (:func:`map_frame`)."""
    w = walls.reshape(-1, 4)
    return np.hstack([se2.transform_points(frame, w[:, :2]), se2.transform_points(frame, w[:, 2:])])


def changes(a: MapSnapshot, b: MapSnapshot, walls_a: np.ndarray, walls_b: np.ndarray,
            frame: np.ndarray) -> dict[str, float]:
    """How the static layer changed between two flights against the truth: the walls that differ between the two
    flights' worlds are the moved pallets' faces (old and new), carried into the map's frame by ``frame`` (the
    layers are drawn there: flight 1's turn of half a degree puts a pallet 20 cm off its true place at 25 m).
    Reported: the IoU of the two static layers outside the moved pallets (one cell of margin), the cells that
    differ on and off the moved pallets, and where the cells that joined / left the static layer lie."""
    res = a.occupancy_resolution_m
    wa, wb = np.round(walls_a, 6).reshape(-1, 4), np.round(walls_b, 6).reshape(-1, 4)
    ka, kb = set(map(tuple, wa.tolist())), set(map(tuple, wb.tolist()))
    gone = walls_a.reshape(-1, 4)[[tuple(w) not in kb for w in wa.tolist()]]
    came = walls_b.reshape(-1, 4)[[tuple(w) not in ka for w in wb.tolist()]]
    gone, came = to_map_frame(gone, frame), to_map_frame(came, frame)
    old_cells, new_cells = dilate(segment_cells(gone, res)), dilate(segment_cells(came, res))
    moved = old_cells | new_cells
    ca, cb = occupied_cells(a), occupied_cells(b)
    ra, rb = ca - moved, cb - moved
    added, removed = cb - ca, ca - cb
    return {"moved_pallet_faces": float(len(came)), "iou_outside_moved": len(ra & rb) / max(len(ra | rb), 1),
            "differ_on_moved": float(len((ca ^ cb) & moved)), "differ_elsewhere": float(len((ca ^ cb) - moved)),
            "added_cells": float(len(added)), "added_on_new_pallets": len(added & new_cells) / max(len(added), 1),
            "removed_cells": float(len(removed)),
            "removed_on_old_pallets": len(removed & old_cells) / max(len(removed), 1),
            "new_pallet_cells_in_static": len(segment_cells(came, res) & cb) / max(len(segment_cells(came, res)), 1)}


def moved_in_dynamic(est: LidarSession, walls_a: np.ndarray, walls_b: np.ndarray,
                     frame: np.ndarray) -> dict[str, float]:
    """The dynamic layer at the end (last scan) of a lifelong session from a saved map against the pallets moved
    since the previous flight: the new pallet faces' cells (in the map's frame), how many of them the dynamic layer
    holds (also with one cell of margin), and the layer's size (its semi-static part: changes to the loaded map)."""
    lay = est.lidar.map_layers()
    res = lay.resolution
    wa, wb = np.round(walls_a, 6).reshape(-1, 4), np.round(walls_b, 6).reshape(-1, 4)
    ka, kb = set(map(tuple, wa.tolist())), set(map(tuple, wb.tolist()))
    came = to_map_frame(walls_b.reshape(-1, 4)[[tuple(w) not in ka for w in wb.tolist()]], frame)
    gone = to_map_frame(walls_a.reshape(-1, 4)[[tuple(w) not in kb for w in wa.tolist()]], frame)
    new = segment_cells(came, res)
    pts = lay.dynamic_points(lay.last_time_s)
    dyn = set(map(tuple, np.floor(pts / res).astype(np.int64).tolist()))
    chg = int(np.count_nonzero(changed_mask(lay)))
    held = lay.cell_centres(np.flatnonzero(removed_mask(lay).ravel()))
    held_cells = set(map(tuple, np.floor(held / res).astype(np.int64).tolist()))
    return {"new_pallet_cells": float(len(new)), "new_pallet_cells_dynamic": float(len(new & dyn)),
            "new_pallet_margin_dynamic": float(len(dilate(new) & dyn)), "dynamic_cells": float(len(dyn)),
            "changed_cells": float(chg), "removals_held": float(len(held_cells)),
            "removals_held_on_old_pallets": float(len(held_cells & dilate(segment_cells(gone, res))))}


def map_frame(estimated: np.ndarray, true: np.ndarray) -> np.ndarray:
    """The rigid transform (x, y, theta) that takes the simulator's frame to the map's: least squares over the
    positions of flight 1's estimated and true trajectories. A saved map is drawn with flight 1's drift (about half
    a degree of heading here), so a pose can be right in the map and off against the truth; "map-frame error" is the
    error against the truth carried into the map's frame by this transform."""
    a, b = true[:, :2], estimated[:, :2]
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((b - mb).T @ (a - ma))
    r = u @ np.diag([1.0, np.linalg.det(u @ vt)]) @ vt
    return np.array([*(mb - r @ ma), np.arctan2(r[1, 0], r[0, 0])])


def session(cfg: ScenarioConfig, seed: int, prior: MapSnapshot | None, world: str, lifelong: bool,
            survey: tuple[tuple[int, float, float], ...] = (),
            survey_sigma_m: float = 0.01) -> tuple[LidarSession, float, np.ndarray]:
    log = simulate(cfg, seed)
    lidar = LifelongLidarConfig(surveyed_markers=survey, survey_sigma_m=max(survey_sigma_m, 1e-3)) if lifelong \
        else LidarSLAMConfig()
    est = LidarSession(LidarSessionConfig(lidar=lidar), prior=prior, world_id=world)
    t0 = time.perf_counter()
    run(est, log, rng=spawn_streams(seed)["estimator"], progress=False)
    assert log.walls is not None
    return est, time.perf_counter() - t0, log.walls


def trials(prior: MapSnapshot, cfg: ScenarioConfig, seed: int, starts: int, budget_s: float,
           rng: np.random.Generator, frame: np.ndarray) -> list[dict[str, Any]]:
    log = simulate(cfg, seed)
    steps = list(log)
    n = round(budget_s / float(log.metadata["config"]["dt_s"]))
    picks = np.sort(rng.choice(len(steps) - n, size=starts, replace=False))
    out = []
    for s in picks.tolist():
        for markers in (True, False):
            rel = Relocaliser(prior, RelocaliseConfig(use_markers=markers), rng=np.random.default_rng(s))
            row: dict[str, Any] = {"start": s, "markers": markers, "decided": False, "wrong": False}
            t0 = time.perf_counter()
            for st in steps[s:s + n]:
                status = rel.step(st)
                if status.decided and status.pose is not None:
                    e = se2.local(log.true_poses[st.index], status.pose)
                    row.update(decided=True, time_s=st.time_s - steps[s].time_s + float(st.dt_s),
                               error_m=float(np.hypot(e[0], e[1])), error_deg=float(np.degrees(abs(e[2]))))
                    # against the unaligned truth (summarise counts it as off_truth; wrong is judged in the map's frame)
                    row["wrong"] = row["error_m"] > WRONG_M or row["error_deg"] > WRONG_DEG
                    em = se2.local(se2.compose(frame, log.true_poses[st.index]), status.pose)
                    row.update(map_error_m=float(np.hypot(em[0], em[1])), map_error_deg=float(np.degrees(abs(em[2]))))
                    break
            row["cpu_s"] = time.perf_counter() - t0
            row["hypotheses_first"] = rel.history[0]["hypotheses"] if rel.history else 0
            out.append(row)
    return out


def summarise(rows: list[dict[str, Any]], markers: bool) -> dict[str, Any]:
    """A relocalisation is right when it is right in the map's frame (the truth carried into it by the one rigid
    transform of :func:`map_frame`): a map is drawn in a frame of its own, and evo's ATE aligns once too. How many
    accepted poses are more than WRONG_M from the truth itself (``off_truth``) is reported beside it."""
    r = [x for x in rows if x["markers"] == markers]
    decided = [x for x in r if x["decided"]]
    ok = [x for x in decided if x["map_error_m"] <= WRONG_M and x["map_error_deg"] <= WRONG_DEG]
    return {"starts": len(r), "success": len(ok), "success_rate": len(ok) / max(len(r), 1),
            "wrong": len(decided) - len(ok), "undecided": len(r) - len(decided),
            "off_truth": sum(x["wrong"] for x in decided),
            "decide_s_median": float(np.median([x["time_s"] for x in ok])) if ok else float("nan"),
            "decide_s_max": float(np.max([x["time_s"] for x in ok])) if ok else float("nan"),
            "error_m_max": float(np.max([x["error_m"] for x in ok])) if ok else float("nan"),
            "error_m_median": float(np.median([x["error_m"] for x in ok])) if ok else float("nan"),
            "map_error_m_median": float(np.median([x["map_error_m"] for x in ok])) if ok else float("nan"),
            "map_error_deg_median": float(np.median([x["map_error_deg"] for x in ok])) if ok else float("nan"),
            "cpu_s_per_start": float(np.mean([x["cpu_s"] for x in r])) if r else float("nan")}


def print_table(table: list[dict[str, Any]]) -> None:
    cols = ["flight", "markers", "starts", "success", "success_rate", "wrong", "undecided", "off_truth",
            "decide_s_median", "decide_s_max", "error_m_max", "error_m_median", "map_error_m_median",
            "map_error_deg_median", "cpu_s_per_start"]
    print("  ".join(f"{c:>20s}" for c in cols))
    for row in table:
        print("  ".join(f"{row[c]:>20.3f}" if isinstance(row[c], float) else f"{row[c]!s:>20s}" for c in cols))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--full", action="store_true", help="the 100 x 100 m challenge warehouse (slow)")
    ap.add_argument("--starts", type=int, default=20)
    ap.add_argument("--budget-s", type=float, default=10.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None, help="write every trial and the summary here")
    ap.add_argument("--table-from", default=None, help="print the table of a --json file written earlier and stop")
    ap.add_argument("--maps-dir", default=None, help="save each flight's map here (flight1.db, ...)")
    ap.add_argument("--skip-trials", action="store_true", help="only the three sessions and the IoU")
    ap.add_argument("--estimator", choices=("lidar", "lidar-lifelong"), default="lidar",
                    help="the sessions' back end: lidar (keyframe scans, loops; the map is re-drawn from the "
                         "keyframes) or lidar-lifelong (map layers: flights 2 and 3 localise against the saved "
                         "static layer and update it)")
    ap.add_argument("--markers", choices=("read", "surveyed"), default="read",
                    help="floor markers: read (the sessions map the markers they read; the relocaliser uses that "
                         "layer) or surveyed (the lifelong sessions also get the markers' surveyed positions, true "
                         "plus --survey-sigma per axis drawn once, and each reading corrects the pose)")
    ap.add_argument("--survey-sigma", type=float, default=0.01, help="with --markers surveyed: survey error (m)")
    args = ap.parse_args()
    if args.markers == "surveyed" and args.estimator != "lidar-lifelong":
        ap.error("--markers surveyed needs --estimator lidar-lifelong (the survey corrects the lifelong mode)")
    # refused now, not after flight 1's session (minutes; about an hour with --full)
    if args.starts < 0:
        ap.error(f"--starts must be >= 0 (got {args.starts})")
    if args.budget_s <= 0:
        ap.error(f"--budget-s must be > 0 (got {args.budget_s})")
    if args.table_from and not Path(args.table_from).is_file():
        ap.error(f"--table-from {args.table_from}: no such file")
    if args.json and not args.table_from:
        from slam2d.io.atomic import check_output

        try:
            check_output(args.json, "--json")
        except OSError as e:
            ap.error(f"{e.filename}: {e.strerror}")
    if args.maps_dir and not args.table_from:
        try:
            Path(args.maps_dir).mkdir(parents=True, exist_ok=True)
        except OSError as e:
            ap.error(f"--maps-dir {args.maps_dir}: cannot create it ({e.strerror})")
    if args.table_from:
        with open(args.table_from) as fh:
            trials_of = json.load(fh)["trials"]
        print_table([{"flight": int(f), "markers": "yes" if m else "no", **summarise(rows, m)}
                     for f, rows in trials_of.items() for m in (True, False)])
        return
    base = FULL if args.full else SMALL
    from slam2d.cli.map_session import world_of

    world = world_of(scenario(base, 0), args.seed)
    print(f"world: {'100 x 100 m challenge' if args.full else '40 x 30 m, 3 aisles, 40 pallets, 2 forklifts'}, "
          f"seed {args.seed}, {args.starts} random starts per flight, {args.budget_s:.0f} s of motion each")
    lifelong = args.estimator == "lidar-lifelong"
    print(f"sessions: --estimator {args.estimator}")
    survey: tuple[tuple[int, float, float], ...] = ()
    if args.markers == "surveyed":
        sim = Simulator(scenario(base, 0), seed=args.seed, record=False)
        survey = sim.world.marker_survey(args.survey_sigma, np.random.default_rng([args.seed, 17]))
        print(f"floor markers: {len(survey)} surveyed (survey error {100 * args.survey_sigma:g} cm per axis)")
    est1, t1, walls = session(scenario(base, 0), args.seed, None, world, lifelong, survey, args.survey_sigma)
    traj1 = est1.estimate().trajectory
    assert traj1 is not None
    frame = map_frame(traj1, simulate(scenario(base, 0), args.seed).true_poses[: len(traj1)])
    print(f"the map's frame against the simulator's: {frame[0]:+.3f} m, {frame[1]:+.3f} m, "
          f"{np.degrees(frame[2]):+.3f} deg (flight 1's drift; map-frame errors below are against it)")
    maps = [est1.snapshot()]
    if args.maps_dir:
        Path(args.maps_dir).mkdir(parents=True, exist_ok=True)
        est1.save_map(f"{args.maps_dir}/flight1.db")
    c = maps[0].counts()
    print(f"flight 1 (cold start): {t1:.0f} s; map {c['keyframes']} keyframes, {c['edges']} edges, "
          f"{c['occupancy_cells']} cells, {int(np.isfinite(maps[0].layers['floor_markers'][:, 0]).sum())} markers")
    rng = np.random.default_rng(args.seed)
    table, record = [], {"world": base, "estimator": args.estimator, "markers": args.markers, "trials": {},
                         "iou": {}, "iou_co_observed": {}, "changes": {}, "dynamic": {}}
    for flight in (1, 2):
        if not args.skip_trials:
            rows = trials(maps[-1], scenario(base, flight), args.seed, args.starts, args.budget_s, rng, frame)
            record["trials"][flight + 1] = rows
            for markers in (True, False):
                table.append({"flight": flight + 1, "markers": "yes" if markers else "no",
                              **summarise(rows, markers)})
        est, t, walls_next = session(scenario(base, flight), args.seed, maps[-1], world, lifelong, survey,
                                     args.survey_sigma)
        if not est.relocalised:
            print(f"flight {flight + 1} session never relocalised; no map to compare")
            break
        maps.append(est.snapshot())
        if args.maps_dir:
            est.save_map(f"{args.maps_dir}/flight{flight + 1}.db")
        exact, tol = record["iou"][f"{flight}-{flight + 1}"] = iou(maps[-2], maps[-1])
        co = record["iou_co_observed"][f"{flight}-{flight + 1}"] = co_observed_iou(maps[-2], maps[-1])
        ch = record["changes"][f"{flight}-{flight + 1}"] = changes(maps[-2], maps[-1], walls, walls_next, frame)
        dy = moved_in_dynamic(est, walls, walls_next, frame) if lifelong else None
        walls = walls_next
        print(f"flight {flight + 1} session: {t:.0f} s, relocalised at step {est.accepted_step}, "
              f"{est.map_loops} loops into the saved map; static layer IoU vs flight {flight}: {exact:.3f} "
              f"(one-cell tolerance: {tol:.3f}; on cells both observed: {co:.3f}; outside the moved pallets: "
              f"{ch['iou_outside_moved']:.3f}); {len(occupied_cells(maps[-2]))} -> {len(occupied_cells(maps[-1]))} "
              f"static cells, {ch['differ_on_moved']:.0f} differ on the moved pallets, "
              f"{ch['differ_elsewhere']:.0f} elsewhere; "
              f"{ch['moved_pallet_faces']:.0f} pallet faces moved: {ch['added_cells']:.0f} cells joined the static "
              f"layer ({ch['added_on_new_pallets']:.0%} on a new pallet place), {ch['removed_cells']:.0f} left it "
              f"({ch['removed_on_old_pallets']:.0%} on an old one); {ch['new_pallet_cells_in_static']:.0%} of the "
              "new pallet faces' cells are static")
        if dy is not None:
            record["dynamic"][f"{flight}-{flight + 1}"] = dy
            print(f"  end of flight {flight + 1}: the dynamic layer holds {dy['dynamic_cells']:.0f} cells "
                  f"({dy['changed_cells']:.0f} changes to the loaded map); of the {dy['new_pallet_cells']:.0f} cells "
                  f"of the new pallet faces {dy['new_pallet_cells_dynamic']:.0f} are in it "
                  f"({dy['new_pallet_margin_dynamic']:.0f} dynamic cells within one cell of them); "
                  f"{dy['removals_held']:.0f} static cells await removal ({dy['removals_held_on_old_pallets']:.0f} "
                  "of them on the old pallet places)")
    print_table(table)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({**record, "table": table}, fh, indent=1, default=float)


if __name__ == "__main__":
    main()
