"""The backup layer's compiled closed forms, pair checks and pair search (numba; used by :mod:`.kernels`).

Each helper is its numpy reference in :mod:`.paths` or :mod:`.gate` (the name says which) for one robot, sample or pair,
in its order of operations but for ``sqrt(x^2 + y^2)`` for ``hypot`` and :func:`fill_brake`'s recurrence: the results
agree to rounding.  Robots' constants are the columns of :func:`~.gate.team_block`'s ``robots``.
"""

import math

import numpy as np

from aasoatt_env.numba_jit import jit, nclip, nmax
from aasoatt_env.safety.backup.paths import _EPS, MAX_BRAKE_STEPS

__all__ = ["E1", "brake1", "candidate1", "consts", "fill_brake", "fill_row", "near", "pair_margin", "pair_min",
           "sample_at", "segment_margin", "starts"]

OFFSET, TURN_GAIN, MAX_ACCEL, DECEL, RADIUS = 0, 1, 2, 3, 4  # columns of the robots' constants
D1, OMEGA, RATE, BULGE, REACH = 0, 1, 2, 3, 4  # columns of a level's floats F (its complex C: step end, velocity)
_TWO_PI = 2.0 * np.pi
_PI = float(np.pi)
_RESYNC = 16  # samples between the exact rotations of fill_brake's recurrence


@jit
def cabs(z):
    """``|z|`` by ``hypot``, as numpy's scalar code takes it."""
    return math.hypot(z.real, z.imag)


@jit
def sinc1(x):
    """``paths._sinc`` of one number."""
    y = _PI * x
    if y == 0.0:
        y = _EPS
    return math.sin(y) / y


@jit
def E1(x):
    """``paths._E`` of one number, one sine serving both factors (numpy's sinc takes the same angle)."""
    h = 0.5 * x
    sh = math.sin(h)
    sc = sh / h if h != 0.0 else 1.0
    return complex(math.cos(h) * sc, sh * sc)


@jit
def rot(h):
    """``e^{i h}``."""
    return complex(math.cos(h), math.sin(h))


@jit
def starts(diff, rob, pose):
    """Control points ``(n,)`` and headings ``e^{i theta}`` ``(n,)`` (0 for point masses) of axle poses."""
    n = pose.shape[0]
    p0, hd = np.empty(n, dtype=np.complex128), np.empty(n, dtype=np.complex128)
    for g in range(n):
        hd[g] = rot(pose[g, 2]) if diff else 0j
        c = complex(pose[g, 0], pose[g, 1])
        p0[g] = c + rob[g, OFFSET] * hd[g] if diff else c
    return p0, hd


@jit
def consts(rob, cols, g):
    """Robot ``g``'s constants of the closed forms, by value: input columns, turn gain, acceleration, deceleration."""
    return cols[g, 0], cols[g, 1], rob[g, TURN_GAIN], rob[g, MAX_ACCEL], rob[g, DECEL]


@jit
def velocity1(diff, rc, heading, u0, u1):
    """``paths._velocity`` of a robot (``rc``: its :func:`consts`): control-point velocity and yaw rate."""
    if not diff:
        return complex(u0, u1), 0.0
    return heading * (rc[0] * u0 + rc[1] * u1), rc[2] * (u0 - u1)


@jit
def brake_time1(diff, rc, u0, u1):
    """``paths.brake_time`` of a robot."""
    s = nmax(abs(u0), abs(u1))
    speed = cabs(rc[0] * u0 + rc[1] * u1) if diff else math.hypot(u0, u1)
    return nmax(s / rc[3], speed / rc[4])


@jit
def brake1(diff, rc, heading, u0, u1, dt):
    """``paths.brake`` of a robot: ``(pdot, omega, rate, steps, reach, bulge)`` (NaN kept as numpy keeps it)."""
    T = brake_time1(diff, rc, u0, u1)
    pdot, w = velocity1(diff, rc, heading, u0, u1)
    moving = T > 0.0
    ratio = T / dt if moving else 0.0
    r1 = max(ratio, 1.0)
    steps = int(min(max(np.ceil(ratio - 1e-12), 1.0), MAX_BRAKE_STEPS)) if moving else 0
    rate = 1.0 / r1 if moving else 1.0
    speed = cabs(pdot) if moving else cabs(pdot) * 0.0
    K = float(steps)
    tau_end = dt * (0.5 + (K - 1.0) * (1.0 - K / (2.0 * r1))) if moving else 0.0
    aw = abs(w)
    tau_env = _PI / aw if aw * tau_end > _PI else tau_end
    reach = speed * tau_env * sinc1(aw * tau_env / _TWO_PI) + (dt * dt / 8.0) * speed * aw
    bulge = 0.0
    if not diff:
        bulge = (dt / 8.0) * speed * rate
        reach = reach + bulge
    if ratio > MAX_BRAKE_STEPS:  # too long to sample: unbounded
        reach = np.inf
    return (pdot if moving else pdot * 0.0), w, rate, steps, reach, bulge


