"""Each chapter's "Check:" question: one multiple-choice question per page, with feedback for every answer.

The page shows the question and the choices (never which one is right); the server judges an answer and sends back
the feedback written for that choice, so a wrong answer explains what it overlooks.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Check:
    question: str
    choices: tuple[str, ...]
    answer: int
    """index of the right choice"""
    feedback: tuple[str, ...]
    """one explanation per choice"""

    def __post_init__(self) -> None:
        if len(self.choices) != len(self.feedback) or not 0 <= self.answer < len(self.choices):
            raise ValueError(f"check {self.question!r}: one feedback per choice and a valid answer index")

    def describe(self) -> dict[str, Any]:
        return {"question": self.question, "choices": list(self.choices)}

    def judge(self, choice: int) -> dict[str, Any]:
        return {"type": "feedback", "choice": choice, "correct": choice == self.answer,
                "message": self.feedback[choice]}


CHECKS: dict[str, Check] = {
    "problem": Check(
        "Why can the robot not simply draw its map from odometry alone?",
        ("Odometry errors add up, so every landmark placed from the drifting pose drifts with it",
         "Odometry cannot measure turning, only distance",
         "The landmarks move while the robot drives"),
        0,
        ("Right: a map drawn from a drifting pose inherits the drift. SLAM uses the landmarks it re-observes to pull "
         "the pose back, and the pose to place the landmarks.",
         "Not quite: wheel odometry measures turning too (the dθ of every step). The trouble is that each reading "
         "is a little wrong and the errors accumulate.",
         "Not here: the landmarks in these worlds never move (the forklifts in the warehouse are the exception, and "
         "a good SLAM system must ignore them). Look at how the blue path wanders from the green one.")),
    "maps": Check(
        "Which representation tells a robot directly where it may drive?",
        ("A list of landmark positions", "An occupancy grid", "The raw lidar points"),
        1,
        ("A landmark list says where a few distinctive points are, nothing about the free floor between them.",
         "Right: each cell holds the probability that it is occupied, so free space is explicit and a planner can "
         "search the free cells.",
         "Raw points mark where beams hit something, but not that the space the beams crossed was free; the grid "
         "records both.")),
    "drift": Check(
        "Set the odometry noise to 0. What does the ATE readout show?",
        ("Exactly 0: with perfect odometry dead reckoning is the true path",
         "A small value that still grows with distance",
         "The same as with the default noise"),
        0,
        ("Right: every error in dead reckoning comes from the odometry, so with none the estimate is the truth. "
         "Now raise the noise and watch the error grow with the distance driven.",
         "Try it: with noise 0 there is nothing to accumulate, so there is no drift at all.",
         "Try it: the readout falls to 0, because dead reckoning has no other source of error than odometry.")),
    "features": Check(
        "You raise the corner threshold. What happens to precision and recall?",
        ("Precision tends to rise and recall to fall", "Both rise", "Both fall"),
        0,
        ("Right: a higher threshold keeps only the strongest responses, which are mostly real corners (precision "
         "up), but weak real corners are dropped too (recall down).",
         "A stricter threshold cannot find more of the true corners, so recall cannot rise.",
         "The corners that survive a higher threshold are the strongest ones, which are rarely false, so precision "
         "usually rises.")),
    "association": Check(
        "With a very uncertain pose, why does JCBB make fewer wrong matches than nearest neighbour?",
        ("It judges the matches together, using the correlation that one shared pose error creates",
         "It uses a wider gate for each observation",
         "It ignores the pose uncertainty"),
        0,
        ("Right: a pose error shifts all predictions the same way, so the right set of matches is jointly "
         "consistent while a set of individually plausible wrong ones is not.",
         "JCBB uses the same chi-square gate; what differs is that the matches are tested jointly, with S_joint.",
         "The opposite: the pose uncertainty is exactly what S_joint describes, and what JCBB exploits.")),
    "ekf": Check(
        "EKF-SLAM with N landmarks in its state: how does the cost of one update grow with N?",
        ("Like N² (the full covariance is updated)", "Like N", "It does not depend on N"),
        0,
        ("Right: one observation changes the whole (3+2N)×(3+2N) covariance through its correlations (watch the "
         "heat map fill up), so each update costs O(N²).",
         "The Jacobian is sparse, but the covariance update touches every pair of state entries: O(N²).",
         "A bigger map means a bigger covariance matrix to update, and each update touches all of it.")),
    "fastslam": Check(
        "The N_eff readout falls far below the number of particles. What does that mean?",
        ("A few particles carry most of the weight, so it is time to resample",
         "The map is complete",
         "The robot has stopped"),
        0,
        ("Right: N_eff = 1 / Σ w² counts how many particles really contribute. When it drops, resampling copies the "
         "good ones and drops the rest.",
         "N_eff says nothing about the map; it measures how unevenly the weights are spread.",
         "A stopped robot still gets weighted by its observations; N_eff is about the spread of the weights.")),
    "graph": Check(
        "Why is the information matrix Ω of graph SLAM sparse?",
        ("Each factor involves only the few variables it measures",
         "Because its inverse, the covariance, is sparse",
         "Gauss-Newton removes small entries at every iteration"),
        0,
        ("Right: a factor adds a block only where its own variables meet (see the matrix on the right), so most "
         "pairs of variables are never coupled.",
         "The covariance is dense (everything is correlated through the path); its inverse is the sparse one.",
         "Gauss-Newton removes nothing; the pattern is fixed by which variables share a factor.")),
    "loop": Check(
        "After a loop closure, why do poses far from the loop's two ends move as well?",
        ("Odometry factors chain every pose, so the correction spreads along the whole path",
         "The optimiser moves poses at random to lower the cost",
         "Only the landmarks move; the poses stay"),
        0,
        ("Right: the closure pulls the newest pose towards the oldest, and every odometry factor in between passes a "
         "share of that correction on — compare the grey ghost with the blue path.",
         "Gauss-Newton is deterministic: each pose moves exactly as far as the factors require.",
         "Press close loop now and compare the ghost with the path: the poses move, all the way round.")),
    "simulator": Check(
        "Drive into an unexplored part of the room with the EKF. When does the robot's uncertainty shrink again?",
        ("When it re-observes landmarks it mapped earlier", "As soon as it stops", "Never: it only grows"),
        0,
        ("Right: a landmark already in the map carries information from before, so seeing it again tightens the "
         "pose (and, through the correlations, the rest of the map).",
         "Standing still adds no new information (and the odometry noise model still adds some uncertainty).",
         "It grows while only new landmarks are seen, but re-observing a mapped one shrinks it at once.")),
    "connections": Check(
        "A lidar scan matcher (ICP) gives the back end what, in place of landmark observations?",
        ("A measured relative pose between two scans: a between factor, like odometry but from the world",
         "The ids of the landmarks",
         "The absolute position of the robot"),
        0,
        ("Right: aligning two scans measures how the robot moved between them; the graph treats it like an "
         "odometry factor, and a match to an old scan is a loop closure.",
         "Scan matching has no landmarks and no ids: it aligns raw points.",
         "It is relative: it says how two poses relate, not where either one is.")),
    "warehouse": Check(
        "Two aisles look the same to the lidar. What should relocalisation do until something tells them apart?",
        ("Keep both hypotheses and accept neither until one clearly wins (or a floor marker confirms it)",
         "Pick the aisle with the slightly better scan match at once",
         "Give up and start a new map"),
        0,
        ("Right: a wrong aisle accepted is worse than no answer; the hypotheses collapse only when the evidence "
         "(more scans while moving, a marker id) separates them, and the status stays undecided until then.",
         "A small score difference between mirror-image places is noise (a forklift, a moved pallet); accepting "
         "it is how a wrong relocalisation happens.",
         "The saved map is still right; it is the pose in it that is unknown.")),
}
