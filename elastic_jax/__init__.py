"""elastic_jax: elastic shape analysis of spherical surfaces (split metrics, Su et al. 2020)."""

from . import shapes as shapes
from ._differential import differential as differential
from ._energy import path_energy as path_energy
from ._energy import path_length as path_length
from ._energy import straight_path as straight_path
from ._errors import InputError as InputError
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
from ._srnf_inverse import SrnfGeodesic as SrnfGeodesic
from ._srnf_inverse import SrnfInversion as SrnfInversion
from ._srnf_inverse import srnf_geodesic as srnf_geodesic
from ._srnf_inverse import srnf_invert as srnf_invert
from ._transport import TransportResult as TransportResult
from ._transport import parallel_transport as parallel_transport
from ._validation import validate_surface as validate_surface

__version__ = "0.1.0"
from ._cache import enable_compilation_cache as enable_compilation_cache
from ._errors import ConvergenceWarning as ConvergenceWarning
from ._geodesic import GeodesicResult as GeodesicResult
from ._geodesic import geodesic as geodesic
from ._geodesic import upsample_coefficients as upsample_coefficients
from ._harmonics import SphericalHarmonics as SphericalHarmonics
from ._harmonics import max_degree as max_degree
from ._harmonics import real_sph_harm as real_sph_harm
from ._harmonics import surface_basis as surface_basis
from ._harmonics import vector_field_basis as vector_field_basis
from ._interp import resample as resample
from ._karcher import DistanceMatrixResult as DistanceMatrixResult
from ._karcher import KarcherResult as KarcherResult
from ._karcher import distance_matrix as distance_matrix
from ._karcher import karcher_mean as karcher_mean
from ._options import ShapeOptions as ShapeOptions
from ._pca import TangentPCA as TangentPCA
from ._pca import mode_path as mode_path
from ._pca import tangent_pca as tangent_pca
from ._reparam import diffeomorphism as diffeomorphism
from ._reparam import diffeomorphism_bound as diffeomorphism_bound
from ._reparam import jacobian_determinant as jacobian_determinant
from ._reparam import moebius as moebius
from ._reparam import reparametrize as reparametrize
from ._reparam import rotate_parametrization as rotate_parametrization
from ._shape import Refinement as Refinement
from ._shape import ShapeGeodesicResult as ShapeGeodesicResult
from ._shape import shape_geodesic as shape_geodesic
from ._shooting import LogResult as LogResult
from ._shooting import ShootingResult as ShootingResult
from ._shooting import exp as exp
from ._shooting import log as log
from ._shooting import shoot as shoot
from ._so3 import hat as hat
from ._so3 import icosahedral_group as icosahedral_group
from ._so3 import so3_exp as so3_exp
from ._so3 import so3_log as so3_log
from ._so3 import vee as vee
from ._solvers import RESULTS as RESULTS

_SUBMODULES = ("cli", "io", "plot")


def __getattr__(name: str):
    # io (trimesh) and plot (matplotlib) load on first use: `import elastic_jax` stays light.
    if name in _SUBMODULES:
        import importlib

        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
