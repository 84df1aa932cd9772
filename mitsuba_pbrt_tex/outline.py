"""A lookup's footprint parallelogram and the walk along its outline, for Green's-theorem integrals.

Two exact area averages over the footprint ``c + a·e0 + b·e1``, ``a, b ∈ [-1/2, 1/2]``, are line
integrals ``∮ F dy`` around its outline: the ``box`` image filter's (:mod:`.box`, ``F`` an
antiderivative along rows of the bilinear reconstruction) and the checkerboard's ``area`` mode
(:mod:`.checker`, ``F = S(x)·c(y)``). Both integrands are smooth between integer rows (*bands*:
between texel rows, or cell rows), so both walk the outline the same way — this module; each
brings its integral over one piece of the walk:

* :class:`Parallelogram` — the footprint in lattice units; :meth:`Parallelogram.transposed` swaps
  the axes of lanes whose footprint is taller than wide (:meth:`Parallelogram.taller`), so that
  the walk crosses fewer bands (the checkerboard is symmetric under it; the image filter reads its
  texels transposed).
* :class:`Outline` — its corners counter-clockwise from the lowest: ``B``, ``R``, ``T``, ``L``.
  The right chain ``B → R → T`` goes up, the left chain ``T → L → B`` down, so on each chain the
  bands come in order.
* :func:`walk` — one loop along the outline, one iteration per :class:`Piece`: from where the walk
  is to the next band boundary, the edge's end or — for integrands that are also piecewise in x
  (``knots``: the bilinear reconstruction at integer columns) — the next integer column. The
  integrand is a function of the piece and of its own loop state.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi


@dataclass
class Parallelogram:
    """``c + a·e0 + b·e1``, ``a, b ∈ [-1/2, 1/2]``, per lane."""
    c: mi.Point2f
    e0: mi.Vector2f
    e1: mi.Vector2f

    def half_extent(self) -> mi.Vector2f:
        """Half the bounding box's width and height."""
        return 0.5 * (dr.abs(self.e0) + dr.abs(self.e1))

    def taller(self):
        """Lanes whose bounding box is taller than wide (more bands than columns)."""
        h = self.half_extent()
        return h.y > h.x

    def transposed(self, swap) -> 'Parallelogram':
        """The same footprint with x and y exchanged in lanes ``swap``."""
        def t(v, kind):
            return kind(dr.select(swap, v.y, v.x), dr.select(swap, v.x, v.y))
        return Parallelogram(t(self.c, mi.Point2f), t(self.e0, mi.Vector2f),
                             t(self.e1, mi.Vector2f))

    def moved(self, c) -> 'Parallelogram':
        return Parallelogram(mi.Point2f(c), self.e0, self.e1)

    def det(self):
        """Signed area (positive: ``e0``, ``e1`` counter-clockwise)."""
        return self.e0.x * self.e1.y - self.e0.y * self.e1.x

    def outline(self) -> 'Outline':
        h0, h1 = 0.5 * self.e0, 0.5 * self.e1
        corners = [self.c - h0 - h1, self.c + h0 - h1, self.c + h0 + h1, self.c - h0 + h1]
        # clockwise: the same corners in the other order
        ccw = self.det() >= 0
        corners[1], corners[3] = (dr.select(ccw, corners[1], corners[3]),
                                  dr.select(ccw, corners[3], corners[1]))
        k, lowest = mi.UInt32(0), corners[0].y
        for m in (1, 2, 3):
            lower = corners[m].y < lowest
            k = dr.select(lower, m, k)
            lowest = dr.select(lower, corners[m].y, lowest)

        def pick(idx):
            out = corners[3]
            for m in (2, 1, 0):
                out = dr.select(idx == m, corners[m], out)
            return out

        B, R = pick(k), pick((k + 1) & 3)
        return Outline.of(B, R, 2 * self.c - B, 2 * self.c - R)   # opposite: B + T = 2·c


@dataclass
class Edge:
    """From ``start`` to ``start + d``; ``inv`` the reciprocals of ``d``'s components (0 where a
    component is 0)."""
    start: mi.Point2f
    d: mi.Vector2f
    inv: mi.Vector2f

    @staticmethod
    def between(p, q) -> 'Edge':
        d = mi.Vector2f(q - p)
        return Edge(p, d, dr.select(d != 0, dr.rcp(d), 0.0))

    def select(self, mask, other: 'Edge') -> 'Edge':
        return Edge(dr.select(mask, self.start, other.start), dr.select(mask, self.d, other.d),
                    dr.select(mask, self.inv, other.inv))


