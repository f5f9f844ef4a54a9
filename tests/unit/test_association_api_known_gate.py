import numpy as np

from slam2d.association import CLUTTER, AssociationConfig, Candidates, associate
from slam2d.log import Observations


def test_known_ids_outside_the_wide_gate_are_clutter_unless_trusted():
    cands = Candidates(np.array([4, 7]), np.array([[5.0, 0.0], [3.0, 1.0]]), np.stack([np.diag([0.01, 0.001])] * 2))
    obs = Observations(np.array([5.05, 9.0]), np.array([0.01, -2.0]), np.array([4, 7]))  # 2nd: a misread id
    res = associate(obs, cands, AssociationConfig(method="known"), rng=np.random.default_rng(0))
    assert res.assignment.tolist() == [4, CLUTTER]
    trusted = associate(obs, cands, AssociationConfig(method="known", known_outlier_gate=False),
                        rng=np.random.default_rng(0))
    assert trusted.assignment.tolist() == [4, 7]
