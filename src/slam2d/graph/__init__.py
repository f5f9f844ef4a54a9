"""Graph SLAM back end: factor graph, sparse Gauss-Newton / Levenberg-Marquardt, robust kernels, marginals."""

from slam2d.graph.factors import KINDS as KINDS
from slam2d.graph.graph import FactorGraph as FactorGraph
from slam2d.graph.graph import GraphError as GraphError
from slam2d.graph.graph import Values as Values
from slam2d.graph.linear import SolverError as SolverError
from slam2d.graph.linear import available_solvers as available_solvers
from slam2d.graph.marginals import Marginals as Marginals
from slam2d.graph.marginals import density_arrays as density_arrays
from slam2d.graph.marginals import marginal_covariances as marginal_covariances
from slam2d.graph.optimizer import Optimizer as Optimizer
from slam2d.graph.optimizer import OptimizerConfig as OptimizerConfig
from slam2d.graph.optimizer import Summary as Summary
from slam2d.graph.optimizer import optimize as optimize
from slam2d.graph.problem import Analysis as Analysis
from slam2d.graph.problem import chi2 as chi2
from slam2d.graph.problem import chi2_by_kind as chi2_by_kind
