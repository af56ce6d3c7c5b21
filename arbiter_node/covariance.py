"""Covariance hygiene shared by the arbiters: what they publish must be finite, symmetric, PD.

Fusion and filtering keep covariances in floating point for hours; rounding makes them
slightly asymmetric and, after many updates, can push the smallest eigenvalue below zero.
Every covariance an arbiter hands on goes through `condition_covariance`.
"""
import numpy as np

MIN_VARIANCE = 1e-10        # eigenvalue floor: above se3.is_valid_covariance's 1e-12, keeps it invertible
MAX_VARIANCE = 1e12         # eigenvalue ceiling: keeps endless prediction from overflowing


def _conditioned(C, min_eig: float, max_eig: float):
    """(conditioned C, (w, V) = its eigen-decomposition when already computed, else None)."""
    C = np.asarray(C, dtype=float)
    n = C.shape[0]
    if not np.all(np.isfinite(C)):
        return np.eye(n) * max_eig, None
    C = 0.5 * (C + C.T)
    w, V = np.linalg.eigh(C)
    if w.min() >= min_eig and w.max() <= max_eig:
        return C, (w, V)
    w = np.clip(w, min_eig, max_eig)
    C = (V * w) @ V.T
    return 0.5 * (C + C.T), None


def condition_covariance(C, min_eig: float = MIN_VARIANCE, max_eig: float = MAX_VARIANCE) -> np.ndarray:
    """Symmetrize and clamp eigenvalues into [min_eig, max_eig]; non-finite -> max_eig * I."""
    return _conditioned(C, min_eig, max_eig)[0]


def safe_inverse(C) -> np.ndarray:
    """Inverse of a covariance after conditioning (eigen-decomposition, so never singular).
    A covariance that needed no clamping (the usual case) is inverted with the decomposition
    the conditioning already made of that very matrix: the same numbers, one eigh less."""
    C, eig = _conditioned(C, MIN_VARIANCE, MAX_VARIANCE)
    w, V = eig if eig is not None else np.linalg.eigh(C)
    Ci = (V / w) @ V.T
    return 0.5 * (Ci + Ci.T)


def mahalanobis2(e, C) -> float:
    """Squared Mahalanobis distance of error vector e under covariance C."""
    e = np.asarray(e, dtype=float)
    return float(e @ safe_inverse(C) @ e)
