"""SE(2) geometry, angles and Gaussian helpers (numpy only)."""

from slam2d.geometry.angles import angle_diff as angle_diff
from slam2d.geometry.angles import wrap_angle as wrap_angle
from slam2d.geometry.angles import wrap_angle_scalar as wrap_angle_scalar
from slam2d.geometry.gaussian import Ellipse as Ellipse
from slam2d.geometry.gaussian import chi2_gate as chi2_gate
from slam2d.geometry.gaussian import covariance_ellipse as covariance_ellipse
from slam2d.geometry.gaussian import mahalanobis as mahalanobis
from slam2d.geometry.gaussian import mahalanobis_sq as mahalanobis_sq
from slam2d.geometry.se2 import between as between
from slam2d.geometry.se2 import between_jacobians as between_jacobians
from slam2d.geometry.se2 import compose as compose
from slam2d.geometry.se2 import compose_chain as compose_chain
from slam2d.geometry.se2 import compose_jacobians as compose_jacobians
from slam2d.geometry.se2 import exp as exp
from slam2d.geometry.se2 import exp_jacobians as exp_jacobians
from slam2d.geometry.se2 import inverse as inverse
from slam2d.geometry.se2 import inverse_jacobians as inverse_jacobians
from slam2d.geometry.se2 import inverse_transform_points as inverse_transform_points
from slam2d.geometry.se2 import inverse_transform_points_jacobians as inverse_transform_points_jacobians
from slam2d.geometry.se2 import local as local
from slam2d.geometry.se2 import log as log
from slam2d.geometry.se2 import log_jacobians as log_jacobians
from slam2d.geometry.se2 import retract as retract
from slam2d.geometry.se2 import rotation_matrix as rotation_matrix
from slam2d.geometry.se2 import transform_points as transform_points
from slam2d.geometry.se2 import transform_points_jacobians as transform_points_jacobians
