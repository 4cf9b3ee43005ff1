"""Two-view geometry of pixel matches between two devices (cameras, or a camera and the projector).

The epipolar geometry and triangulation that :mod:`.rig_refine` adjusts a pose with, and that
:mod:`.scan_matches` and :mod:`.projector_fit` check matches by: undistorted normalised coordinates,
the fundamental matrix of a relative pose, each match's Sampson distance and epipolar distances,
the points two rays meet at and their reprojection errors.

Poses follow OpenCV: the relative pose of device 2 is ``X_2 = R X_1 + t``.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["epipolar_distances", "reprojection_errors", "triangulate_pair"]

_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 50, 1e-12)


def _normalize(uv: np.ndarray, K, dist) -> np.ndarray:
    """(n, 2) observed (distorted) pixels -> (n, 2) normalised undistorted image coordinates."""
    if uv.shape[0] == 0:
        return np.zeros((0, 2))
    out = cv2.undistortPoints(uv.reshape(-1, 1, 2), np.asarray(K, float), np.asarray(dist, float), None, None, None,
                              _UNDISTORT_CRITERIA)
    return out.reshape(-1, 2)


def _skew(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _fundamental(R, t, K1, K2) -> np.ndarray:
    """F with x2^T F x1 = 0 for undistorted pixels of devices 1 and 2."""
    E = _skew(np.asarray(t, float) / max(np.linalg.norm(t), 1e-300)) @ R
    return np.linalg.inv(K2).T @ E @ np.linalg.inv(K1)


def _homog(p):
    return np.concatenate([p, np.ones((p.shape[0], 1))], 1)


def _sampson(F, p1, p2) -> np.ndarray:
    """Signed Sampson distance (px) of undistorted pixel matches: the first-order
    length of the smallest correction of (p1, p2) onto the epipolar geometry."""
    x1, x2 = _homog(p1), _homog(p2)
    Fx1 = x1 @ F.T
    Ftx2 = x2 @ F
    num = np.sum(x2 * Fx1, 1)
    den = np.sqrt(Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2)
    return num / np.maximum(den, 1e-300)


def epipolar_distances(R, t, K1, K2, n1, n2) -> np.ndarray:
    """Per match, the mean of the distances (px) of each undistorted pixel from the
    epipolar line of the other, for normalised coordinates ``n1``, ``n2`` ((n, 2))."""
    F = _fundamental(R, t, K1, K2)
    p1 = n1 @ np.asarray(K1)[:2, :2].T + np.asarray(K1)[:2, 2]
    p2 = n2 @ np.asarray(K2)[:2, :2].T + np.asarray(K2)[:2, 2]
    x1, x2 = _homog(p1), _homog(p2)
    l2 = x1 @ F.T
    l1 = x2 @ F
    e = np.abs(np.sum(x2 * l2, 1))
    d2 = e / np.maximum(np.hypot(l2[:, 0], l2[:, 1]), 1e-300)
    d1 = e / np.maximum(np.hypot(l1[:, 0], l1[:, 1]), 1e-300)
    return 0.5 * (d1 + d2)


def triangulate_pair(R, t, n1, n2) -> np.ndarray:
    """Device-1-frame points (n, 3) of normalised coordinates ``n1``, ``n2`` with X_2 = R X_1 + t."""
    if n1.shape[0] == 0:
        return np.zeros((0, 3))
    P1 = np.hstack([np.eye(3), np.zeros((3, 1))])
    P2 = np.hstack([np.asarray(R, float), np.asarray(t, float).reshape(3, 1)])
    X = cv2.triangulatePoints(P1, P2, n1.T.astype(np.float64), n2.T.astype(np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        return (X[:3] / X[3]).T


def reprojection_errors(R, t, dev1, dev2, uv1, uv2, n1, n2) -> tuple[np.ndarray, np.ndarray]:
    """Per match, the RMS over both devices of the reprojection error (px) of the
    triangulated point, and whether the point lies in front of both devices."""
    X = triangulate_pair(R, t, n1, n2)
    ok = np.all(np.isfinite(X), 1)
    X = np.where(ok[:, None], X, 0.0)
    X2 = X @ np.asarray(R).T + np.asarray(t).ravel()
    front = ok & (X[:, 2] > 0) & (X2[:, 2] > 0)
    zero = np.zeros(3)
    q1, _ = cv2.projectPoints(X.reshape(-1, 1, 3), zero, zero, np.asarray(dev1.K, float), np.asarray(dev1.dist, float))
    q2, _ = cv2.projectPoints(X2.reshape(-1, 1, 3), zero, zero, np.asarray(dev2.K, float), np.asarray(dev2.dist, float))
    e1 = np.sum((q1.reshape(-1, 2) - uv1) ** 2, 1)
    e2 = np.sum((q2.reshape(-1, 2) - uv2) ** 2, 1)
    err = np.sqrt(0.5 * (e1 + e2))
    return np.where(ok, err, np.inf), front