@dataclass
class Outline:
    """The corners counter-clockwise from the lowest, ``B``, ``R``, ``T``, ``L``, and the edges
    0 = B→R, 1 = R→T (the right chain, upwards), 2 = T→L, 3 = L→B (the left chain, downwards)."""
    B: mi.Point2f
    R: mi.Point2f
    T: mi.Point2f
    L: mi.Point2f
    edges: list

    @staticmethod
    def of(B, R, T, L) -> 'Outline':
        return Outline(B, R, T, L, [Edge.between(B, R), Edge.between(R, T), Edge.between(T, L),
                                    Edge.between(L, B)])

    def edge(self, e) -> Edge:
        """Edge ``e`` (UInt32, per lane)."""
        odd = (e & 1) == 1
        lo = self.edges[1].select(odd, self.edges[0])
        hi = self.edges[3].select(odd, self.edges[2])
        return hi.select(e >= 2, lo)

    def chain_x(self, right: bool, y):
        """x of the right or left chain at height y (between B and T), from the same edge
        values the walk reads, so that it meets a row where the walk does, to the last bit."""
        middle = self.R if right else self.L
        lower, upper = (self.edges[0], self.edges[1]) if right else (self.edges[3],
                                                                      self.edges[2])
        edge = lower.select(y <= middle.y, upper)
        return dr.fma((y - edge.start.y) * edge.inv.y, edge.d.x, edge.start.x)


# ------------------------------------------------------------------------------------ the walk
@dataclass
class Piece:
    """One iteration of :func:`walk`: edge ``e`` from ``(x, y)`` to ``(x1, y1)`` inside band ``j``
    (``y`` between j and j + 1) and, with knots, column cell ``i``. What ends it: ``knot`` (an
    integer column crossed, to the ``right`` or left), ``band`` (a band boundary crossed,
    upwards when ``rising``). Back at B the walk counts as crossing the band boundary above
    (``band``, ``rising``), and a flush iteration (``e`` = 4, not ``walking``: no piece) as
    crossing the next — so an integrand that holds values per band row can hand them out."""
    e: object
    x: object
    y: object
    x1: object
    y1: object
    i: object
    j: object
    knot: object
    band: object
    right: object
    rising: object
    walking: object


@dataclass
class _Event:
    s1: object
    x1: object
    y1: object
    knot: object
    band: object
    end: object
    right: object


def _next_event(edge: Edge, s, i, j, up, knots: bool) -> _Event:
    """The next band boundary, edge end or (``knots``) integer column along ``edge`` from
    param ``s`` in band ``j`` and column cell ``i`` (``up``: the edge's chain goes up)."""
    start, d, inv = edge.start, edge.d, edge.inv
    right = d.x > 0
    knot_x = dr.select(right, i + 1, i)
    band_y = dr.select(up, j + 1, j)
    sk = dr.select(d.x != 0, (knot_x - start.x) * inv.x, dr.inf) if knots else mi.Float(dr.inf)
    # band boundaries only in the chain's direction: corners opposite each other come from the
    # centre (rounded), so a side of a nearly axis-aligned footprint can run an ulp the other
    # way, and its next boundary would then lie behind it, for ever
    along = dr.select(up, d.y > 0, d.y < 0)
    sb = dr.select(along, (band_y - start.y) * inv.y, dr.inf)
    first = dr.minimum(sk, sb)
    end = ~(first < 1)
    band = ~end & (sb <= sk)
    knot = ~end & ~band
    s1 = dr.clip(first, s, 1.0)
    x1 = dr.select(knot, knot_x, dr.fma(s1, d.x, start.x))
    y1 = dr.select(band, band_y, dr.fma(s1, d.y, start.y))
    x1 = dr.select(end, start.x + d.x, x1)
    y1 = dr.select(end, start.y + d.y, y1)
    if knots:
        x1 = dr.clip(x1, i, i + 1)
    return _Event(s1, x1, dr.clip(y1, j, j + 1), knot, band, end, right)


def walk(outline: Outline, active, integrand, carry: tuple, knots: bool, flush: bool,
         label: str) -> tuple:
    """``integrand(piece, *carry) → carry`` over the outline counter-clockwise from B (lanes
    ``active``), cut at band boundaries and, with ``knots``, integer columns; with ``flush``,
    one more iteration back at B (see :class:`Piece`). Returns the final ``carry``."""
    def body(e, s, x, y, i, j, *carry):
        up = e < 2
        step = _next_event(outline.edge(e), s, i, j, up, knots)
        walking = e < 4
        x1 = dr.select(walking, step.x1, x)             # the flush stays put: no piece
        y1 = dr.select(walking, step.y1, y)
        knot = walking & step.knot
        closed = (walking & step.end & (e == 3)) | ~walking     # back at B
        band = (walking & step.band) | closed
        rising = up | closed
        carry = integrand(Piece(e, x, y, x1, y1, i, j, knot, band, step.right, rising, walking),
                          *carry)
        i_n = dr.select(knot, dr.select(step.right, i + 1, i - 1), i)
        j_n = dr.select(band, dr.select(rising, j + 1, j - 1), j)
        next_edge = (walking & step.end) | ~walking
        return (dr.select(next_edge, e + 1, e), dr.select(next_edge, 0.0, step.s1), x1, y1,
                i_n, j_n, *carry)

    B = outline.B
    state = (mi.UInt32(0), mi.Float(0), B.x, B.y, dr.floor(B.x), dr.floor(B.y), *carry)
    edges = 5 if flush else 4
    # every iteration ends the edge or moves to the next column or band towards its end: at
    # most |Δx| + |Δy| + 3 per edge (a NaN ends it), so no step count is needed
    return dr.while_loop(state, lambda e, *_: active & (e < edges), body, max_iterations=-1,
                         label=label)[6:]
