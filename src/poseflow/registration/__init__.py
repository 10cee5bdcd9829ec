"""Registration: weighted Procrustes, RANSAC-Procrustes and ICP, batched over instances.

Every solver is a function plus a solver class with the same arguments; transforms map the
source onto the target (``target ≈ R @ source + t``), as in Open3D. Every solver says which
instances it could solve: :func:`procrustes` returns a :class:`ProcrustesResult`, the robust
solvers a :class:`RegistrationResult`.
"""

from poseflow.registration.icp import ICP, MultiScaleICP, icp, multi_scale_icp
from poseflow.registration.procrustes import Procrustes, ProcrustesResult, procrustes
from poseflow.registration.ransac import RANSACProcrustes, ransac_procrustes
from poseflow.registration.result import RegistrationResult

__all__ = [
    "ICP",
    "MultiScaleICP",
    "Procrustes",
    "ProcrustesResult",
    "RANSACProcrustes",
    "RegistrationResult",
    "icp",
    "multi_scale_icp",
    "procrustes",
    "ransac_procrustes",
]
