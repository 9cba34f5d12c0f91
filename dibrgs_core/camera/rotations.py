"""Rotations as quaternions: conversion, slerp, axis-angle (NumPy only: Blender's Python imports
it, and it has no scipy). Quaternions are ``(w, x, y, z)``; rotation matrices 3x3."""
from __future__ import annotations

import numpy as np


def quat_of(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a 3x3 rotation matrix (Shepperd's method, w >= 0)."""
    R = np.asarray(R, np.float64)
    tr = np.trace(R)
    diag = np.array([tr, R[0, 0], R[1, 1], R[2, 2]])
    k = int(np.argmax(diag))
    if k == 0:
        s = 2.0 * np.sqrt(max(1.0 + tr, 1e-300))
        q = np.array([0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s])
    else:
        i, j, m = k - 1, k % 3, (k + 1) % 3
        s = 2.0 * np.sqrt(max(1.0 + R[i, i] - R[j, j] - R[m, m], 1e-300))
        q = np.empty(4)
        q[0] = (R[m, j] - R[j, m]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + m] = (R[m, i] + R[i, m]) / s
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def rot_of(q: np.ndarray) -> np.ndarray:
    """3x3 rotation matrix of a quaternion (w, x, y, z) (normalised first)."""
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def slerp(Ra: np.ndarray, Rb: np.ndarray, t: float) -> np.ndarray:
    """Rotation a fraction ``t`` in [0, 1] of the way from ``Ra`` to ``Rb`` along the shortest arc."""
    qa, qb = quat_of(Ra), quat_of(Rb)
    d = float(qa @ qb)
    if d < 0:
        qb, d = -qb, -d
    if d > 1.0 - 1e-12:
        return rot_of(qa + t * (qb - qa))
    th = np.arccos(min(d, 1.0))
    return rot_of((np.sin((1 - t) * th) * qa + np.sin(t * th) * qb) / np.sin(th))


def axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation by ``angle`` radians about ``axis`` (Rodrigues)."""
    a = np.asarray(axis, np.float64)
    a = a / max(np.linalg.norm(a), 1e-300)
    Kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * Kx + (1 - np.cos(angle)) * Kx @ Kx
