"""Data association: one interface (``associate``), several methods; see ``base.py`` for the contract."""

from slam2d.association.api import associate as associate
from slam2d.association.base import CLUTTER as CLUTTER
from slam2d.association.base import METHODS as METHODS
from slam2d.association.base import NEW as NEW
from slam2d.association.base import AssociationConfig as AssociationConfig
from slam2d.association.base import AssociationResult as AssociationResult
from slam2d.association.base import Candidates as Candidates
from slam2d.association.base import associate_known as associate_known
from slam2d.association.base import resolve_method as resolve_method
from slam2d.association.gating import gate_thresholds as gate_thresholds
from slam2d.association.gating import joint_thresholds as joint_thresholds
from slam2d.association.predict import candidates_from_belief as candidates_from_belief
from slam2d.association.predict import candidates_from_pose_belief as candidates_from_pose_belief
from slam2d.association.predict import innovation_covariance as innovation_covariance
from slam2d.association.predict import joint_innovation_covariance as joint_innovation_covariance
