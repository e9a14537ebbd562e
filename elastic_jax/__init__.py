"""elastic_jax: elastic shape analysis of spherical surfaces (split metrics, Su et al. 2020)."""

from . import shapes as shapes
from ._differential import differential as differential
from ._energy import path_energy as path_energy
from ._energy import path_length as path_length
from ._energy import straight_path as straight_path
from ._grid import grid_angles as grid_angles
from ._grid import integrate as integrate
from ._grid import quadrature_weights as quadrature_weights
from ._grid import sphere_points as sphere_points
from ._metric import SplitMetric as SplitMetric
from ._metric import base_inner as base_inner
from ._metric import elastic_metric_inner as elastic_metric_inner
from ._metric import metric_inner as metric_inner
from ._metric import split_inner as split_inner
from ._metric import split_parts as split_parts
from ._srnf import center as center
from ._srnf import srnf as srnf
from ._srnf import srnf_distance as srnf_distance
from ._srnf import srnf_path_length as srnf_path_length
from ._srnf import surface_area as surface_area
from ._validation import validate_surface as validate_surface

__version__ = "0.1.0"
