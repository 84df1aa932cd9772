"""Extra paths in the pixels that cross a silhouette (``pbrt_path`` ``silhouette_spp``).

With pixel footprints (``footprint="pixel"``, box film) every sample of a fully covered pixel
sees the pixel's texture average, so a 1-spp image is converged there; what is left is where a
pixel crosses a silhouette or the horizon, and the texture's pixel average no longer describes
what the pixel sees. Those pixels are found by five camera rays per lane that disagree about the
surface they hit (:func:`edge_pixels`) — the pixel's centre and its four corners with a box
film; with a Gaussian film (whose pixel sees ±2 pixels) its centre and the corners of the square
±1.5 pixels around it (3 standard deviations) —; their lanes, compacted, trace ``silhouette_spp``
more paths (:func:`extra_paths`) through points of their pixel (box film) or film offsets
drawn from the filter around its centre (Gaussian film: each an independent point estimate of
the pixel's filtered value, unlike the render's shared offsets), which the integrator averages
with the sample's own.

What those paths estimate at a silhouette is mostly coverage: how much of the pixel (or of the
filter) each surface takes. Independent points estimate it with a binomial error that falls as
``count^-1/2``; the points are therefore the first ``count`` of a (0, 2)-sequence (van der
Corput and Sobol's second dimension) under a random digital shift per lane (:func:`net_point`):
each power-of-two prefix has one point in every elementary interval of its size, so a straight
edge crosses only about ``√count`` of the strata (a horizontal or vertical one, a single row
of them), and the estimate stays unbiased.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .raydiff import film_ray

#: box film: the pixel's centre, then its corners (offsets from the pixel's corner, in pixels)
PROBES = ((0.5, 0.5), (0, 0), (1, 0), (0, 1), (1, 1))
#: Gaussian film: the pixel's centre, then the corners of the square of 3 standard deviations
#: (Mitsuba's gaussian: σ = 0.5 pixel) around it (offsets from the pixel's centre)
FILTER_PROBES = ((0, 0), (-1.5, -1.5), (1.5, -1.5), (-1.5, 1.5), (1.5, 1.5))
#: normals more than ~25° apart count as different surfaces
SAME_NORMAL = 0.9


def _ray(sensor, pixel_pos, offset, active):
    """The camera ray through full-film position ``pixel_pos + offset``."""
    origin = mi.ScalarVector2f(sensor.film().crop_offset())
    ray, _ = film_ray(sensor, pixel_pos + offset - origin, None, active)
    return ray


def edge_pixels(scene, sensor, pixel_pos, active, probes=PROBES):
    """Lanes whose pixel (full-film coordinates of its corner, ``pixel_pos``; of its centre with
    ``FILTER_PROBES``) has probe rays that disagree about the surface they hit: a miss, another
    shape, or normals more than ~25° apart."""
    pixel_pos = mi.Vector2f(pixel_pos)
    hits = []
    for offset in probes:
        ray = _ray(sensor, pixel_pos, mi.Vector2f(*offset), active)
        si = scene.ray_intersect(mi.Ray3f(ray), mi.RayFlags.Minimal, True, active)
        hits.append((si.is_valid(), dr.reinterpret_array(mi.UInt32, si.shape),
                     mi.Vector3f(si.n)))
    valid0, shape0, n0 = hits[0]
    edge = mi.Bool(False)
    for valid, shape, n in hits[1:]:
        edge |= (valid != valid0) | (valid & ((shape != shape0) | (dr.dot(n, n0) < SAME_NORMAL)))
    return active & edge


def extra_paths(trace, sensor, sampler, pixel_pos, edge, count: int, offset=None):
    """Sum of ``count`` more paths in each ``edge`` lane's pixel (0 elsewhere); ``trace(sampler,
    ray, active)`` gives a path's radiance, ``offset(u)`` the film offset from ``pixel_pos`` of
    a uniform 2D sample (default: ``u`` itself, a point of the pixel whose corner it is). The edge lanes are compacted first — a few percent
    of the lanes, which a masked loop over all lanes would carry along — and draw from a sampler
    of their own, seeded from this one. (Compaction needs this to run outside a symbolic scope:
    Mitsuba's ``render`` methods call ``sample()`` there, in symbolic and wavefront mode and
    under ``dr.freeze``.)"""
    index = dr.compress(edge)
    n = dr.width(index)
    total = dr.zeros(mi.Spectrum, dr.width(edge))
    if n == 0:
        return total
    seed = dr.gather(mi.UInt32, mi.UInt32(sampler.next_1d() * 4294967040.0), 0)
    sub = sampler.fork()
    sub.seed(seed, n)
    acc = _paths(trace, sensor, sub, dr.gather(mi.Vector2f, mi.Vector2f(pixel_pos), index),
                 dr.full(mi.Bool, True, n), count, offset or (lambda u: u))
    dr.scatter(total, acc, index)
    return total


def net_point(k, shift_x, shift_y, bits: int):
    """Point ``k`` (UInt32, below ``2^bits``) of the (0, 2)-sequence — van der Corput in x,
    Sobol's second dimension in y — XORed with the lane's digital shift (two UInt32): a point of
    [0, 1)², uniformly distributed for a uniform shift, and the first ``2^m`` points of a lane
    one per elementary interval of area ``2^-m``."""
    x, y = mi.UInt32(0), mi.UInt32(0)
    column = 1 << 31                                    # Sobol's direction numbers for x + 1
    for j in range(bits):
        bit = ((k >> j) & 1) != 0
        x = x ^ dr.select(bit, mi.UInt32(1 << (31 - j)), 0)
        y = y ^ dr.select(bit, mi.UInt32(column), 0)
        column ^= column >> 1
    scale = 2.0 ** -24                                  # float32's 24 bits: below 1 exactly
    return mi.Point2f(mi.Float((x ^ shift_x) >> 8) * scale, mi.Float((y ^ shift_y) >> 8) * scale)


def digital_shift(sampler):
    """A lane's random digital shift for :func:`net_point`: two UInt32 whose top 24 bits are
    uniform (a float32 sample's resolution)."""
    shift_x = mi.UInt32(sampler.next_1d() * 16777216.0) << 8
    shift_y = mi.UInt32(sampler.next_1d() * 16777216.0) << 8
    return shift_x, shift_y


@dr.syntax
def _paths(trace, sensor, sampler, pixel_pos, edge, count, offset):
    """Sum of ``count`` paths through film positions ``pixel_pos + offset(u)`` of each lane,
    ``u`` the lane's shifted (0, 2)-sequence."""
    bits = max(1, (count - 1).bit_length())
    shift_x, shift_y = digital_shift(sampler)
    k = mi.UInt32(0)
    acc = mi.Spectrum(0)
    while dr.hint(edge & (k < count), label='pbrt_path (silhouettes)',
                  exclude=[sensor, pixel_pos, edge, shift_x, shift_y]):   # read only
        ray = _ray(sensor, pixel_pos, offset(net_point(k, shift_x, shift_y, bits)), edge)
        acc += trace(sampler, ray, edge)
        k += 1
    return acc
