"""Named tolerances of the test suite (STYLE.md §7).

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

#: Sparse vs dense Gauss-Newton solution (STYLE.md §7).
SPARSE_VS_DENSE_GN = 1e-9

#: Energy after OnlineSolver.refine (LM from the online estimate) vs the prefix optimum (LM from
#: the odometry chain), relative: both stop at LM's energy tolerance 1e-10 on the same optimum.
ONLINE_REFINED = 1e-6

#: iSAM2 (relinearization threshold 0.1, its default) vs the batch optimum, relative energy.
ISAM2_VS_OPTIMUM = 1e-3
