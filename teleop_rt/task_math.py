"""The compiled linear algebra of the task-space map (``teleop_rt.mapping``), in place on a
block's float buffer so that a tick allocates nothing: the damped least-squares inverse of a
tool Jacobian, its smallest singular value, and the exponential and logarithm of SO(3).

* **Damped least squares** (Wampler, "Manipulator inverse kinematic solutions based on vector
  formulations and damped least-squares methods", IEEE T-SMC 1986; Nakamura & Hanafusa,
  "Inverse kinematic solutions with singularity robustness for robot manipulator control",
  J. Dyn. Sys. Meas. Control 1986): J# = J^T (J J^T + l^2 I)^-1. A = J J^T + l^2 I is
  symmetric positive definite for any J once l > 0, so its Cholesky factor L (A = L L^T)
  exists and row j of J# is the solution y of A y = J[:, j] (A symmetric), two triangular
  solves per joint, all joints' in one sweep over L (their chains of operations overlap), each
  row's division by L's diagonal a product with its reciprocal (kept in L's place).
* **Its smallest singular value**: sigma_min(J)^2 = lambda_min(A) - l^2. lambda_min(A) is found
  by inverse iteration (the power method on A^-1, with the Cholesky factor already at hand),
  one step per call (in the same sweep as J#'s rows), started from the previous tick's vector:
  J moves little in a tick, so the steps of successive ticks track it. The figure is the
  Rayleigh quotient of the step's result y = A^-1 u (u unit), y^T A y / y^T y = u . y / |y|^2
  = |z|^2 / |y|^2 (z = L^-1 u, the forward solve's intermediate: no product with A or L^T). A
  Rayleigh quotient is never below lambda_min(A) and errs by the square of the vector's error
  (Golub & Van Loan, Matrix Computations, 4th ed. 2013, sec. 8.2), so the figure is a slight
  over-estimate at worst, never an under-estimate (to rounding).
* **SO(3)**: exp by Rodrigues' formula, R = I + (sin t / t) [w]x + ((1 - cos t) / t^2) [w]x^2
  (t = |w|). log inverts it: tr R = 1 + 2 cos t and R - R^T = 2 sin t [u]x give t = atan2(sin t,
  cos t) and w = t / (2 sin t) vee(R - R^T). Near t = pi, sin t vanishes and the axis comes from
  the symmetric part instead, (R + R^T) / 2 = cos t I + (1 - cos t) u u^T, its sign from
  vee(R - R^T). ``tests/test_task_math.py`` checks both against Pinocchio's exp3 and log3.

Rotations are 9 floats, row-major, at an offset of the buffer.
"""

from __future__ import annotations

import math

import numpy as np

from teleop_rt.flat import Index, jit

NEAR_PI_COS = -0.9  # cos t below this (t > 2.69 rad): log's axis from the symmetric part


@jit
def dls_inverse(
    f: np.ndarray, jac: np.ndarray, n: int, m: int, damping2: float, inv: int, work: int
) -> float:  # fmt: skip
    """J# = J^T (J J^T + l^2 I)^-1 of J = jac[:m, :n] into f[inv:] (n x m, row-major), with
    the Cholesky factor at f[work:] (m x m, its diagonal stored as reciprocals) and the inverse
    iteration's vector after it (m, kept from call to call); returns sigma_min(J)^2 (see the
    module's docstring). Its indices are unsigned (``flat.Index``: no wraparound checks)."""
    one, nn, mm = Index(1), Index(n), Index(m)
    inv_, work_ = Index(inv), Index(work)
    for j in range(nn):  # J^T into J#'s place (its rows are solved in place below)
        b = inv_ + j * mm
        for a in range(mm):
            f[b + a] = jac[a, j]
    for r in range(mm):  # A's lower triangle, from that copy (flat: cheaper than jac[r, j])
        for c in range(r + one):
            s = damping2 if r == c else 0.0
            for j in range(nn):
                s += f[inv_ + j * mm + r] * f[inv_ + j * mm + c]
            f[work_ + r * mm + c] = s
    for c in range(mm):  # A = L L^T, in place; 1 / L_cc on the diagonal (products, not divisions)
        cc = work_ + c * mm
        d = f[cc + c]
        for p in range(c):
            d -= f[cc + p] * f[cc + p]
        d = 1.0 / math.sqrt(d)
        f[cc + c] = d
        for r in range(c + one, mm):
            rr = work_ + r * mm
            s = f[rr + c]
            for p in range(c):
                s -= f[rr + p] * f[cc + p]
            f[rr + c] = s * d
    # row j of J# is A^-1 J[:, j]: all n rows and the inverse iteration's step (k = n: the
    # vector u) are solved in one sweep over L's rows, so their chains of operations overlap
    u = work_ + mm * mm
    for r in range(mm):  # L z = b
        rr = work_ + r * mm
        d = f[rr + r]
        for k in range(nn + one):
            at = u if k == nn else inv_ + k * mm
            s = f[at + r]
            for p in range(r):
                s -= f[rr + p] * f[at + p]
            f[at + r] = s * d
    zz = 0.0  # |z|^2 = u^T A^-1 u = u . y
    for a in range(mm):
        zz += f[u + a] * f[u + a]
    for back in range(mm):  # L^T y = z, row from m - 1 down to 0
        row = mm - one - back
        d = f[work_ + row * mm + row]
        for k in range(nn + one):
            at = u if k == nn else inv_ + k * mm
            s = f[at + row]
            for p in range(row + one, mm):
                s -= f[work_ + p * mm + row] * f[at + p]
            f[at + row] = s * d
    yy = 0.0
    for a in range(mm):
        yy += f[u + a] * f[u + a]
    scale = 1.0 / math.sqrt(yy)
    for a in range(mm):
        f[u + a] *= scale
    # the Rayleigh quotient of y = A^-1 u: y^T A y / y^T y = u . y / |y|^2 = |z|^2 / |y|^2
    return zz / yy - damping2


