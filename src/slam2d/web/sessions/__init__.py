"""Per-connection sessions: each browser tab owns one simulation (and estimator) on the server.

One module per page family: ``sim`` (the simulator-backed pages), ``graph`` (batch graph SLAM), ``association``,
``maps`` (map representations and features); ``base`` holds what they share.
"""

from slam2d.web.sessions.association import AssociationSession as AssociationSession
from slam2d.web.sessions.base import Session as Session
from slam2d.web.sessions.base import abs_correlation as abs_correlation
from slam2d.web.sessions.base import block_average as block_average
from slam2d.web.sessions.base import observation_covariances as observation_covariances
from slam2d.web.sessions.graph import GraphSession as GraphSession
from slam2d.web.sessions.maps import FeaturesSession as FeaturesSession
from slam2d.web.sessions.maps import MapsSession as MapsSession
from slam2d.web.sessions.sim import SimSession as SimSession
from slam2d.web.sessions.sim import graph_view_sections as graph_view_sections
