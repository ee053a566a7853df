"""Compiled kinematics and exact-arc step (numba; loaded through :mod:`aasoatt_env.compiled`).

:func:`~aasoatt_env.model.dynamics.kinematics`' and :func:`~aasoatt_env.model.dynamics.integrate`'s
differential-drive numbers, bit for bit, in one pass per robot (numpy's complex products: :func:`cmul`).
"""

from __future__ import annotations

import math

import numpy as np

from aasoatt_env.numba_jit import cmul, jit

__all__ = ["integrate", "kinematics"]


@jit
def kinematics(columns, offset, turn_gain, pose, u):
    """``(p, v, A, adot_u)`` of :func:`~aasoatt_env.model.dynamics.kinematics` (each complex product as numpy's)."""
    n = pose.shape[0]
    p, v, A, adot = np.empty((n, 2)), np.empty((n, 2)), np.empty((n, 2, 2)), np.empty((n, 2))
    for i in range(n):
        e = np.exp(1j * pose[i, 2])
        z0 = cmul(e.real, e.imag, columns[i, 0].real, columns[i, 0].imag)
        z1 = cmul(e.real, e.imag, columns[i, 1].real, columns[i, 1].imag)
        a = cmul(z0[0], z0[1], u[i, 0], 0.0)
        b = cmul(z1[0], z1[1], u[i, 1], 0.0)
        vz = (a[0] + b[0], a[1] + b[1])
        w = cmul(0.0, 1.0, turn_gain[i] * (u[i, 0] - u[i, 1]), 0.0)
        ad = cmul(w[0], w[1], vz[0], vz[1])
        q = cmul(offset[i], 0.0, e.real, e.imag)
        p[i, 0], p[i, 1] = pose[i, 0] + q[0], pose[i, 1] + q[1]
        v[i, 0], v[i, 1] = vz
        A[i, 0, 0], A[i, 0, 1], A[i, 1, 0], A[i, 1, 1] = z0[0], z1[0], z0[1], z1[1]
        adot[i, 0], adot[i, 1] = ad
    return p, v, A, adot


@jit
def integrate(wheel_map, pose, u, du, dt, small):
    """New poses ``(N, 3)`` and wheel speeds ``(N, 2)`` (the reference's order of operations)."""
    n = pose.shape[0]
    pose_new, u_new = np.empty((n, 3)), np.empty((n, 2))
    for i in range(n):
        u0, u1 = u[i, 0] + du[i, 0] * dt, u[i, 1] + du[i, 1] * dt
        m0, m1 = 0.5 * (u[i, 0] + u0), 0.5 * (u[i, 1] + u1)
        forward = wheel_map[i, 0, 0] * m0 + wheel_map[i, 0, 1] * m1
        half = (0.5 * dt) * (wheel_map[i, 1, 0] * m0 + wheel_map[i, 1, 1] * m1)
        sinc = 1.0 if abs(half) < small else math.sin(half) / half
        chord = (dt * forward * sinc) * np.exp(1j * (pose[i, 2] + half))
        pose_new[i, 0], pose_new[i, 1] = pose[i, 0] + chord.real, pose[i, 1] + chord.imag
        pose_new[i, 2] = pose[i, 2] + 2.0 * half
        u_new[i, 0], u_new[i, 1] = u0, u1
    return pose_new, u_new
