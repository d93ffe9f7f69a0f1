"""Named tolerances of the test suite (docs/contributing.md#tests).

Import these instead of typing numbers into tests, and never loosen one to make a test pass:
a failure is a bug (or a wrong expectation) to understand first.  Unless a name says otherwise a
tolerance is *absolute* for quantities of order one; tests scale it by the size of the data
(e.g. translations of 10 m) where that is the honest comparison.
"""

from __future__ import annotations

#: Exact identities evaluated in float64 (Exp(Log(T)) = T, kernel vs NumPy twin, vs scipy).
FLOAT64_IDENTITY = 1e-12

#: R^T R = I after re-orthonormalizing a slightly perturbed rotation.
ORTHONORMAL = 1e-14

#: Analytic Jacobian vs central finite differences with step ``CENTRAL_DIFF_STEP``.
CENTRAL_DIFF = 1e-6

#: Step of central differences: truncation ~ h^2 |f'''| ~ 1e-12, rounding ~ eps |f| / h ~ 1e-9.
CENTRAL_DIFF_STEP = 1e-6

#: Sparse vs dense Gauss-Newton solution (docs/contributing.md#tests).
SPARSE_VS_DENSE_GN = 1e-9

#: Two backward-stable solutions of one SPD system H x = b differ by up to about
#: cond(H) * eps relative to |x| (the forward-error bound): where a test's random graph makes
#: H worse conditioned than SPARSE_VS_DENSE_GN / eps (~4.5e6), the two may differ by this
#: factor times cond(H) * eps (a random 11-pose graph with three GPS readings: cond 3e8-2e9,
#: differences of 0.04-0.07 cond(H) eps).  A test using it also requires cond(H) * eps <= 1e-5,
#: so that the comparison still says something.
FORWARD_ERROR = 1.0

#: A kernel vs its NumPy twin when the two take different routes through float64 (path products
#: vs global 4x4 products, Jr^-1 in closed form vs a series inverse), relative to the data's size.
TWIN_JACOBIAN = 1e-12

#: Two exact solves of the same linear system (Woodbury / Givens / Cholesky vs numpy.linalg.solve),
#: relative to the size of the solution.  Blocks of B_c that are singular but for the damping (a
#: GPS anchor: rank 3 per reading, damped by ~1e-9 relative) make the Woodbury forms lose digits:
#: measured 8e-11 (single step) and 3e-10 (segmented batch) on the twin tests, Givens 3e-15.
SAME_EQUATION = 1e-9

#: Two exact routes to the same marginal covariance blocks (the selected inverse of the whole
#: factor vs per-pose solves with SuperLU, whose orderings differ), relative to the largest
#: entry.  Measured on a generated 2 500-pose city (covariance entries from 4e-4 to 17 m^2):
#: 1.3e-9 between the two routes, and 1.7e-9 between two SuperLU solves of the same poses
#: (the graph in memory and read back from its g2o file: same numbers, another ordering).
COVARIANCE_ROUTES = 1e-8

#: Marginal covariance blocks vs GTSAM's Marginals (a different factorization and a 1e-6 sigma
#: prior standing in for our fixed gauge pose): relative to the block's largest entry.
COVARIANCE_VS_GTSAM = 1e-6

#: Energy after OnlineSolver.refine (LM from the online estimate) vs the prefix optimum (LM from
#: the odometry chain), relative: both stop at LM's energy tolerance 1e-10 on the same optimum.
ONLINE_REFINED = 1e-6

#: Relative change of E when an exact solve is repeated from its own optimum and adopted again
#: (LM stops at its energy tolerance 1e-10; the adopted local transforms round at 1e-16).
REFINE_REPEATED = 1e-10

#: Online hybrid updates alone on a small generated city (stiff odometry, soft loop closures,
#: 600 poses, 13 loops): energy over the optimum after the stream and 100 extra frames.  Measured
#: 3.5 with junction groups (the default), 15 without (the valencia bug).
ONLINE_CITY_RATIO = 5.0

#: iSAM2 (relinearization threshold 0.1, its default) vs the batch optimum, relative energy.
ISAM2_VS_OPTIMUM = 1e-3

#: The default pipeline (``--solver auto``) vs the best optimum known (LM from the truth, the
#: file, the chordal and the tree starts): the optimum to 1e-6 relative.
OPTIMUM_RELATIVE = 1e-6

#: The incremental exact solver run to convergence vs the batch exact solver (LM with energy
#: tolerance 1e-15) on the same graph, relative energy.
INCREMENTAL_VS_BATCH = 1e-9
