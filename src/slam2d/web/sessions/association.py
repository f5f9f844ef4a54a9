"""Page 4: a frozen moment of data association: which observation belongs to which landmark."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from slam2d.association import (
    CLUTTER,
    METHODS,
    AssociationConfig,
    AssociationResult,
    Candidates,
    associate,
    candidates_from_pose_belief,
)
from slam2d.log import Observations
from slam2d.models.sensors import SensorConfig, range_bearing, range_bearing_inverse, sense_landmarks
from slam2d.web.params import Param
from slam2d.web.sessions.base import Sections, Session, seed_param

ASSOCIATION_LABELS = {
    "observations": "observations",
    "matched": "matched to a landmark",
    "correct": "correct matches",
    "wrong": "wrong matches",
    "new_or_clutter": "declared new or clutter",
    "precision": "precision (correct / matched)",
    "recall": "recall (correct / matchable)",
    "joint_nis": "joint NIS of the matches",
    "search_nodes": "search nodes visited",
    "truncated": "stopped at the time budget (1 = yes)",
}

#: wall time one association may take; JCBB then returns its best hypothesis so far, flagged truncated
TIME_BUDGET_S = 1.0


class AssociationSession(Session):
    """Landmarks, a robot whose believed pose is off by a sampled error, and its observations.

    Candidates are predicted from the believed pose (:func:`slam2d.association.candidates_from_pose_belief`: the
    map is taken as known, so the whole ambiguity comes from pose uncertainty and sensor noise), and the chosen
    method assigns observations.
    """

    page = "association"
    title = "data association"
    scalars = tuple(ASSOCIATION_LABELS)
    labels = ASSOCIATION_LABELS

    def __init__(self, seed: int = 0) -> None:
        params = [
            Param("method", "method", "choice", "mahalanobis", choices=METHODS),
            Param("pose_sigma_m", "pose uncertainty (m)", "float", 0.3, lo=0.0, hi=2.0, step=0.05,
                  help="standard deviation of the believed robot position; heading sigma is this / 5 m (rad)"),
            Param("landmarks", "landmarks", "int", 40, lo=2, hi=300, step=1),
            Param("obs_noise", "observation noise (× default)", "float", 1.0, lo=0.1, hi=10.0, step=0.1),
            seed_param(),
        ]
        super().__init__(params, seed)
        self.actions = (("scramble", "scramble"),)
        self._greedy: tuple[str, int, int] | None = None
        self.rng = np.random.default_rng(int(self.values["seed"]))
        self._draw_scene()

    def bounds(self) -> tuple[float, float, float, float]:
        return (0.0, 0.0, 16.0, 12.0)

    def on_param(self, name: str, value: Any, old: Any) -> None:
        if name == "seed":
            self.rng = np.random.default_rng(int(value))
            self._draw_scene()
        elif name in ("landmarks", "pose_sigma_m", "obs_noise"):
            self._draw_scene()
        else:
            self._associate_now()

    def on_action(self, name: str) -> None:
        self._draw_scene()

    def _draw_scene(self) -> None:
        rng = self.rng
        n = int(self.values["landmarks"])
        self.landmarks = rng.uniform([0.5, 0.5], [15.5, 11.5], size=(n, 2))
        self.true_pose = np.array([8.0, 6.0, rng.uniform(-np.pi, np.pi)])
        s = float(self.values["pose_sigma_m"])
        self.pose_cov = np.diag([s * s, s * s, (s / 5.0) ** 2]) + 1e-12 * np.eye(3)
        self.belief = self.true_pose + rng.multivariate_normal(np.zeros(3), self.pose_cov)
        k = float(self.values["obs_noise"])
        base = SensorConfig()
        self.sensor = dataclasses.replace(base, max_range_m=6.0, range_std_m=base.range_std_m * k,
                                          bearing_std_rad=base.bearing_std_rad * k)
        z, ids, _ = sense_landmarks(self.true_pose, self.landmarks, np.arange(n), self.sensor, rng)
        self.obs = Observations(z[:, 0], z[:, 1], ids.astype(np.int64))
        self._associate_now()

    def candidates(self) -> Candidates:
        """Every landmark within reach of the belief (range plus a margin for the pose error) is a candidate."""
        zp = range_bearing(self.belief, self.landmarks)
        near = np.flatnonzero(zp[:, 0] <= self.sensor.max_range_m + 3.0)
        return candidates_from_pose_belief(self.belief, self.pose_cov, self.landmarks[near], near,
                                           self.sensor.covariance)

    def _associate_now(self) -> None:
        cands = self.candidates()
        method = str(self.values["method"])
        self.notices = [n for n in self.notices if not n.startswith("association method")]
        cfg = AssociationConfig(method=method, jcbb_time_budget_s=TIME_BUDGET_S)  # type: ignore[arg-type]
        try:
            res = associate(self.obs, cands, cfg, rng=self.rng)
        except Exception as e:  # show the failure on the page instead of losing the session
            self.notices.append(f"association method {method!r} failed: {type(e).__name__}: {e}")
            res = AssociationResult(np.full(len(self.obs), CLUTTER, dtype=np.int64), np.full(len(self.obs), np.nan))
        if res.truncated:
            self.notices.append(f"association method {method!r} stopped at its {TIME_BUDGET_S:g} s time budget after "
                                f"{res.nodes} search nodes: the matches shown are the best found so far, not proven "
                                "the best.")
        self.result = res
        self.cands = cands
        self._watch_task(method)

    def _watch_task(self, method: str) -> None:
        """Wrong matches with a greedy method at >= 1 m pose uncertainty, then the same with JCBB."""
        if float(self.values["pose_sigma_m"]) < 1.0:
            return
        a = np.asarray(self.result.assignment)
        matched = a >= 0
        wrong = int((matched & (a != self.obs.landmark_id)).sum())
        if method in ("nn", "mahalanobis"):
            self._greedy = (method, wrong, int(matched.sum()))
        elif method == "jcbb" and self._greedy is not None:
            g, w0, m0 = self._greedy
            cut = " (stopped at its time budget: the best found so far)" if self.result.truncated else ""
            self.complete_task(f"Done: at {float(self.values['pose_sigma_m']):g} m pose uncertainty {g} made {w0} "
                               f"wrong of {m0} matches; jcbb made {wrong} wrong of {int(matched.sum())}{cut}. JCBB "
                               "accepts only matches that are jointly consistent: one shared pose error must explain "
                               "them all.")

    def rows(self) -> list[str]:
        method = self.values["method"]
        skip = set() if method == "jcbb" else {"truncated"}
        if method not in ("jcbb", "ransac"):
            skip.add("search_nodes")
        return [s for s in self.scalars if s not in skip]

    def numbers(self) -> dict[str, float]:
        a = np.asarray(self.result.assignment)
        truth = self.obs.landmark_id
        matched = a >= 0
        correct = matched & (a == truth)
        reachable = np.isin(truth, self.cands.ids)
        n_match = int(matched.sum())
        return {"observations": float(len(a)), "matched": float(n_match), "correct": float(correct.sum()),
                "wrong": float(n_match - int(correct.sum())), "new_or_clutter": float((~matched).sum()),
                "precision": float(correct.sum() / n_match) if n_match else float("nan"),
                "recall": float(correct.sum() / reachable.sum()) if reachable.any() else float("nan"),
                "joint_nis": float(self.result.joint_nis), "search_nodes": float(self.result.nodes),
                "truncated": float(self.result.truncated)}

    def sections(self) -> Sections:
        nums = self.numbers()
        a = np.asarray(self.result.assignment)
        obs_xy = range_bearing_inverse(np.broadcast_to(self.belief, (len(self.obs), 3)), self.obs.z) \
            if len(self.obs) else np.zeros((0, 2))
        m = a >= 0
        lines = np.hstack([obs_xy[m], self.landmarks[a[m]], (a[m] == self.obs.landmark_id[m])[:, None]]) \
            if m.any() else np.zeros((0, 5))
        return [
            ("NUMS", np.array([nums[k] for k in self.scalars])),
            ("TLMK", self.landmarks),
            ("TPOS", self.true_pose),
            ("EPOS", self.belief),
            ("PCOV", self.pose_cov[:2, :2].reshape(1, 4)),
            ("OBSV", obs_xy),
            ("MTCH", lines),
            ("NEWO", obs_xy[~m]),
        ]
