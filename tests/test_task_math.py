"""The task-space map's compiled linear algebra (teleop_rt.task_math) against closed forms and
Pinocchio: SO(3)'s log and exp against pin.log3 / pin.exp3, the damped least-squares inverse
against J^T (J J^T + l^2 I)^-1, its smallest singular value against an SVD."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from teleop_rt.task_math import dls_inverse, so3_exp, so3_log

RNG = np.random.default_rng(7)


def axis() -> np.ndarray:
    u = RNG.normal(size=3)
    return u / np.linalg.norm(u)


# angles from the series' range to just short of pi (where the axis comes from R + R^T)
ANGLES = [0.0, 1e-12, 1e-7, 1e-4, 0.3, 1.0, 2.0, 2.6, 2.8, 3.0, np.pi - 1e-4, np.pi - 1e-7]


@pytest.mark.parametrize("angle", ANGLES)
def test_log_and_exp_are_pinocchio_s(angle: float) -> None:
    for _ in range(20):
        w = angle * axis()
        f = np.zeros(32)
        so3_exp(f, *w, 0)
        np.testing.assert_allclose(f[:9].reshape(3, 3), pin.exp3(w), atol=1e-14)
        f[9:18] = pin.exp3(w).ravel()
        so3_log(f, 9, 18)
        # near pi the axis is ill-conditioned in R itself (d log / d R ~ 1 / sin t): compare the
        # rotation the log gives back, and the vector to what R still says
        tol = 1e-12 if angle < 3.0 else 1e-12 / np.sin(angle)
        np.testing.assert_allclose(f[18:21], pin.log3(pin.exp3(w)), atol=tol)
        np.testing.assert_allclose(pin.exp3(f[18:21]), pin.exp3(w), atol=1e-13)


def test_log_at_pi_gives_a_rotation_by_pi_about_the_axis() -> None:
    for _ in range(20):
        u = axis()
        rotation = pin.exp3(np.pi * u)
        f = np.zeros(12)
        f[:9] = rotation.ravel()
        so3_log(f, 0, 9)
        assert np.linalg.norm(f[9:12]) == pytest.approx(np.pi, abs=1e-12)
        assert abs(f[9:12] @ u) == pytest.approx(np.pi, abs=1e-7)
        np.testing.assert_allclose(pin.exp3(f[9:12]), rotation, atol=1e-12)


def dls(jac: np.ndarray, damping: float, calls: int = 1) -> tuple[np.ndarray, float, np.ndarray]:
    m, n = jac.shape
    work, inv = n * m, 0
    f = np.zeros(n * m + m * m + m)
    f[work + m * m :] = 1.0 / np.sqrt(m)
    for _ in range(calls):
        sigma2 = dls_inverse(f, jac, n, m, damping**2, inv, work)
    return f[: n * m].reshape(n, m), sigma2, f


@pytest.mark.parametrize("m, n", [(3, 6), (3, 9), (6, 6), (6, 9)])
def test_the_dls_inverse_is_the_closed_form(m: int, n: int) -> None:
    """J# against V diag(s / (s^2 + l^2)) U^T from J's SVD, to the solve's conditioning."""
    for scale in (1.0, 1e-2, 1e-4):  # well away from, near, and at a singular pose
        jac = RNG.normal(size=(m, n))
        u, s, vt = np.linalg.svd(jac, full_matrices=False)
        s[-1] *= scale
        jac = (u * s) @ vt
        lam = 1e-3
        inverse, _, _ = dls(jac, lam)
        u, s, vt = np.linalg.svd(jac, full_matrices=False)
        closed = (vt.T * (s / (s**2 + lam**2))) @ u.T  # V diag(s / (s^2 + l^2)) U^T
        # a Cholesky solve errs by ~ cond(A) eps (A = J J^T + l^2 I)
        cond = (s[0] ** 2 + lam**2) / (s[-1] ** 2 + lam**2)
        tol = 10 * cond * np.finfo(float).eps * np.abs(closed).max()
        np.testing.assert_allclose(inverse, closed, rtol=0, atol=tol)


@pytest.mark.parametrize("m, n", [(3, 6), (6, 9)])
def test_the_smallest_singular_value_converges_from_above(m: int, n: int) -> None:
    """Inverse iteration from a fixed start: each call's Rayleigh quotient is above
    sigma_min^2 + l^2 and reaches it (to 1e-12 relative) within a few calls on one J."""
    jac = RNG.normal(size=(m, n))
    true = np.linalg.svd(jac, compute_uv=False)[-1]
    lam = 1e-3
    f = dls(jac, lam)[2]
    estimates = [dls_inverse(f, jac, n, m, lam**2, 0, n * m) for _ in range(30)]
    assert min(estimates) >= true**2 * (1 - 1e-12)
    assert np.sqrt(estimates[-1]) == pytest.approx(true, rel=1e-12)


@pytest.mark.parametrize("m, n", [(3, 6), (6, 6), (6, 9)])
def test_each_call_returns_the_rayleigh_quotient_of_its_step(m: int, n: int) -> None:
    """One call is one inverse-iteration step from the kept vector u: it returns the Rayleigh
    quotient of y = A^-1 u, y^T A y / y^T y - l^2 (numpy's, to 1e-12 relative; cond(A) ~ 10 here:
    J well away from a singular pose), and keeps y / |y| for the next call."""
    jac = RNG.normal(size=(m, n))
    lam = 1e-3
    a = jac @ jac.T + lam**2 * np.eye(m)
    f = dls(jac, lam)[2]
    for _ in range(3):
        u = f[n * m + m * m :].copy()
        y = np.linalg.solve(a, u)
        sigma2 = dls_inverse(f, jac, n, m, lam**2, 0, n * m)
        assert sigma2 + lam**2 == pytest.approx(y @ a @ y / (y @ y), rel=1e-12)
        np.testing.assert_allclose(f[n * m + m * m :], y / np.linalg.norm(y), rtol=0, atol=1e-12)


@pytest.mark.parametrize("m, n", [(3, 6), (6, 6), (6, 9)])
def test_the_compiled_dls_is_its_source_bit_for_bit_at_any_offset(m: int, n: int) -> None:
    """The kernel's unsigned indices (flat.Index) change no arithmetic: at offsets into a larger
    buffer (J# after 5 floats, the factor 3 floats after J#) the compiled kernel gives its own
    Python source's J#, factor, vector and figure to the last bit, and those of the kernel at
    offset 0; and J moved by one ulp in one entry gives other bits: the comparison can tell
    a change of arithmetic (whether a fastmath build differs depends on the CPU target)."""
    jac = RNG.normal(size=(m, n))
    lam2 = 1e-6
    inv, work = 5, 5 + n * m + 3
    size = work + m * m + m

    def run(kernel, inv: int, work: int) -> tuple[np.ndarray, list[float]]:
        f = np.zeros(size + 4)
        f[work + m * m : work + m * m + m] = 1.0 / np.sqrt(m)
        figures = [kernel(f, jac, n, m, lam2, inv, work) for _ in range(3)]
        return f, figures

    f, figures = run(dls_inverse, inv, work)
    f_py, figures_py = run(dls_inverse.py_func, inv, work)
    assert np.array_equal(f, f_py) and figures == figures_py
    f0, figures0 = run(dls_inverse, 0, n * m)
    assert np.array_equal(f[inv : inv + n * m], f0[: n * m]) and figures == figures0
    # the comparison sees one ulp: the same kernel on J with one entry moved by an ulp differs
    jac[0, 0] = np.nextafter(jac[0, 0], np.inf)
    moved, _ = run(dls_inverse, inv, work)
    assert not np.array_equal(moved, f)
