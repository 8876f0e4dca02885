"""Closed-form and high-accuracy reference solutions for verifying calfit-fe.

Everything here is computed in Python from the strain-energy functions, never
copied from an engine run. Energies follow the CalculiX / Abaqus definitions
(CalculiX User's Manual, *HYPERELASTIC), with plane strain F33 = 1 and the
isochoric invariants I1bar = J^(-2/3) tr C, I2bar = J^(-4/3) I2(C):

    NEO HOOKE           W = C10 (I1bar-3) + (J-1)^2/D1
    MOONEY-RIVLIN       W = C10 (I1bar-3) + C01 (I2bar-3) + (J-1)^2/D1
    REDUCED POLYNOMIAL  W = sum_i Ci0 (I1bar-3)^i + sum_i (J-1)^(2i)/Di
    ARRUDA-BOYCE        W = mu sum_i c_i / lm^(2i-2) (I1bar^i - 3^i) + (1/D) ((J^2-1)/2 - ln J),
                        c = 1/2, 1/20, 11/1050, 19/7000, 519/673750
    AVRIL               W = C10 (I1bar-3) + C20 (I1bar-3)^2 + Kv ((J^2-1)/2 - ln J)
                        (Avril et al., eq. (2); C20 optional, 0 by default: the `stiffening` effect)
    ELASTIC             St Venant-Kirchhoff, W = lambda/2 (tr E)^2 + mu E:E

Cauchy stress of an invariant-based law (Holzapfel, Nonlinear Solid Mechanics, 6.5):
    sigma = (2/J) dev[(W1 + I1bar W2) bbar - W2 bbar^2] + U'(J) I,   bbar = J^(-2/3) F F^T.

Principal form, used for the homogeneous states and the annulus:
    P_i = dW/dlambda_i (first Piola, principal), sigma_i = lambda_i P_i / J.

The annulus (inner radius A clamped, outer radius B loaded by a follower pressure
or by Laplace's law p = T / r) is the axisymmetric plane-strain boundary-value problem
    d P_R / dR + (P_R - P_Theta) / R = 0,  r(A) = A,  P_R(B) = -p lambda_theta(B),
solved for r(R) with scipy.integrate.solve_bvp (second-order form, complex-step
derivatives of the analytic principal stresses, tolerance 1e-10).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import integrate, optimize

_AB_COEF = (0.5, 1.0 / 20.0, 11.0 / 1050.0, 19.0 / 7000.0, 519.0 / 673750.0)


def _fmt(v: float) -> str:
    text, digits = repr(float(v)), 17
    while len(text) > 20:  # CalculiX reads 20-character fields
        digits -= 1
        text = f"{float(v):.{digits}g}"
    return text


def full_gradient(F2) -> np.ndarray:
    """The 3x3 deformation gradient of a plane-strain F (2x2, F33 = 1), or a general 3x3 F as given."""
    F2 = np.asarray(F2, dtype=float)
    if F2.shape == (3, 3):
        return F2.copy()
    F = np.eye(3)
    F[:2, :2] = F2
    return F


@dataclass(frozen=True)
class Law:
    """A material law by its deck name and parameters (deck order)."""

    kind: str  # NEO HOOKE, MOONEY-RIVLIN, REDUCED POLYNOMIAL, ARRUDA-BOYCE, AVRIL, ELASTIC
    params: tuple[float, ...]
    n: int = 1  # REDUCED POLYNOMIAL order
    extra: dict = field(default_factory=dict, compare=False)

    # -- deck text ---------------------------------------------------------------
    def deck_lines(self, name: str = "MAT") -> str:
        vals = ", ".join(_fmt(v) for v in self.params)
        if self.kind == "ELASTIC":
            return f"*MATERIAL, NAME={name}\n*ELASTIC, TYPE=ISO\n{vals}\n"
        if self.kind == "REDUCED POLYNOMIAL":
            head = f"*HYPERELASTIC, REDUCED POLYNOMIAL, N={self.n}"
        else:
            head = f"*HYPERELASTIC, {self.kind}"
        return f"*MATERIAL, NAME={name}\n{head}\n{vals}\n"

    # -- energy derivatives W1 = dW/dI1bar, W2 = dW/dI2bar, U' = dU/dJ ----------------
    def w1(self, i1b):
        k, p = self.kind, self.params
        if k in ("NEO HOOKE", "MOONEY-RIVLIN"):
            return p[0] + 0.0 * i1b
        if k == "AVRIL":  # params C10, Kv[, C20]
            c20 = p[2] if len(p) > 2 else 0.0
            return p[0] + 2.0 * c20 * (i1b - 3.0)
        if k == "REDUCED POLYNOMIAL":
            c = p[: self.n]
            return sum((i + 1) * c[i] * (i1b - 3.0) ** i for i in range(self.n))
        if k == "ARRUDA-BOYCE":
            mu, lm = p[0], p[1]
            return mu * sum((i + 1) * _AB_COEF[i] / lm ** (2 * i) * i1b**i for i in range(5))
        raise ValueError(k)

    def w2(self, i1b):
        if self.kind == "MOONEY-RIVLIN":
            return self.params[1] + 0.0 * i1b
        return 0.0 * i1b

    def dudj(self, J):
        k, p = self.kind, self.params
        if k == "NEO HOOKE":
            return 2.0 * (J - 1.0) / p[1]
        if k == "MOONEY-RIVLIN":
            return 2.0 * (J - 1.0) / p[2]
        if k == "REDUCED POLYNOMIAL":
            d = p[self.n : 2 * self.n]
            return sum(2 * (i + 1) * (J - 1.0) ** (2 * i + 1) / d[i] for i in range(self.n) if d[i] > 0)
        if k == "ARRUDA-BOYCE":
            return (J - 1.0 / J) / p[2]
        if k == "AVRIL":
            return p[1] * (J - 1.0 / J)
        raise ValueError(k)

    # -- principal first Piola stresses (plane strain, lambda3 = 1) ----------------------
    def principal_piola(self, l1, l2):
        """(P1, P2) = (dW/dl1, dW/dl2); works on complex arrays (complex step)."""
        if self.kind == "ELASTIC":
            E, nu = self.params
            lam, mu = E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))
            e1, e2 = 0.5 * (l1 * l1 - 1), 0.5 * (l2 * l2 - 1)
            tr = e1 + e2
            return l1 * (lam * tr + 2 * mu * e1), l2 * (lam * tr + 2 * mu * e2)
        J = l1 * l2
        I1 = l1 * l1 + l2 * l2 + 1.0
        I2 = l1 * l1 * l2 * l2 + l1 * l1 + l2 * l2
        Jm23 = J ** (-2.0 / 3.0)
        Jm43 = Jm23 * Jm23
        i1b = Jm23 * I1
        W1, W2, Up = self.w1(i1b), self.w2(i1b), self.dudj(J)
        out = []
        for la, lb in ((l1, l2), (l2, l1)):
            di1b = Jm23 * (2 * la - (2.0 / 3.0) * I1 / la)
            di2b = Jm43 * (2 * la * lb * lb + 2 * la - (4.0 / 3.0) * I2 / la)
            out.append(W1 * di1b + W2 * di2b + Up * lb)
        return out[0], out[1]

    def principal_cauchy(self, l1, l2):
        P1, P2 = self.principal_piola(l1, l2)
        J = l1 * l2
        return l1 * P1 / J, l2 * P2 / J

    # -- full Cauchy tensor for a plane-strain F (2x2, F33 = 1) or a general F (3x3) -------
    def cauchy(self, F2):
        F = full_gradient(F2)
        J = np.linalg.det(F)
        if self.kind == "ELASTIC":
            E, nu = self.params
            lam, mu = E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))
            Eg = 0.5 * (F.T @ F - np.eye(3))
            S = lam * np.trace(Eg) * np.eye(3) + 2 * mu * Eg
            return F @ S @ F.T / J
        bbar = J ** (-2.0 / 3.0) * F @ F.T
        i1b = np.trace(bbar)
        W1, W2 = self.w1(i1b), self.w2(i1b)
        A = (W1 + i1b * W2) * bbar - W2 * bbar @ bbar
        dev = A - np.trace(A) / 3.0 * np.eye(3)
        return 2.0 / J * dev + self.dudj(J) * np.eye(3)


def _dP_dl(law: Law, l1, l2, h=1e-30):
    """Complex-step derivatives of (P1, P2) with respect to l1 and l2 (exact to rounding)."""
    a1, a2 = law.principal_piola(l1 + 1j * h, l2 + 0j)
    b1, b2 = law.principal_piola(l1 + 0j, l2 + 1j * h)
    return np.imag(a1) / h, np.imag(a2) / h, np.imag(b1) / h, np.imag(b2) / h  # P1,1 P2,1 P1,2 P2,2


# ----------------------------------------------------------------------------------------
# Homogeneous states
# ----------------------------------------------------------------------------------------


def stretches_for_stress(law: Law, s1: float, s2: float, guess=(1.0, 1.0)) -> tuple[float, float]:
    """Principal stretches (l1, l2) whose principal Cauchy stresses are (s1, s2)."""

    def res(x):
        c1, c2 = law.principal_cauchy(x[0], x[1])
        return [c1 - s1, c2 - s2]

    sol = optimize.root(res, guess, method="hybr", tol=1e-14)
    if np.max(np.abs(res(sol.x))) > 1e-12 * max(1.0, abs(s1), abs(s2)):
        raise RuntimeError(f"closed form did not converge: {sol.message}")
    return float(sol.x[0]), float(sol.x[1])


def stretch_for_stress_given_other(law: Law, l2: float, s1: float, guess=1.0) -> float:
    """l1 such that sigma_1(l1, l2) = s1 (uniaxial plane-strain stretching with a free side)."""
    sol = optimize.brentq(lambda l1: law.principal_cauchy(l1, l2)[0] - s1, 0.2, 5.0, xtol=1e-15, rtol=1e-15)
    return float(sol)


# ----------------------------------------------------------------------------------------
# Growth eigenstrain and generalized plane strain (the project keywords)
# ----------------------------------------------------------------------------------------
#
# *VOLUME CHANGE dv: F = F_e F_g, F_g = g I, g = (1 + dv)^(1/3) (Rodriguez, Hoger &
# McCulloch 1994), W = g^3 W_e(C / g^2); the Cauchy stress is the elastic law's at F_e:
#     sigma = F S F^T / J = F_e S_e(C_e) F_e^T / J_e.
# *AXIAL STRETCH lambda_z: F33 = lambda_z.
#
# A free body (statically determinate supports) stays homogeneous, F = diag(l, l, lambda_z),
# with sigma_11 = sigma_22 = 0 and sigma_33 carried by the plane-strain (or axial) constraint.
# In plane strain (lambda_z = 1) the stress-free state F_e = I would need F33 = g != 1, so
# the body is NOT stress free: F_e = diag(l/g, l/g, 1/g) and l solves sigma_11(F_e) = 0,
# which is not g: at small strain l - 1 = (1 + nu)(g - 1) (sigma_33 = -E (g - 1) pushes the
# plane out by Poisson's effect), with nu the Poisson ratio of the law. A clamped body (F = I) carries sigma = sigma_e(I / g), hydrostatic for an
# isochoric/volumetric split law: sigma = U'(1 / g^3) I.


def growth_factor(dv: float) -> float:
    return (1.0 + dv) ** (1.0 / 3.0)


def elastic_gradient(l1: float, l2: float, dv: float = 0.0, axial_stretch: float = 1.0) -> np.ndarray:
    """F_e = diag(l1, l2, lambda_z) / g."""
    return np.diag([l1, l2, axial_stretch]) / growth_factor(dv)


def free_inplane_stretch(law: Law, dv: float = 0.0, axial_stretch: float = 1.0) -> float:
    """Equal in-plane stretch l of a free body: sigma_11 = sigma_22 = 0 at F = diag(l, l, lambda_z), F_e = F / g."""
    sol = optimize.brentq(
        lambda l: law.cauchy(elastic_gradient(l, l, dv, axial_stretch))[0, 0], 0.2, 5.0, xtol=1e-15, rtol=1e-15
    )
    return float(sol)


def clamped_growth_pressure(law: Law, dv: float) -> float:
    """Hydrostatic Cauchy stress of a clamped body (F = I) with volume change dv, AVRIL law: U'(J_e), J_e = 1/g^3."""
    assert law.kind == "AVRIL"
    Je = 1.0 / (1.0 + dv)
    return law.params[1] * (Je - 1.0 / Je)


