"""The loop-closure lesson in numbers: drift around the 200 m loop, one constraint, the whole path bends back.

``loop_closure_experiment`` drives online graph SLAM around the ``loop`` scenario with loop closure off (the robot
never recognises old landmarks), then, at the end, lets place recognition close the loop once. It reports the final
pose error before and after, the ATE with loop closure on / off, and how the correction is spread along the path:
it grows with the distance travelled from the anchor (the first pose), as the lesson derives for a chain of
odometry constraints.

``offset_puzzle`` reproduces the lesson's "2 m offset": the loop closure fires, but with overconfident odometry
(or a weak loop constraint) the optimum keeps a gap; the diagnosis is in the normalised residuals of each factor type.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from slam2d.eval.trajectory import ate
from slam2d.geometry import se2
from slam2d.lab.registry import make_config
from slam2d.lab.runner import run
from slam2d.log import Log
from slam2d.sim.simulator import simulate, spawn_streams


def _graph(log: Log, overrides: dict[str, Any]) -> Any:
    from slam2d.graph.online import GraphSLAM

    return GraphSLAM(make_config("graph", overrides, log.metadata))


def loop_closure_experiment(seed: int = 0) -> dict[str, Any]:
    """Numbers for the loop-closure lesson on the ``loop`` scenario (see the module docstring)."""
    log = simulate("loop", seed)
    assert log.true_poses is not None
    est = _graph(log, {"loop_closure": "false"})
    rng = spawn_streams(seed)["estimator"]
    res_off = run(est, log, rng=rng)
    before = res_off.trajectory.copy()
    closed = est.close_loop_now(log.observations_at(log.num_steps).z)
    after = est.estimate().trajectory
    truth = log.true_poses
    res_on = run(_graph(log, {}), log, rng=spawn_streams(seed)["estimator"])
    travelled = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(truth[:, :2], axis=0).T))])
    correction = np.hypot(*(after[:, :2] - before[:, :2]).T)
    quart = np.quantile(travelled, [0.25, 0.5, 0.75, 1.0])
    idx = [int(np.searchsorted(travelled, q)) for q in quart]
    idx[-1] = len(travelled) - 1
    return {
        "seed": seed,
        "loop_closed": bool(closed),
        "final_error_before_m": float(np.hypot(*(before[-1, :2] - truth[-1, :2]))),
        "final_error_after_m": float(np.hypot(*(after[-1, :2] - truth[-1, :2]))),
        "ate_no_loop_closure_m": float(ate(before, truth).rmse_m),
        "ate_closed_once_m": float(ate(after, truth).rmse_m),
        "ate_online_loop_closure_m": float(res_on.metrics["ate_rmse_m"]),
        "correction_at_quarter_path_m": [float(correction[i]) for i in idx],
        "correction_distance_corr": float(np.corrcoef(travelled, correction)[0, 1]) if closed else float("nan"),
    }


def offset_puzzle(seed: int = 0) -> list[dict[str, Any]]:
    """The "2 m offset" case: baseline vs overconfident odometry vs a weak loop, with the residual diagnosis."""
    log = simulate("loop", seed)
    assert log.true_poses is not None
    rows = []
    for label, over in (("baseline", {}), ("odometry information x1000", {"odometry_info_scale": "1000"}),
                        ("loop information x1e-4", {"loop_info_scale": "1e-4"})):
        est = _graph(log, {"loop_closure": "false", **over})
        run(est, log, rng=spawn_streams(seed)["estimator"])
        est.close_loop_now(log.observations_at(log.num_steps).z)
        traj = est.estimate().trajectory
        loops = [lp for lp in est.estimate().new_loops if lp.accepted]
        gap = float("nan")
        if loops:
            lp = loops[-1]
            # the gap: how far the optimised end pose sits from where the loop constraint says it should be
            gap = float(np.hypot(*se2.local(se2.between(traj[lp.a], traj[lp.b]), lp.T_a_b)[:2]))
        rows.append({
            "case": label,
            "loop_accepted": bool(loops),
            "gap_m": gap,
            "final_error_m": float(np.hypot(*(traj[-1, :2] - log.true_poses[-1, :2]))),
            "ate_m": float(ate(traj, log.true_poses).rmse_m),
            **{f"chi2_per_dof_{k}": v for k, v in est.chi2_per_dof().items()},
        })
    return rows
