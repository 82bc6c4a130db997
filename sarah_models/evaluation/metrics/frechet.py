"""The Fréchet distance between Gaussians fitted to two sample sets (FGD and FGD_acc)."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
from scipy import linalg

from sarah_data.moments import Moments

from .clips import as_numpy


class FrechetRidgeWarning(RuntimeWarning):
    """A ridge was added to the covariances because their product's square root was unreliable."""


def _sqrtm_problem(root: np.ndarray, product: np.ndarray, caught: list, imag_tol: float) -> str | None:
    """Why `root` is not a trustworthy square root of `product`, or None if it is."""
    if not np.all(np.isfinite(root)):
        return "non-finite square root"
    for w in caught:
        if issubclass(w.category, linalg.LinAlgWarning):
            return f"ill-conditioned product ({w.message})"
    scale = max(float(np.abs(root.real).max()), np.finfo(np.float64).tiny)
    if np.iscomplexobj(root) and float(np.abs(root.imag).max()) > imag_tol * scale:
        return f"imaginary part {np.abs(root.imag).max():.3g} vs real scale {scale:.3g}"
    residual = np.linalg.norm(root @ root - product) / max(np.linalg.norm(product), 1e-300)
    if residual > 1e-6:
        return f"relative residual {residual:.3g} of root @ root"
    return None


def frechet_distance_from_moments(mean_a, cov_a, mean_b, cov_b, ridge: float = 1e-6,
                                  max_retries: int = 6, imag_tol: float = 1e-3) -> float:
    """||mu_a - mu_b||^2 + tr(C_a + C_b - 2 (C_a C_b)^(1/2)) of two Gaussians, in float64.

    The square root is scipy.linalg.sqrtm of the covariance product. If it is non-finite, scipy
    reports the product singular or ill-conditioned, its imaginary residue exceeds `imag_tol`
    times its real scale, or root @ root misses the product, a ridge eps*I is added to both
    covariances and the root retried, eps starting at `ridge` times the mean variance and growing
    tenfold per retry; the distance is then that of the ridged Gaussians (so FD(x, x) stays 0).
    A small imaginary residue is dropped; a large one after all retries raises.
    """
    mean_a, mean_b = (np.asarray(as_numpy(m), dtype=np.float64) for m in (mean_a, mean_b))
    cov_a, cov_b = (np.asarray(as_numpy(c), dtype=np.float64) for c in (cov_a, cov_b))
    dim = mean_a.shape[0]
    if mean_b.shape != (dim,) or cov_a.shape != (dim, dim) or cov_b.shape != (dim, dim):
        raise ValueError(f"Fréchet distance: mismatched shapes {mean_a.shape}, {cov_a.shape}, "
                         f"{mean_b.shape}, {cov_b.shape}")
    variance_scale = (np.trace(cov_a) + np.trace(cov_b)) / (2 * dim)
    eps_step = ridge * variance_scale if variance_scale > 0 else ridge
    eye = np.eye(dim)
    offset, problem = 0.0, None
    for attempt in range(max_retries + 1):
        ridged_a, ridged_b = cov_a + offset * eye, cov_b + offset * eye
        product = ridged_a @ ridged_b
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            root = linalg.sqrtm(product)
        problem = _sqrtm_problem(root, product, caught, imag_tol)
        if problem is None:
            break
        offset = eps_step * 10.0 ** attempt
    else:
        raise FloatingPointError(f"Fréchet distance: no reliable covariance square root after "
                                 f"{max_retries} ridge retries (last: {problem})")
    if offset > 0:
        warnings.warn(f"Fréchet distance: added ridge {offset:.3g}*I to both covariances",
                      FrechetRidgeWarning, stacklevel=2)
    diff = mean_a - mean_b
    value = float(diff @ diff + np.trace(ridged_a) + np.trace(ridged_b) - 2.0 * np.trace(root.real))
    # Rounding can leave an exact match a hair below zero; anything larger is a real failure.
    tolerance = 1e-6 * max(float(np.trace(ridged_a) + np.trace(ridged_b)), 1.0)
    if value < -tolerance:
        raise FloatingPointError(f"Fréchet distance: negative result {value:.3g}")
    return max(value, 0.0)


def _sample_moments(feats_a, feats_b) -> tuple[np.ndarray, ...]:
    """(mean_a, cov_a, mean_b, cov_b) in float64 of two (N>=2, D) sample arrays."""
    a, b = (np.asarray(as_numpy(f), dtype=np.float64) for f in (feats_a, feats_b))
    if a.ndim != 2 or b.ndim != 2 or a.shape[1] != b.shape[1] or len(a) < 2 or len(b) < 2:
        raise ValueError(f"Fréchet distance needs two (N>=2, D) sample arrays; got {a.shape}, {b.shape}")
    return (a.mean(0), np.atleast_2d(np.cov(a, rowvar=False)),
            b.mean(0), np.atleast_2d(np.cov(b, rowvar=False)))


def frechet_distance(feats_a, feats_b, ridge: float = 1e-6) -> float:
    """Fréchet distance between Gaussians fitted to samples (N,D) and (M,D) (float64 moments)."""
    return frechet_distance_from_moments(*_sample_moments(feats_a, feats_b), ridge=ridge)


@dataclass(frozen=True)
class FrechetTerms:
    """A Fréchet distance, ``total``, as the sum of three terms: ``mean``, the squared distance
    of the means; ``spectrum``, what the covariances keep when their principal axes are aligned,
    sum_i (sqrt(lambda_a,i) - sqrt(lambda_b,i))^2 over the eigenvalues sorted alike, the least
    the covariance term can be over every rotation of one sample set (by von Neumann's trace
    inequality, so never above it); and ``orientation``, what the axes' directions add to that.
    ``energy`` is trace(C_a) / trace(C_b). Two sets with the same spread in other directions (a
    rotation of one) differ by orientation alone; one set twice the other's size, by spectrum
    alone."""

    total: float
    mean: float
    spectrum: float
    orientation: float
    energy: float


def frechet_terms(feats_a, feats_b, ridge: float = 1e-6) -> FrechetTerms:
    """``frechet_distance`` of samples (N, D) and (M, D) with its three terms (``FrechetTerms``)."""
    mean_a, cov_a, mean_b, cov_b = _sample_moments(feats_a, feats_b)
    total = frechet_distance_from_moments(mean_a, cov_a, mean_b, cov_b, ridge=ridge)
    # eigvalsh sorts ascending, alike for both; rounding can leave a zero eigenvalue below 0
    roots = [np.sqrt(np.clip(np.linalg.eigvalsh(c), 0.0, None)) for c in (cov_a, cov_b)]
    diff = mean_a - mean_b
    mean, spectrum = float(diff @ diff), float(np.sum((roots[0] - roots[1]) ** 2))
    trace_b = float(np.trace(cov_b))
    return FrechetTerms(total=total, mean=mean, spectrum=spectrum,
                        orientation=max(total - mean - spectrum, 0.0),
                        energy=float(np.trace(cov_a)) / trace_b if trace_b > 0 else math.nan)


def moments_distance(a: Moments, b: Moments, ridge: float) -> float:
    """The Fréchet distance of two full-covariance ``Moments`` (NaN below two samples each)."""
    if a.count < 2 or b.count < 2:
        return math.nan
    return frechet_distance_from_moments(a.mean, a.covariance, b.mean, b.covariance, ridge=ridge)
