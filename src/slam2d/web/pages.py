"""The lab's pages: slug, chapter number, title and the session each page's websocket gets.

Pages discover what exists when a connection opens (the estimator registry, optional modules), so a back end that
lands later shows up without touching this file; until then the page says what is missing.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from slam2d.web.backends import optional_module
from slam2d.web.sessions import AssociationSession, FeaturesSession, GraphSession, MapsSession, Session, SimSession


@dataclass(frozen=True)
class Page:
    slug: str
    number: int
    title: str
    summary: str
    make: Callable[[int], Session]


PAGES: tuple[Page, ...] = (
    Page("problem", 0, "The SLAM problem", "a robot drives among landmarks: true vs estimated path and map",
         lambda seed: SimSession(page="problem", title="the SLAM problem", seed=seed,
                                 prefer=("ekf", "fastslam", "graph", "fastslam2"), drive="route",
                                 controls=("estimator", "drive", "steps_per_s"),
                                 need_note=", which has no map: it never estimates landmarks")),
    Page("maps", 1, "Map representations", "one room as landmarks, lidar points, occupancy grid, topology",
         lambda seed: MapsSession(seed)),
    Page("drift", 2, "Pose and odometry drift", "dead reckoning drifts away from the truth; ATE measures how far",
         lambda seed: SimSession(page="drift", title="pose and odometry drift", seed=seed, drive="route",
                                 controls=("motion_noise", "drive", "steps_per_s"), speed=20.0)),
    Page("features", 3, "Feature extraction", "corners on a room image with a threshold slider",
         lambda seed: FeaturesSession(seed)),
    Page("association", 4, "Data association", "which observation belongs to which landmark, and when it goes wrong",
         lambda seed: AssociationSession(seed)),
    Page("ekf", 5, "EKF-SLAM", "one Gaussian over pose and map: growing state, ellipses, correlations",
         lambda seed: SimSession(page="ekf", title="EKF-SLAM", seed=seed, prefer=("ekf",), drive="route",
                                 heat=True, controls=("estimator", "drive", "steps_per_s", "sensor_range_m",
                                                      "obs_noise", "obs_ellipses"))),
    Page("fastslam", 6, "FastSLAM", "particles, each with its own map; N_eff and resampling",
         lambda seed: SimSession(page="fastslam", title="FastSLAM", seed=seed, prefer=("fastslam", "fastslam2"),
                                 drive="route", controls=("estimator", "particles", "drive", "steps_per_s",
                                                          "motion_noise"))),
    Page("graph", 7, "Graph SLAM", "poses and landmarks as a factor graph, optimised together",
         lambda seed: GraphSession(seed) if optional_module("slam2d.graph") is not None else SimSession(
             page="graph", title="graph SLAM", seed=seed, prefer=("graph",), drive="route",
             controls=("estimator", "drive", "steps_per_s"),
             notes=("not available yet: the 'optimize' button animating Gauss-Newton iterations and the sparsity "
                    "view of the information matrix (they need the graph back end, slam2d.graph).",))),
    Page("loop", 8, "Loop closure", "a drifted loop snaps back when the robot recognises its start",
         lambda seed: SimSession(page="loop", title="loop closure", seed=seed, prefer=("graph",), scenario="loop",
                                 drive="route", controls=("estimator", "motion_noise", "steps_per_s", "loop_closure",
                                           "wrong_association", "few_landmarks"), speed=20.0)),
    Page("simulator", 9, "The simulator", "drive with the arrow keys or let it explore; any estimator",
         lambda seed: SimSession(page="simulator", title="the simulator", seed=seed,
                                 prefer=("ekf", "fastslam", "graph"), drive="keys",
                                 controls=("estimator", "scenario", "landmarks", "drive", "steps_per_s",
                                           "sensor_range_m", "obs_noise", "motion_noise", "particles",
                                           "obs_ellipses"))),
)

PAGE_BY_SLUG = {p.slug: p for p in PAGES}
