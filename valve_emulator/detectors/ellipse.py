r"""Least-squares ellipse through scattered points, and its width along the x axis.

The fit is the direct least-squares ellipse of A. Fitzgibbon, M. Pilu, R. B. Fisher ("Direct least square
fitting of ellipses", IEEE Trans. PAMI 21 (1999) 476–480) in the numerically stable form of R. Halíř and
J. Flusser ("Numerically stable direct least squares fitting of ellipses", WSCG 1998): minimise the algebraic
distance of the conic :math:`a x^2 + b xy + c y^2 + d x + e y + f = 0` subject to :math:`4ac - b^2 = 1`, which
always yields an ellipse. Points are centred and scaled first, for conditioning.

Choudhury, Thornhill & Shah quantify "apparent stiction" from the PV–OP ellipse as its width along the OP axis
through its centre, :math:`2mn/\sqrt{m^2\sin^2\alpha + n^2\cos^2\alpha}` for semi-axes ``m``, ``n`` and tilt
α; :func:`width_along_x` computes the same chord directly from the conic.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["fit_ellipse", "width_along_x"]


def fit_ellipse(x: np.ndarray, y: np.ndarray) -> np.ndarray | None:
    """Conic coefficients ``(a, b, c, d, e, f)`` of the best ellipse in the original units, or ``None``.

    ``None`` when fewer than 6 points are given or the points do not determine an ellipse (all on a line).
    """
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    if x.size < 6:
        return None
    mx, my = x.mean(), y.mean()
    sx, sy = x.std(), y.std()
    if sx == 0 or sy == 0:
        return None
    u, v = (x - mx) / sx, (y - my) / sy
    d1 = np.column_stack((u * u, u * v, v * v))
    d2 = np.column_stack((u, v, np.ones_like(u)))
    s1, s2, s3 = d1.T @ d1, d1.T @ d2, d2.T @ d2
    try:
        t = -np.linalg.solve(s3, s2.T)
    except np.linalg.LinAlgError:
        return None
    m = s1 + s2 @ t
    # Multiply by the inverse of the constraint matrix C1 = [[0, 0, 2], [0, -1, 0], [2, 0, 0]].
    m = np.vstack((m[2] / 2.0, -m[1], m[0] / 2.0))
    vals, vecs = np.linalg.eig(m)
    vecs = np.real(vecs)
    cond = 4.0 * vecs[0] * vecs[2] - vecs[1] ** 2
    ok = np.flatnonzero(cond > 0)
    if ok.size == 0:
        return None
    a1 = vecs[:, ok[0]]
    a2 = t @ a1
    A, B, C = a1
    D, E, F = a2
    # Back to original units: u = (x - mx)/sx, v = (y - my)/sy.
    a, b, c = A / sx**2, B / (sx * sy), C / sy**2
    d = -2 * a * mx - b * my + D / sx
    e = -2 * c * my - b * mx + E / sy
    f = a * mx**2 + b * mx * my + c * my**2 - D * mx / sx - E * my / sy + F
    return np.array([a, b, c, d, e, f])


def width_along_x(conic: np.ndarray) -> float:
    """Length of the ellipse's chord parallel to the x axis through its centre (NaN if not an ellipse)."""
    a, b, c, d, e, f = conic
    det = 4 * a * c - b * b
    if det <= 0:
        return math.nan
    yc = (b * d - 2 * a * e) / det
    # a x^2 + (b yc + d) x + (c yc^2 + e yc + f) = 0 on the line y = yc
    p, q = b * yc + d, c * yc * yc + e * yc + f
    disc = p * p - 4 * a * q
    return math.sqrt(disc) / abs(a) if disc > 0 else math.nan
