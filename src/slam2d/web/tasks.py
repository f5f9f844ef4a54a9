"""Each chapter's "Try this" task: a prompt on the page, and a result the session writes when it sees the task done
(the detection lives in the sessions; the message quotes the numbers the library computed at that moment)."""

from __future__ import annotations

TASKS: dict[str, str] = {
    "problem": "Switch the estimator to dead-reckoning and let it drive past step 200: the page compares its "
               "trajectory error with the EKF's at the same step.",
    "maps": "Show each of the four representations in turn (landmarks, points, occupancy, topology).",
    "drift": "Set the odometry noise to 0 and let it drive 100 steps; then set it to 10 and drive 100 steps again.",
    "features": "With the default noise, slide the threshold from 0.05 or less up to 0.3 or more.",
    "association": "Raise the pose uncertainty to 1 m or more with the method nearest neighbour (nn) or mahalanobis "
                   "and count the wrong matches; then switch the method to jcbb.",
    "ekf": "Let the robot drive its round and come back to where it started: watch the ellipses when the first "
           "landmarks come back into view.",
    "fastslam": "Set the particles to 20 or fewer: the page tells you when the weights collapse and the filter "
                "resamples.",
    "graph": "Let the drive finish, then press optimize and follow the cost down to convergence.",
    "loop": "Let the robot drive once round the block; when it is back near its start, press close loop now.",
    "simulator": "Drive a big loop: leave the start by more than 10 m, then come back within 2 m of it.",
    "connections": "Switch the representation to occupancy: the same scans become free and occupied cells.",
}
