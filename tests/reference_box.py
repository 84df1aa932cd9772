"""Independent numpy reference for the ``box`` filter: the exact area average of a level's
bilinear reconstruction over a footprint parallelogram, by polygon clipping.

Nothing here shares an algorithm with the package (which uses Green's theorem and per-row
antiderivative tables): the parallelogram is clipped (Sutherland–Hodgman, float64) against every
cell between four texel centres it touches; on a cell the reconstruction is one bilinear
polynomial, integrated exactly over each triangle of the clipped polygon's fan by the
edge-midpoint rule (exact for polynomials of degree 2, and ``x·y`` is one).
"""

import numpy as np

import reference_mipmap as ref


def _clip(poly, axis, bound, keep_above):
    out = []
    n = len(poly)
    for k in range(n):
        p, q = poly[k], poly[(k + 1) % n]
        pin = p[axis] >= bound if keep_above else p[axis] <= bound
        qin = q[axis] >= bound if keep_above else q[axis] <= bound
        if pin:
            out.append(p)
        if pin != qin:
            u = (bound - p[axis]) / (q[axis] - p[axis])
            out.append(p + u * (q - p))
    return out


def _area(poly):
    x, y = np.array(poly).T
    return 0.5 * (np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def clipped_cells(quad):
    """(i, j, polygon) for every unit cell [i, i+1] × [j, j+1] that the convex polygon ``quad``
    overlaps with positive area: the part of ``quad`` inside it (Sutherland–Hodgman)."""
    lo, hi = np.min(quad, 0), np.max(quad, 0)
    for j in range(int(np.floor(lo[1])), int(np.floor(hi[1])) + 1):
        for i in range(int(np.floor(lo[0])), int(np.floor(hi[0])) + 1):
            poly = quad
            for axis, bound, above in ((0, i, True), (0, i + 1, False),
                                       (1, j, True), (1, j + 1, False)):
                poly = _clip(poly, axis, bound, above)
                if len(poly) < 3:
                    break
            if len(poly) >= 3:
                yield i, j, poly


def box_average(level, s, t, d0, d1, mode):
    """Average over ``(s, t) + a·d0 + b·d1``, ``a, b ∈ [-1/2, 1/2]``, of the bilinear
    reconstruction of ``level`` (H, W, C) with wrap ``mode``; returns (C,)."""
    h, w = level.shape[:2]
    c = np.array([s * w - 0.5, t * h - 0.5])
    e0 = np.array([d0[0] * w, d0[1] * h])
    e1 = np.array([d1[0] * w, d1[1] * h])
    quad = [c - e0 / 2 - e1 / 2, c + e0 / 2 - e1 / 2, c + e0 / 2 + e1 / 2, c - e0 / 2 + e1 / 2]
    total_area = _area(quad)
    acc = np.zeros(level.shape[2])
    for i, j, poly in clipped_cells(quad):
        corners = [ref.texel(level, np.array([i + bx]), np.array([j + by]), mode)[0]
                   for by in (0, 1) for bx in (0, 1)]

        def f(p):
            fx, fy = p[0] - i, p[1] - j
            return ((1 - fx) * (1 - fy) * corners[0] + fx * (1 - fy) * corners[1]
                    + (1 - fx) * fy * corners[2] + fx * fy * corners[3])

        p0 = poly[0]
        for k in range(1, len(poly) - 1):
            p1, p2 = poly[k], poly[k + 1]
            a = _area([p0, p1, p2])
            acc += a / 3 * (f((p0 + p1) / 2) + f((p1 + p2) / 2) + f((p2 + p0) / 2))
    return acc / total_area