@jit
def times_transposed(f: np.ndarray, a: int, b: int, out: int) -> None:
    """f[out] = A B^T (3 x 3 each; out apart from a and b)."""
    one, three = Index(1), Index(3)  # (unsigned, and so their literals: flat.Index)
    for r in range(three):
        ar = Index(a) + three * r
        for c in range(three):
            bc = Index(b) + three * c
            f[Index(out) + three * r + c] = (f[ar] * f[bc] + f[ar + one] * f[bc + one]
                                             + f[ar + one + one] * f[bc + one + one])  # fmt: skip


@jit
def times(f: np.ndarray, a: int, b: int, out: int) -> None:
    """f[out] = A B (3 x 3 each; out apart from a and b)."""
    one, three = Index(1), Index(3)  # (unsigned, and so their literals: flat.Index)
    for r in range(three):
        ar = Index(a) + three * r
        for c in range(three):
            bc, six = Index(b) + c, three + three
            f[Index(out) + three * r + c] = (f[ar] * f[bc] + f[ar + one] * f[bc + three]
                                             + f[ar + one + one] * f[bc + six])  # fmt: skip


@jit
def so3_exp(f: np.ndarray, wx: float, wy: float, wz: float, out: int) -> None:
    """f[out] = exp([w]x), Rodrigues' formula (series for |w| below 1e-6 rad)."""
    t2 = wx * wx + wy * wy + wz * wz
    if t2 < 1e-12:  # sin t / t and (1 - cos t) / t^2 to O(t^4), below rounding here
        a, b = 1.0 - t2 / 6.0, 0.5 - t2 / 24.0
    else:
        t = math.sqrt(t2)
        a, b = math.sin(t) / t, (1.0 - math.cos(t)) / t2
    # I + a [w]x + b (w w^T - t^2 I)
    f[out + 0] = 1.0 + b * (wx * wx - t2)
    f[out + 4] = 1.0 + b * (wy * wy - t2)
    f[out + 8] = 1.0 + b * (wz * wz - t2)
    f[out + 1] = b * wx * wy - a * wz
    f[out + 3] = b * wx * wy + a * wz
    f[out + 2] = b * wx * wz + a * wy
    f[out + 6] = b * wx * wz - a * wy
    f[out + 5] = b * wy * wz - a * wx
    f[out + 7] = b * wy * wz + a * wx


@jit
def so3_log(f: np.ndarray, at: int, out: int) -> None:
    """f[out : out + 3] = log(R), the rotation vector t u (t in [0, pi]) of R at f[at]."""
    sx = f[at + 7] - f[at + 5]  # vee(R - R^T) = 2 sin t u
    sy = f[at + 2] - f[at + 6]
    sz = f[at + 3] - f[at + 1]
    c = 0.5 * (f[at] + f[at + 4] + f[at + 8] - 1.0)
    s = 0.5 * math.sqrt(sx * sx + sy * sy + sz * sz)
    t = math.atan2(s, c)
    if c >= NEAR_PI_COS:
        k = 0.5 if s == 0.0 else 0.5 * t / s
        f[out], f[out + 1], f[out + 2] = k * sx, k * sy, k * sz
        return
    # u u^T = ((R + R^T) / 2 - c I) / (1 - c): the column of the largest diagonal
    d = 0
    for a in range(1, 3):
        if f[at + 4 * a] > f[at + 4 * d]:
            d = a
    one_c = 1.0 - c
    ud = math.sqrt(max(0.0, (f[at + 4 * d] - c) / one_c))
    u0 = u1 = u2 = 0.0
    for e in range(3):
        ue = ud if e == d else 0.5 * (f[at + 3 * d + e] + f[at + 3 * e + d]) / (one_c * ud)
        if e == 0:
            u0 = ue
        elif e == 1:
            u1 = ue
        else:
            u2 = ue
    if u0 * sx + u1 * sy + u2 * sz < 0.0:
        t = -t
    f[out], f[out + 1], f[out + 2] = t * u0, t * u1, t * u2