@jit
def candidate1(diff, rc, p0, theta, heading, u0, u1, du0, du1, dt):
    """``paths.candidate`` of a robot: ``(p1, dev, pdot, omega, rate, steps, reach, bulge)`` (the candidate's reach)."""
    c8 = dt * dt / 8.0
    u10 = u0 + du0 * dt
    u11 = u1 + du1 * dt
    pm, wm = velocity1(diff, rc, heading, 0.5 * (u0 + u10), 0.5 * (u1 + u11))
    p1 = p0 + pm * dt * E1(wm * dt)
    dev = c8 * cabs(pm) * abs(wm)
    if not diff:
        dev = dev + c8 * math.hypot(du0, du1)
    pdot, w, rate, steps, reach, bulge = brake1(diff, rc, rot(theta + wm * dt) if diff else 0j, u10, u11, dt)
    return p1, dev, pdot, w, rate, steps, cabs(p1 - p0) + dev + reach, bulge


@jit
def fill_brake(row_p, row_d, start, p_start, pdot, omega, rate, bulge, has_bulge, dt, length, fast):
    """``paths.brake_samples`` into ``row_p[start:length]`` from ``p_start``, deviations into ``row_d``.

    ``fast``: while the robot decelerates each step's rotation ``e^{i omega dtau / 2}`` is the previous one's times a
    fixed factor, so the rotations come by recurrence, exact every :data:`_RESYNC` samples and at rest: samples within
    ~1e-13 of the path's length of the exact ones, far below the check's tolerance.
    """
    c8, half_dt, apd, aw = dt * dt / 8.0, 0.5 * dt, cabs(pdot), abs(omega)
    tau, sig_prev = 0.0, 1.0
    row_p[start] = p_start + (pdot * tau) * E1(omega * tau)
    qw = 0.25 * omega * dt
    z = w = c = 1.0 + 0.0j  # e^{i omega tau / 2}; a step's rotation; the factor from one step's to the next
    if fast:
        w = rot(qw * (2.0 - rate))  # step 1's: dtau = dt (1 - rate / 2)
        c = rot(-2.0 * qw * rate)
    for k in range(1, length - start):
        raw = 1.0 - k * rate
        sig = 0.0 if raw < 0.0 else (1.0 if raw > 1.0 else raw)
        tau = tau + half_dt * (sig_prev + sig)
        s = 0.5 * (sig_prev + sig)
        d = c8 * apd * (s * s) * aw
        if has_bulge and sig_prev > 0.0:
            d = d + bulge
        row_d[start + k - 1] = d
        if not fast:
            row_p[start + k] = p_start + (pdot * tau) * E1(omega * tau)
        else:
            h = 0.5 * (omega * tau)
            if k % _RESYNC == 0:
                z = rot(h)
                w = rot(qw * (2.0 - (2 * k + 1) * rate))  # step k + 1's
            elif raw > 0.0:  # both ends of the step still decelerating
                z = z * w
                w = w * c
            elif sig_prev > 0.0:  # the step that ends at rest
                z = rot(h)
            if abs(h) < 0.1:
                h2 = h * h
                sc = 1.0 - h2 / 6.0 * (1.0 - h2 / 20.0 * (1.0 - h2 / 42.0))
            else:
                sc = z.imag / h
            row_p[start + k] = p_start + (pdot * tau) * (z * sc)
        sig_prev = sig


@jit
def fill_row(cur, curd, g, k, last, p0, C, F, has_bulge, dt, need, fast):
    """Row ``g`` of ``cur``/``curd``: robot ``g``'s path on level ``k`` (``need`` samples; ``last``: braking now)."""
    s = 0 if k == last else 1
    if s:
        cur[g, 0], curd[g, 0] = p0[g], F[k, g, D1]
    fill_brake(cur[g], curd[g], s, p0[g] if k == last else C[k, g, 0], C[k, g, 1], F[k, g, OMEGA], F[k, g, RATE],
               F[k, g, BULGE], has_bulge, dt, need, fast)