# ----------------------------------------------------------------------------------------
# Annulus: axisymmetric plane-strain BVP
# ----------------------------------------------------------------------------------------


@dataclass
class AnnulusSolution:
    law: Law
    A: float
    B: float
    sol: object

    def r(self, R):
        return self.sol.sol(np.asarray(R, dtype=float))[0]

    def u_r(self, R):
        R = np.asarray(R, dtype=float)
        return self.r(R) - R

    def u_xy(self, X, Y):
        """Displacement at reference points (X, Y)."""
        R = np.hypot(X, Y)
        ur = self.u_r(R)
        return ur * X / R, ur * Y / R


def annulus(law: Law, A: float = 1.0, B: float = 2.0, p: float = 0.0, tension: float = 0.0, tol: float = 1e-10):
    """Inner radius A clamped, outer radius B under follower pressure p plus Laplace tension T (p_T = T/r)."""

    def rhs(R, y):
        r, rp = y
        lt = r / R
        P1, P2 = law.principal_piola(rp, lt)
        P11, _, P12, _ = _dP_dl(law, rp, lt)
        rpp = ((P2 - P1) / R - P12 * (rp / R - r / R**2)) / P11
        return np.vstack([rp, rpp])

    def bc(ya, yb):
        rB, rpB = yb
        lt = rB / B
        P1, _ = law.principal_piola(rpB, lt)
        p_tot = p + tension / rB
        return np.array([ya[0] - A, P1 + p_tot * lt])

    R = np.linspace(A, B, 41)
    y0 = np.vstack([R, np.ones_like(R)])
    sol = integrate.solve_bvp(rhs, bc, R, y0, tol=tol, max_nodes=200000, bc_tol=1e-13)
    if not sol.success:
        raise RuntimeError(f"annulus BVP failed: {sol.message}")
    return AnnulusSolution(law, A, B, sol)


def patch_linear_stress(E: float, nu: float, exx: float, eyy: float, gxy: float):
    """Plane-strain small-strain stresses (sx, sy, sz, txy)."""
    lam, mu = E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))
    tr = exx + eyy
    return lam * tr + 2 * mu * exx, lam * tr + 2 * mu * eyy, lam * tr, mu * gxy
