"""elastic_jax: elastic shape analysis of spherical surfaces (split metrics, Su et al. 2020)."""

from . import datasets as datasets
from . import shapes as shapes
from ._errors import ConvergenceWarning as ConvergenceWarning
from ._errors import InputError as InputError
from ._geodesics.geodesic import GeodesicResult as GeodesicResult
from ._geodesics.geodesic import geodesic as geodesic
from ._geodesics.geodesic import upsample_coefficients as upsample_coefficients
from ._geodesics.shooting import ShootingResult as ShootingResult
from ._geodesics.shooting import exp as exp
from ._geodesics.shooting import shoot as shoot
from ._geodesics.srnf_inverse import SrnfGeodesic as SrnfGeodesic
from ._geodesics.srnf_inverse import SrnfInversion as SrnfInversion
from ._geodesics.srnf_inverse import srnf_geodesic as srnf_geodesic
from ._geodesics.srnf_inverse import srnf_invert as srnf_invert
from ._geodesics.transport import TransportResult as TransportResult
from ._geodesics.transport import parallel_transport as parallel_transport
from ._geometry.differential import differential as differential
from ._geometry.energy import EnergyDensity as EnergyDensity
from ._geometry.energy import energy_density as energy_density
from ._geometry.energy import path_energy as path_energy
from ._geometry.energy import path_length as path_length
from ._geometry.energy import straight_path as straight_path
from ._geometry.grid import grid_angles as grid_angles
from ._geometry.grid import integrate as integrate
from ._geometry.grid import quadrature_weights as quadrature_weights
from ._geometry.grid import sphere_points as sphere_points
from ._geometry.harmonics import SphericalHarmonics as SphericalHarmonics
from ._geometry.harmonics import max_degree as max_degree
from ._geometry.harmonics import real_sph_harm as real_sph_harm
from ._geometry.harmonics import surface_basis as surface_basis
from ._geometry.harmonics import vector_field_basis as vector_field_basis
from ._geometry.interp import resample as resample
from ._geometry.metric import SplitMetric as SplitMetric
from ._geometry.metric import base_inner as base_inner
from ._geometry.metric import elastic_metric_inner as elastic_metric_inner
from ._geometry.metric import metric_inner as metric_inner
from ._geometry.metric import split_inner as split_inner
from ._geometry.metric import split_parts as split_parts
from ._geometry.reparam import diffeomorphism as diffeomorphism
from ._geometry.reparam import diffeomorphism_bound as diffeomorphism_bound
from ._geometry.reparam import jacobian_determinant as jacobian_determinant
from ._geometry.reparam import moebius as moebius
from ._geometry.reparam import reparametrize as reparametrize
from ._geometry.reparam import rotate_parametrization as rotate_parametrization
from ._geometry.smoothing import smooth_surface as smooth_surface
from ._geometry.so3 import hat as hat
from ._geometry.so3 import icosahedral_group as icosahedral_group
from ._geometry.so3 import so3_exp as so3_exp
from ._geometry.so3 import so3_log as so3_log
from ._geometry.so3 import vee as vee
from ._geometry.srnf import center as center
from ._geometry.srnf import srnf as srnf
from ._geometry.srnf import srnf_distance as srnf_distance
from ._geometry.srnf import srnf_path_length as srnf_path_length
from ._geometry.srnf import surface_area as surface_area
from ._geometry.validation import validate_surface as validate_surface
from ._options import ShapeOptions as ShapeOptions
from ._registration.records import Levels as Levels
from ._registration.records import Refinement as Refinement
from ._registration.records import ShapeGeodesicResult as ShapeGeodesicResult
from ._registration.shape import shape_geodesic as shape_geodesic
from ._registration.warmup import WarmupReport as WarmupReport
from ._registration.warmup import warmup as warmup
from ._results import RESULTS as RESULTS
from ._runtime import precision as _precision
from ._runtime.cache import clear_caches as clear_caches
from ._runtime.cache import enable_compilation_cache as enable_compilation_cache
from ._statistics.distances import DistanceMatrixResult as DistanceMatrixResult
from ._statistics.distances import distance_matrix as distance_matrix
from ._statistics.driver import JobOptions as JobOptions
from ._statistics.fit import MetricFit as MetricFit
from ._statistics.fit import fit_metric as fit_metric
from ._statistics.karcher import KarcherResult as KarcherResult
from ._statistics.karcher import karcher_mean as karcher_mean
from ._statistics.log import LogResult as LogResult
from ._statistics.log import log as log
from ._statistics.pca import TangentPCA as TangentPCA
from ._statistics.pca import mode_path as mode_path
from ._statistics.pca import sigmas_reached as sigmas_reached
from ._statistics.pca import tangent_pca as tangent_pca
from ._statistics.retrieval import RetrievalScores as RetrievalScores
from ._statistics.retrieval import retrieval_scores as retrieval_scores
from ._version import VERSION as __version__  # noqa: F401  (elastic_jax.__version__)

# The public API (the pages of docs/api/ document each; tests/test_structure.py pins the list).
__all__ = [
    "ConvergenceWarning",
    "DistanceMatrixResult",
    "EnergyDensity",
    "GeodesicResult",
    "InputError",
    "JobOptions",
    "KarcherResult",
    "Levels",
    "LogResult",
    "MetricFit",
    "RESULTS",
    "Refinement",
    "RetrievalScores",
    "ShapeGeodesicResult",
    "ShapeOptions",
    "ShootingResult",
    "SphericalHarmonics",
    "SplitMetric",
    "SrnfGeodesic",
    "SrnfInversion",
    "TangentPCA",
    "TransportResult",
    "WarmupReport",
    "base_inner",
    "center",
    "clear_caches",
    "diffeomorphism",
    "diffeomorphism_bound",
    "differential",
    "distance_matrix",
    "elastic_metric_inner",
    "enable_compilation_cache",
    "energy_density",
    "exp",
    "fit_metric",
    "geodesic",
    "grid_angles",
    "hat",
    "icosahedral_group",
    "integrate",
    "jacobian_determinant",
    "karcher_mean",
    "log",
    "max_degree",
    "metric_inner",
    "mode_path",
    "moebius",
    "parallel_transport",
    "path_energy",
    "path_length",
    "quadrature_weights",
    "real_sph_harm",
    "reparametrize",
    "resample",
    "retrieval_scores",
    "rotate_parametrization",
    "shape_geodesic",
    "shoot",
    "sigmas_reached",
    "smooth_surface",
    "so3_exp",
    "so3_log",
    "sphere_points",
    "split_inner",
    "split_parts",
    "srnf",
    "srnf_distance",
    "srnf_geodesic",
    "srnf_invert",
    "srnf_path_length",
    "straight_path",
    "surface_area",
    "surface_basis",
    "tangent_pca",
    "upsample_coefficients",
    "validate_surface",
    "vector_field_basis",
    "vee",
    "warmup",
]


# Each public function traces its float32 products at float32's own precision (on recent
# GPUs JAX's default is TensorFloat-32, ~1e-3: _runtime/precision.py), unless the caller has
# chosen a precision. The internal modules are called from these.
_precision.trace_public_at_full_precision(globals(), __all__)

_SUBMODULES = ("cli", "io", "plot")


def __getattr__(name: str):
    # io (trimesh) and plot (matplotlib) load on first use: `import elastic_jax` stays light.
    if name in _SUBMODULES:
        import importlib

        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