@jit
def sample_at(p0, p1, d1, pdot, omega, rate, steps, bulge, has_bulge, dt, s):
    """Sample ``s`` of a candidate path and the deviation of step ``s -> s + 1`` (``paths.candidate_samples_at``)."""
    if s == 0:
        return p0, d1
    r = rate
    kf = math.floor(1.0 / r)
    k = float(max(s - 1, 0))
    kc = min(k, kf)
    tau = dt * (kc - 0.5 * r * kc * kc + (0.5 * nclip(1.0 - kf * r, 0.0, 1.0) if k > kf else 0.0))
    p = p1 + (pdot * tau) * E1(omega * tau)
    a, b = nclip(1.0 - k * r, 0.0, 1.0), nclip(1.0 - (k + 1.0) * r, 0.0, 1.0)
    sig = 0.5 * (a + b)
    d = (dt * dt / 8.0) * cabs(pdot) * (sig * sig) * abs(omega)
    if has_bulge:
        d = d + (bulge if a > 0.0 and k < steps else 0.0)
    return p, d


@jit
def segment_margin(qa0, qa1, qc0, qc1, da, dc):
    """Smallest ``|q| - da - dc`` on the segment of relative positions ``qa - qc`` (``gate.pair_margins``' step)."""
    q0 = qa0 - qc0
    q1 = qa1 - qc1
    dr = q1.real - q0.real
    dm = q1.imag - q0.imag
    dd = dr * dr + dm * dm
    if not dd > 0.0:
        dd = 1.0
    t = -(q0.real * dr + q0.imag * dm) / dd
    t = 0.0 if t < 0.0 else (1.0 if t > 1.0 else t)
    x = q0.real + t * dr
    y = q0.imag + t * dm
    return math.sqrt(x * x + y * y) - da - dc


@jit
def step_margin(cur, curd, na, nc, a, c, oc, k):
    """Step ``k``'s :func:`segment_margin` of rows ``a``, ``c`` (``c < 0``: point ``oc``), resting past their own."""
    ka0, ka1 = min(k, na - 1), min(k + 1, na - 1)
    da = curd[a, k] if k < na - 1 else 0.0
    if c < 0:
        return segment_margin(cur[a, ka0], cur[a, ka1], oc, oc, da, 0.0)
    kc0, kc1 = min(k, nc - 1), min(k + 1, nc - 1)
    dc = curd[c, k] if k < nc - 1 else 0.0
    return segment_margin(cur[a, ka0], cur[a, ka1], cur[c, kc0], cur[c, kc1], da, dc)


@jit
def pair_min(cur, curd, na, nc, a, c, oc, nseg, tie):
    """Least margin (before ``- d_s``) over ``nseg`` steps and its step (a NaN first; ``tie >= 0``: ``closest``'s)."""
    best, kbest = np.inf, 0
    for k in range(nseg):
        dist = step_margin(cur, curd, na, nc, a, c, oc, k)
        if dist != dist:
            return dist, k
        if dist < best:
            best, kbest = dist, k
    for k in range(kbest if tie >= 0.0 else 0):
        dist = step_margin(cur, curd, na, nc, a, c, oc, k)
        if dist <= best + tie:
            return dist, k
    return best, kbest


@jit
def pair_margin(cur, curd, na, nc, a, c, ds, oc):
    """:func:`pair_min` over the pair's own horizon, minus ``ds``."""
    L = na if c < 0 else max(na, nc)
    return pair_min(cur, curd, na, nc, a, c, oc, max(L, 2) - 1, -1.0)[0] - ds


@jit
def near(cand, p0, R, rob, group, has_group, sensing_range, oc, orad, ogroup, has_ogroup, slack):
    """``gate.pairs_near`` of ``cand``, then ``gate.obstacles_near`` (``c = -1``): ``(a, c, d_s, obstacle centre)``."""
    n, m = p0.shape[0], oc.shape[0]
    a, c = np.empty(cand.shape[0] + n * m, np.int64), np.empty(cand.shape[0] + n * m, np.int64)
    ds, at = np.empty(a.shape[0]), np.zeros(a.shape[0], np.complex128)
    P = 0
    for q in range(cand.shape[0]):
        g, h = cand[q, 0], cand[q, 1]
        if has_group and group[g] != group[h]:
            continue
        dist = cabs(p0[g] - p0[h])
        if dist <= sensing_range and dist < rob[g, RADIUS] + rob[h, RADIUS] + R[g] + R[h] + slack:
            a[P], c[P], ds[P] = g, h, rob[g, RADIUS] + rob[h, RADIUS]
            P += 1
    for g in range(n):
        for o in range(m):
            if has_group and has_ogroup and group[g] != ogroup[o]:
                continue
            if cabs(p0[g] - oc[o]) < rob[g, RADIUS] + orad[o] + R[g] + slack:
                a[P], c[P], ds[P], at[P] = g, -1, rob[g, RADIUS] + orad[o], oc[o]
                P += 1
    return a[:P], c[:P], ds[:P], at[:P]
