"""``slam2d optimize``: read a g2o / TORO / iSAM graph, optimise it, write g2o and (optionally) a JSON summary."""

from __future__ import annotations

import argparse
import sys
from typing import Any

import numpy as np

from slam2d.cli.common import add_force_argument, check_number, check_outputs, write_json
from slam2d.graph import FactorGraph, OptimizerConfig, Values, optimize
from slam2d.graph.initialization import chordal_poses, initial_points
from slam2d.io import FORMATS, read_graph, write_g2o
from slam2d.io.atomic import atomic_path
from slam2d.io.g2o import point_id_shift


def register(sub: Any) -> None:
    p = sub.add_parser("optimize", help="optimise a pose / landmark graph file",
                       description="Optimise a 2D graph (g2o, TORO or iSAM text) with Gauss-Newton, "
                                   "Levenberg-Marquardt or Powell's dog leg; chi2 is g2o's sum of e^T Omega e.")
    p.add_argument("input", metavar="IN", help="graph file")
    p.add_argument("--format", choices=sorted(FORMATS), default=None,
                   help="input format (default: from the extension .g2o/.graph/.isam, else from the tags)")
    p.add_argument("--out", required=True, metavar="OUT.g2o", help="write the optimised graph here (g2o)")
    p.add_argument("--solver", choices=["gn", "lm", "dogleg"], default="lm", help="optimiser (default lm)")
    p.add_argument("--robust", default=None, metavar="KERNEL[:PARAM]",
                   help="robust kernel on every factor: huber, cauchy or dcs, optional parameter (default 1)")
    p.add_argument("--init", choices=["file", "chordal"], default="file",
                   help="initial guess: the file's vertices / spanning tree (default) or chordal relaxation")
    p.add_argument("--max-iterations", type=int, default=100, help="iteration cap of the solver (default 100)")
    p.add_argument("--lambda-initial", type=float, default=OptimizerConfig().lambda_initial_factor,
                   help="LM initial damping (relative to diag H; default %(default)g; Victoria Park needs ~1)")
    p.add_argument("--linear-solver", default="auto", help="auto, qdldl, cholmod, splu or dense")
    p.add_argument("--json", default=None, metavar="OUT", help="write a JSON summary")
    add_force_argument(p)
    p.set_defaults(func=cmd)


def _kernel(spec: str | None) -> tuple[str | None, float]:
    if spec is None:
        return None, 1.0
    name, _, param = spec.partition(":")
    try:
        value = float(param) if param else 1.0
    except ValueError:
        raise ValueError(f"--robust: parameter {param!r} is not a number") from None
    check_number("--robust parameter", value, low=1e-12, high=1e12)
    return name.lower(), value


def _chordal(graph: FactorGraph, values: Values, fixed: Any) -> Values:
    poses = chordal_poses(graph, values.pose_keys, fixed)
    pts = initial_points(graph, values.pose_keys, poses, values.point_keys) if values.point_keys.size else values.points
    return Values(values.pose_keys, poses, values.point_keys, pts)


def cmd(args: argparse.Namespace) -> int:
    check_number("--max-iterations", args.max_iterations, low=1, high=1e6)
    check_number("--lambda-initial", args.lambda_initial, low=0, low_open=True, high=1e12)
    kernel, param = _kernel(args.robust)
    check_outputs(args, [args.input], [("--out", args.out), ("--json", args.json)])
    gf = read_graph(args.input, args.format)
    try:  # g2o has one id space: landmark ids that are also pose ids move (or fail here, before the work)
        shift = point_id_shift(gf.values.pose_keys, gf.values.point_keys)
    except ValueError as e:
        raise ValueError(f"{args.input}: {e}") from None
    cfg = OptimizerConfig(method=args.solver, max_iterations=args.max_iterations, robust_kernel=kernel,
                          robust_param=param, linear_solver=args.linear_solver,
                          lambda_initial_factor=args.lambda_initial)
    values = _chordal(gf.graph, gf.values, gf.fixed_pose_keys) if args.init == "chordal" else gf.values
    out, s = optimize(gf.graph, values, cfg, fixed_pose_keys=gf.fixed_pose_keys)
    # divergence is an error, never a result: a non-finite state or a final chi2 above the initial one
    if not (np.isfinite(s.chi2_final) and np.all(np.isfinite(out.poses)) and np.all(np.isfinite(out.points))):
        raise FloatingPointError(f"{args.input}: the {args.solver} solver diverged to a non-finite state after "
                                 f"{s.iterations} iterations ({s.termination})")
    if s.cost_final > s.cost_initial * (1 + 1e-9) + 1e-12:  # the (robust) objective, not chi2
        worst = int(np.argmax(s.cost_history)) if s.cost_history else s.iterations
        raise ValueError(f"{args.input}: the {args.solver} solver diverged: the cost rose from {s.cost_initial:.6g} "
                         f"to {s.cost_final:.6g} (largest at iteration {worst}); try --solver lm or --init file")
    record = {
        "input": str(args.input), "format": gf.format, "initial_guess": "chordal" if args.init == "chordal"
        else gf.initial_guess, "solver": args.solver, "robust": args.robust,
        "chi2_initial": s.chi2_initial, "chi2_final": s.chi2_final, "cost_final": s.cost_final,
        "iterations": s.iterations, "rejected_steps": s.rejected_steps, "termination": s.termination,
        "solve_s": s.solve_s, "linear_solver": s.linear_solver, "poses": int(out.pose_keys.size),
        "landmarks": int(out.point_keys.size), "factors": gf.graph.num_factors,
        "components": s.num_components, "gauge_pose_keys": s.gauge_pose_keys,
        "skipped_lines": gf.skipped, "point_id_offset": shift,
    }
    print(f"{args.input}: {record['poses']} poses, {record['landmarks']} landmarks, {record['factors']} factors; "
          f"chi2 {s.chi2_initial:.6g} -> {s.chi2_final:.10g} in {s.iterations} iterations ({s.termination}), "
          f"{s.solve_s:.3f} s")
    if shift:
        print(f"note: landmark ids share numbers with pose ids; written as VERTEX_XY id {shift:+d} (g2o has one id "
              "space)", file=sys.stderr)
    if s.num_components > 1:
        print(f"note: {s.num_components} disconnected components; held poses {s.gauge_pose_keys}", file=sys.stderr)
    # both outputs or neither: the graph goes to a temporary file that is renamed only after the JSON is written
    with atomic_path(args.out) as tmp:
        write_g2o(tmp, gf.graph, out, fixed_pose_keys=gf.fixed_pose_keys if gf.fixed_pose_keys.size else None)
        if args.json:
            write_json(args.json, record)
    return 0
