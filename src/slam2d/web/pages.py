"""The lab's pages: slug, chapter number, title and the session each page's websocket gets."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import slam2d.web.tasks as web_tasks
from slam2d.web.checks import CHECKS
from slam2d.web.sessions import AssociationSession, FeaturesSession, GraphSession, MapsSession, Session, SimSession
from slam2d.web.sessions.warehouse import WarehouseSession


@dataclass(frozen=True)
class Page:
    slug: str
    number: int
    title: str
    summary: str
    build: Callable[[int], Session]

    def make(self, seed: int) -> Session:
        """A new session for this page (with the chapter's check question and try-this task)."""
        session = self.build(seed)
        session.check = CHECKS.get(self.slug)
        session.task = web_tasks.TASKS.get(self.slug)
        return session


PAGES: tuple[Page, ...] = (
    Page("problem", 0, "The SLAM problem", "a robot drives among landmarks: true vs estimated path and map",
         lambda seed: SimSession(page="problem", title="the SLAM problem", seed=seed, estimator="ekf", drive="route",
                                 controls=("estimator", "drive", "steps_per_s"))),
    Page("maps", 1, "Map representations", "one room as landmarks, lidar points, occupancy grid, topology",
         lambda seed: MapsSession(seed)),
    Page("drift", 2, "Pose and odometry drift", "dead reckoning drifts away from the truth; ATE measures how far",
         lambda seed: SimSession(page="drift", title="pose and odometry drift", seed=seed, estimator="dead-reckoning",
                                 drive="route", controls=("motion_noise", "drive", "steps_per_s"), speed=20.0)),
    Page("features", 3, "Feature extraction", "corners on a room image with a threshold slider",
         lambda seed: FeaturesSession(seed)),
    Page("association", 4, "Data association", "which observation belongs to which landmark, and when it goes wrong",
         lambda seed: AssociationSession(seed)),
    Page("ekf", 5, "EKF-SLAM", "one Gaussian over pose and map: growing state, ellipses, correlations",
         lambda seed: SimSession(page="ekf", title="EKF-SLAM", seed=seed, estimator="ekf", drive="route", heat=True,
                                 controls=("estimator", "drive", "steps_per_s", "sensor_range_m", "obs_noise",
                                           "obs_ellipses"))),
    Page("fastslam", 6, "FastSLAM", "particles, each with its own map; N_eff and resampling",
         lambda seed: SimSession(page="fastslam", title="FastSLAM", seed=seed, estimator="fastslam", drive="route",
                                 controls=("estimator", "particles", "drive", "steps_per_s", "motion_noise"))),
    Page("graph", 7, "Graph SLAM", "poses and landmarks as a factor graph, optimised together",
         lambda seed: GraphSession(seed)),
    Page("loop", 8, "Loop closure", "a drifted loop snaps back when the robot recognises its start",
         lambda seed: SimSession(page="loop", title="loop closure", seed=seed, estimator="graph", scenario="loop",
                                 drive="route", graph_view=True,
                                 controls=("estimator", "motion_noise", "steps_per_s", "loop_closure",
                                           "wrong_association", "few_landmarks"), speed=20.0,
                                 # drift enough to see, and the closure left to the button (or the switch)
                                 defaults={"loop_closure": False, "motion_noise": 4.0})),
    Page("simulator", 9, "The simulator", "drive with the arrow keys or let it explore; any estimator",
         lambda seed: SimSession(page="simulator", title="the simulator", seed=seed, estimator="ekf", drive="keys",
                                 controls=("estimator", "scenario", "landmarks", "drive", "steps_per_s",
                                           "sensor_range_m", "obs_noise", "motion_noise", "particles",
                                           "obs_ellipses", "view"))),
    Page("connections", 10, "Connections", "what lidar, visual and multi-robot SLAM add to what you have seen",
         lambda seed: MapsSession(seed, page="connections", title="connections", layer="points")),
    Page("warehouse", 11, "The warehouse design challenge", "saved maps, relocalisation in identical aisles, "
         "forklifts; the five questions with measured answers", lambda seed: WarehouseSession(seed)),
)

PAGE_BY_SLUG = {p.slug: p for p in PAGES}
