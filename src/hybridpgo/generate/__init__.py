"""Synthetic pose graphs with ground truth.

* :func:`generate_city`: a vehicle driving through a 3D street-grid city, with odometry,
  probabilistic loop closures and optional GPS (paper section IV, Table II); any size with
  :func:`scale_city`.
* :func:`generate_grid`: a Manhattan world after Olson (the M3500 family): a robot taking unit
  steps on a grid of streets, turning at intersections, with loop closures to nearby earlier
  poses; 2D (written as g2o SE2) or 3D, with presets for the hard, large-rotation-noise
  variants (:data:`GRID_PRESETS`).
* :func:`add_outliers`: false loop closures (random pairs and near misses) and the list of which
  edges are false (:func:`write_outliers`); :func:`add_pattern_outliers`: Sünderhauf and
  Protzel's four patterns (random, local, random-grouped, local-grouped);
  :func:`add_gps_outliers`: false GPS fixes (:func:`write_gps_outliers`).
* :func:`noisify`: rotation noise about the local up axis on every edge (paper Fig. 8).

Every generator returns the graph (vertex estimates: the noisy odometry chained from the true
first pose, as in M3500) with the true poses; :func:`write_ground_truth` writes them.  The same
seed gives bit-identical output.

Example (not a doctest)::

    from hybridpgo.generate import generate_grid, write_ground_truth, write_outliers
    from hybridpgo.io import write_graph

    grid = generate_grid("m3500b", seed=1, num_outliers=50)   # rotation sigma 0.2 rad
    write_graph(grid.graph, "m3500b_1.g2o")                  # EDGE_SE2 / VERTEX_SE2
    write_ground_truth("m3500b_1_gt.g2o", grid.graph, grid.truth_rotations,
                       grid.truth_translations)
    write_outliers("m3500b_1_gt.outliers.csv", grid.graph, grid.outliers)
"""

from __future__ import annotations

from ._common import MIN_SIGMA as MIN_SIGMA
from ._common import noisify as noisify
from ._common import write_ground_truth as write_ground_truth
from .city import PRESETS as PRESETS
from .city import City as City
from .city import CityParams as CityParams
from .city import generate_city as generate_city
from .city import scale_city as scale_city
from .grid import GRID_PRESETS as GRID_PRESETS
from .grid import Grid as Grid
from .grid import GridParams as GridParams
from .grid import generate_grid as generate_grid
from .outliers import OUTLIER_KINDS as OUTLIER_KINDS
from .outliers import OUTLIER_PATTERNS as OUTLIER_PATTERNS
from .outliers import GpsOutliers as GpsOutliers
from .outliers import Outliers as Outliers
from .outliers import add_gps_outliers as add_gps_outliers
from .outliers import add_outliers as add_outliers
from .outliers import add_pattern_outliers as add_pattern_outliers
from .outliers import write_gps_outliers as write_gps_outliers
from .outliers import write_outliers as write_outliers

__all__ = [
    "GRID_PRESETS",
    "MIN_SIGMA",
    "OUTLIER_KINDS",
    "OUTLIER_PATTERNS",
    "PRESETS",
    "City",
    "CityParams",
    "GpsOutliers",
    "Grid",
    "GridParams",
    "Outliers",
    "add_gps_outliers",
    "add_outliers",
    "add_pattern_outliers",
    "generate_city",
    "generate_grid",
    "noisify",
    "scale_city",
    "write_gps_outliers",
    "write_ground_truth",
    "write_outliers",
]
