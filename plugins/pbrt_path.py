"""pbrt_path — a differentiable path tracer that gives textures pbrt-v4's differentials everywhere.

Mitsuba's own integrators leave ``si.duv_dx = si.duv_dy = 0`` in the JIT variants, so every
filtered texture degenerates to a point sample under them. ``pbrt_path`` is Mitsuba's ``path``
light transport (emitter sampling with MIS, BSDF sampling, Russian roulette) written as a path
replay integrator (like Mitsuba's ``prb``: primal, forward and backward modes through
``mi.render``/``dr.backward``/``dr.forward``) that additionally computes the uv partials of every
hit before its BSDF is evaluated or sampled.

| parameter | type | default | meaning | differentiable |
|---|---|---|---|---|
| max_depth | integer | 6 | longest path depth (-1: unbounded; at most 2^31 - 1) | no |
| rr_depth | integer | 5 | depth at which Russian roulette starts (1 to 2^31 - 1) | no |
| hide_emitters | boolean | false | hide directly visible emitters | no |
| texture_differentials | boolean | true | compute differentials (also needs a texture that uses them) | no |
| spp_scale | string or float | pbrt | footprint scale: `pbrt` = max(1/8, 1/√spp) (pbrt-v4), `none` = one pixel, or a positive number | no |
| footprint | string | sample | camera hits' texture footprint: `sample` (around each sample, as pbrt) or `pixel` (the pixel's own footprint, for textures that opt in; needs a `perspective` sensor and a `box` or `gaussian` film filter) | no |
| silhouette_spp | integer | 0 | `footprint="pixel"`: this many more paths in each pixel whose centre and corner rays disagree about the surface they hit (silhouettes, the horizon), averaged with the sample's; primal renders with a `box` film filter only | no |
| aovs | string | (none) | comma-separated extra outputs: `duv_dx`, `duv_dy` (uv partials at the first hit; 2 channels each) | no |

Where the differentials come from:

* camera hits: the sensor's ray differentials (one pixel), scaled by ``spp_scale``, intersected
  with the tangent plane;
* after an ideal specular reflection or transmission (a delta lobe): the ray differential is
  propagated (pbrt-v4's formulas with shading-normal derivatives; the transmission formula is
  corrected, see :mod:`mitsuba_pbrt_tex.raydiff`) and dropped if an offset exceeds 1e16;
* everywhere else (after diffuse/glossy bounces, or when a propagated differential is lost):
  pbrt-v4's camera approximation — the footprint a camera ray would have at that point —, on
  the shapes whose BSDF or emitter has a texture that reads differentials (its only readers;
  the other shapes' hits after a bounce get zero partials, as under Mitsuba's integrators).

``footprint="pixel"``: with a box film filter each sample counts only in its own pixel, so a
texture that opts in (``pbrt_imagemap`` ``filter="box"``) filters the footprint of the *pixel*
at camera hits — centred on the pixel, with the perspective-corrected partials — and every
sample of a pixel sees the same value: a 1-spp image of such a texture is already its pixel
average (:mod:`mitsuba_pbrt_tex.pixel` explains the geometry and how the texture learns the
pixel without any per-lane data passed to it). This is exact for textures that enter the shading
linearly (albedo, emission); a roughness, bump or opacity texture would converge to the shading
of the pixel-averaged texture, so only opting-in filters are pixel-centred, the other textures
and later bounces keep the sample's footprint (``si.duv_dx``/``si.duv_dy`` are unchanged).

With a ``gaussian`` film filter (Mitsuba's default) a sample would splat into every pixel within
the filter's radius: instead each pixel draws its film positions from the filter and counts its
samples alone, at offsets shared by all pixels in a render so that the pixel can be found
from the position (:class:`~mitsuba_pbrt_tex.pixel.FilterPixels`),
and the opting-in texture filters the film filter's own kernel around the pixel centre
(:mod:`mitsuba_pbrt_tex.gauss`). The image converges to the Gaussian-filtered one. Mitsuba's
``render``/``render_forward``/``render_backward`` are not copied: :meth:`Plugin.render` and the
two others hand them a view of the sensor whose film makes image blocks without the filter
(:meth:`Plugin.pixel_view`).

The partials are least-squares solved in the tangent frame, made finite and clamped to ±1e8, and
written to ``si.duv_dx``/``si.duv_dy``, so any texture — ours, Mitsuba's, or a Python texture of
the user's — reads them. Before rendering, the integrator asks the scene's textures whether any
uses differentials (``prepare_differentials()``; Mitsuba's C++ textures never do, a user's Python
texture is assumed to); if none does, nothing is computed and the cost is that of a plain path
tracer.

Samples per pixel: the footprint uses the spp of the ``mi.render`` call, or the total set with
``set_total_spp(n)`` (``python -m mitsuba_pbrt_tex render`` does this when it renders in passes).

Relation to Mitsuba 3.9's ``prb``: :meth:`Plugin.sample` follows ``prb.sample`` stage by stage
and imports Mitsuba's helpers (``mis_weight``, ``solid_angle_to_area_jacobian`` from
``mitsuba.python.ad.integrators.common``, the current variant's) rather than copying them, so with ``texture_differentials``
false, or no texture that reads differentials, it renders and differentiates exactly as ``prb``
(same random numbers; ``tests/test_gradient_workflows.py`` compares gradients). It differs only
where differentials need it:

* before ``si.bsdf()``, each hit gets ``si.duv_dx``/``si.duv_dy`` (``prb`` leaves them 0);
* after BSDF sampling, the ray differential (:class:`~mitsuba_pbrt_tex.raydiff.RayDiff`) is
  propagated through ideal specular lobes or dropped — in scenes where some BSDF has such a
  lobe (read from the BSDFs' flags); elsewhere only camera hits use it;
* the previous hit is kept as an ``Interaction3f`` (``prb``: a whole ``SurfaceInteraction3f``,
  of which the next bounce reads the same fields: a smaller loop state to trace);
* the loop state is only what changes from bounce to bounce: the loop's read-only inputs are
  excluded from it and optional state (the propagated differential, AOVs, the Gaussian film's
  pixel, ``δL``) is ``None`` where it would stay constant (``prb`` carries ``δL`` and its inputs
  in primal renders too, so Dr.Jit records its loop twice to remove them); the camera rays'
  time is broadcast to the loop's width (state narrower than the loop is always re-recorded
  away) and primal renders turn ``OptimizeLoops`` off (:meth:`sample`), so their loop is
  recorded once — tracing the loop in Python is a large part of a render's cost at Mitsuba's
  usual sizes;
* the camera ray's differential is scaled by ``spp_scale`` (``prb`` discards it), the sensor is
  remembered in ``sample_rays`` for the camera approximation, and the scene is searched once
  for textures that read differentials and BSDFs with specular lobes (:meth:`scene_needs`;
  the textures found are prepared again at each render);
* optional AOVs with the first hit's uv partials;
* ``footprint="pixel"``: ``sample()`` publishes the sensor to opting-in textures while it is
  traced (or run, in wavefront mode) — see :mod:`mitsuba_pbrt_tex.pixel`; the light transport,
  the random numbers and ``si`` are those of ``footprint="sample"`` (with a box film filter;
  with a Gaussian one the camera rays go through offsets drawn from the filter, shared by all
  pixels in a render, and each sample counts in the pixel decoded from its first hit);
* ``silhouette_spp > 0`` (with ``footprint="pixel"``, primal renders only): after the sample's
  path, five camera rays per lane (the pixel's centre and corners) find the pixels that cross a
  silhouette; those lanes, compacted, trace ``silhouette_spp`` more paths through random points
  of their pixel (from a sampler forked and seeded from the render's) and return the average;
* under ``dr.freeze`` the spp scale is a literal (the host → device copy of ``dr.opaque`` cannot
  be recorded; spp is part of the frozen function's key).
"""

import drjit as dr
import mitsuba as mi

from mitsuba_pbrt_tex import pixel, raydiff, registry, variants
from mitsuba_pbrt_tex.params import Params, PluginError
from mitsuba_pbrt_tex.raydiff import RayDiff
from mitsuba_pbrt_tex.texture import uses_differentials

#: depths are UInt32 in the loop and int32 in Mitsuba's C++ (-1 means unbounded)
MAX_DEPTH = 2**31 - 1


def _prb_helpers():
    """Mitsuba's own AD-integrator helpers, the current variant's."""
    common = registry.ad_integrators_common()
    return common.mis_weight, common.solid_angle_to_area_jacobian

FOOTPRINTS = ('sample', 'pixel')
PIXEL_SENSORS = ('PerspectiveCamera',)
PIXEL_FILTERS = ('BoxFilter', 'GaussianFilter')
AOV_CHANNELS = {'duv_dx': ('duv_dx.u', 'duv_dx.v'), 'duv_dy': ('duv_dy.u', 'duv_dy.v')}


class Plugin:
    NAME = 'pbrt_path'

    # ------------------------------------------------------------------ construction
    @staticmethod
    def precheck(props):
        """Validate what Mitsuba's base class reads itself, with our error messages."""
        variants.require_supported(Plugin.NAME)
        p = Params(Plugin.NAME, props)
        p.int('max_depth', 6, lo=-1, hi=MAX_DEPTH)
        p.int('rr_depth', 5, lo=1, hi=MAX_DEPTH)
        p.bool('hide_emitters', False)

    def setup(self, props):
        variants.require_supported(self.NAME)
        p = Params(self.NAME, props)
        max_depth = p.int('max_depth', 6, lo=-1, hi=MAX_DEPTH)
        self.max_depth = 0xffffffff if max_depth == -1 else max_depth
        self.rr_depth = p.int('rr_depth', 5, lo=1, hi=MAX_DEPTH)
        self.hide_emitters = p.bool('hide_emitters', False)
        self.texture_differentials = p.bool('texture_differentials', True)
        self.spp_mode = self._spp_mode(p)
        self.footprint_mode = p.enum('footprint', 'sample', FOOTPRINTS)
        self.silhouette_spp = p.int('silhouette_spp', 0, lo=0)
        text = p.string('aovs', '') or ''
        self.aov_list = [a.strip() for a in text.split(',') if a.strip()]
        for a in self.aov_list:
            if a not in AOV_CHANNELS:
                raise p.error('aovs', f'unknown output "{a}"; accepted values: '
                                      f'{", ".join(AOV_CHANNELS)}')
        p.finish()
        self.total_spp = None

    def _spp_mode(self, p):
        if not p.has('spp_scale'):
            return 'pbrt'
        kind = str(p.props.type('spp_scale')).split('.')[-1]
        if kind in ('Float', 'Integer'):
            return p.float('spp_scale', 1.0, lo=0.0, lo_open=True)
        return p.enum('spp_scale', 'pbrt', ('pbrt', 'none'))

    def aov_names(self):
        return [c for a in self.aov_list for c in AOV_CHANNELS[a]]

    def to_string(self):
        return (f'{self.NAME}[max_depth={self.max_depth}, rr_depth={self.rr_depth}, '
                f'hide_emitters={self.hide_emitters}, texture_differentials='
                f'{self.texture_differentials}, spp_scale={self.spp_mode}, '
                f'footprint={self.footprint_mode}, silhouette_spp={self.silhouette_spp}, '
                f'aovs={self.aov_list}]')

    def set_total_spp(self, spp):
        """Use ``spp`` (not the spp of each ``mi.render`` call) for the footprint scale."""
        self.total_spp = None if spp is None else int(spp)

    # ------------------------------------------------------------------ what the scene needs
    def needs_differentials(self, scene) -> bool:
        """Does any texture of the scene use differentials? (Also prepares them.)"""
        return self.scene_needs(scene)[0]

    def scene_needs(self, scene) -> tuple:
        """(does any texture use differentials — also prepares them —, does any BSDF have an
        ideal specular lobe to propagate a ray differential through, the shapes whose textures
        read differentials: :func:`_reader_shapes`).

        The scene is traversed once, not at every render (10 ms for a thousand shapes): while
        a scene lives, Mitsuba keeps its shapes in one JIT array (``shapes_dr()``), and holding
        that array makes its variable index a key that no later scene can take (Mitsuba objects
        admit no weak references, and an ``id()`` can be reused). A texture, once prepared,
        stays so (an image rebuilds every MIP level it had when its texels change). A scene
        without shapes is traversed every time (there is nothing to key on, little to
        traverse)."""
        if not self.texture_differentials:
            return False, False, None
        shapes = scene.shapes_dr()
        cached = getattr(self, '_scene_needs', None)
        if cached is not None and shapes.index != 0 and cached[0].index == shapes.index:
            _, readers, specular, mask = cached
            return bool(readers), specular, mask
        nodes = list(mi.traverse(scene).hierarchy.keys())
        readers = [n for n in nodes if isinstance(n, mi.Texture) and uses_differentials(n)]
        delta = int(mi.BSDFFlags.DeltaReflection | mi.BSDFFlags.DeltaTransmission)
        specular = any(int(n.flags()) & delta for n in nodes if isinstance(n, mi.BSDF))
        mask = _reader_shapes(scene, readers)
        self._scene_needs = (shapes, readers, specular, mask)
        return bool(readers), specular, mask

    def footprint(self, sensor) -> raydiff.CameraFootprint:
        """The camera approximation's minimum differentials (512 rays and a few small kernels,
        ~0.4 ms of tracing): found again when the sensor has changed — any of its parameters
        (:func:`_state_key`) — and always while ``dr.freeze`` records (the frozen function must
        record those kernels)."""
        key, held = _state_key(sensor)
        cached = getattr(self, '_camera', None)
        if cached is not None and cached[0] == key and \
                not dr.flag(dr.JitFlag.FreezingScope):
            return cached[2]
        with dr.suspend_grad():
            camera = raydiff.CameraFootprint(sensor)
        self._camera = (key, held, camera)
        return camera

    def sample_rays(self, scene, sensor, sampler):
        """The base class's camera rays; remembers the sensor for the camera approximation.
        With a Gaussian film and ``footprint="pixel"`` (``sensor`` is then the
        :class:`_PixelSensor` view made by :meth:`render`): the rays through film positions
        drawn from the filter around each pixel (offsets shared by all pixels, so that the
        pixel can be found again from the position: :class:`~mitsuba_pbrt_tex.pixel.
        FilterPixels`), and the pixel centre as the position to count them at."""
        pixels = getattr(sensor, 'pixels', None)
        sensor = getattr(sensor, 'sensor', sensor)
        self._sensor = sensor
        ray, weight, pos = self._pbrt_base.sample_rays(self, scene, sensor, sampler)
        if pixels is not None:
            ray, weight, pos = pixels.rays(sensor, ray, pos, sampler.sample_count())
        self._pixel_pos = pos         # box filter: the sample's pixel; Gaussian: its centre
        return ray, weight, pos

    # ------------------------------------------------------------------ rendering
    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        """``ADIntegrator.render``, given :meth:`pixel_view` of the sensor."""
        return self._pbrt_base.render(self, scene, self.pixel_view(scene, sensor, seed), seed,
                                      spp, develop, evaluate)

    def render_forward(self, scene, params, sensor=0, seed=0, spp=0):
        """``RBIntegrator.render_forward``, given :meth:`pixel_view` of the sensor."""
        return self._pbrt_base.render_forward(self, scene, params,
                                              self.pixel_view(scene, sensor, seed), seed, spp)

    def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
        """``RBIntegrator.render_backward``, given :meth:`pixel_view` of the sensor."""
        return self._pbrt_base.render_backward(self, scene, params, grad_in,
                                               self.pixel_view(scene, sensor, seed), seed, spp)

    def pixel_view(self, scene, sensor, seed=0):
        """The sensor Mitsuba's ``render`` methods are given: the sensor itself, except with
        ``footprint="pixel"``, a Gaussian film filter and a texture that uses differentials —
        then a :class:`_PixelSensor`, whose film makes image blocks that do not splat (each
        sample counts in the one pixel it was drawn for, :meth:`sample_rays`) and which
        carries the render's :class:`~mitsuba_pbrt_tex.pixel.FilterPixels`. Mitsuba's
        ``render``, ``render_forward``, ``render_backward`` run unchanged on it."""
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        self._pixels = None
        if self.footprint_mode != 'pixel' or not self.needs_differentials(scene):
            return sensor
        self.pixel_sensor(sensor)                   # the errors, in our words
        film = sensor.film()
        if film.rfilter().class_name() == 'BoxFilter':
            return sensor
        if self.silhouette_spp:
            raise PluginError(f'{self.NAME}: parameter "silhouette_spp": value '
                              f'{self.silhouette_spp} needs the film filter "box", got '
                              f'{film.rfilter().class_name()}; use 0 with "gaussian"')
        self._pixels = pixel.FilterPixels(film, seed)
        return _PixelSensor(sensor, self._pixels)

    def pixel_sensor(self, sensor):
        """The sensor to publish for ``footprint="pixel"`` (None for ``sample``); an error names
        what does not fit."""
        if self.footprint_mode != 'pixel':
            return None
        kind = sensor.class_name()
        if kind not in PIXEL_SENSORS:
            raise PluginError(f'{self.NAME}: parameter "footprint": value "pixel" needs a '
                              f'perspective sensor, got {kind}; accepted values: '
                              f'{", ".join(FOOTPRINTS)}')
        rfilter = sensor.film().rfilter().class_name()
        if rfilter not in PIXEL_FILTERS:
            raise PluginError(f'{self.NAME}: parameter "footprint": value "pixel" needs the '
                              f'film filter "box" or "gaussian", got {rfilter}; accepted '
                              f'values: {", ".join(FOOTPRINTS)}')
        return sensor

    # ------------------------------------------------------------------ the path tracer
    def sample(self, mode, scene, sampler, ray, δL, state_in, active, **kwargs):
        """See ``ADIntegrator.sample()``: :meth:`trace`, with the sensor published to opting-in
        textures for ``footprint="pixel"``, and extra samples in silhouette pixels
        (``silhouette_spp``)."""
        # Primal renders record trace()'s loop once: its loop state holds nothing constant but
        # the rays' time (see trace()), so OptimizeLoops' second recording, which would remove
        # such state, costs more tracing than it saves. Differentiable renders keep it (its
        # literal propagation prunes derivative code).
        optimize = dr.flag(dr.JitFlag.OptimizeLoops) and mode != dr.ADMode.Primal
        with dr.scoped_set_flag(dr.JitFlag.OptimizeLoops, optimize):
            sensor = getattr(self, '_sensor', None) or scene.sensors()[0]
            prep = self.prepare_trace(scene, sampler, sensor)
            published = self.pixel_sensor(sensor) if prep[0] else None
            extra = self.silhouette_spp if published is not None else 0
            if extra and mode != dr.ADMode.Primal:
                raise PluginError(f'{self.NAME}: parameter "silhouette_spp": value {extra} is for '
                                  f'primal renders; differentiable renders need 0')
            if published is None:
                return self.trace(mode, scene, sampler, ray, δL, state_in, active, prep=prep)
            pixels = getattr(self, '_pixels', None)
            if pixels is None and sensor.film().rfilter().class_name() != 'BoxFilter':
                # a Gaussian film, but the rays are not ours (sample() called without render()):
                # the textures keep the sample's footprint
                return self.trace(mode, scene, sampler, ray, δL, state_in, active, prep=prep)
            with pixel.published(published, pixels):
                out = self.trace(mode, scene, sampler, ray, δL, state_in, active, prep=prep,
                                 pixels=pixels)
                if pixels is not None:
                    self.count_in_decoded_pixel(pixels)
                if extra:
                    L, valid, aovs, state = out
                    edge = self.silhouette_pixels(scene, sensor, mi.Bool(active))
                    acc = self.silhouette_paths(scene, sensor, sampler, edge, prep)
                    L = dr.select(edge, (L + acc) * (1.0 / (extra + 1)), L)
                    out = (L, valid, aovs, L)
                return out

    def count_in_decoded_pixel(self, pixels):
        """Gaussian film: count each camera hit in the pixel its film position decodes to —
        the pixel its textures centred on (:meth:`trace` decodes it exactly as they do) — by
        updating, in place, the positions ``sample_rays`` returned (the object Mitsuba's
        ``render`` splats with). Samples drawn for pixel c decode to c unless rounding moves a
        hit by more than half a stratum (≥ 1/64 pixel up to 1024 spp); were it ever to happen,
        the texture and the film would still agree on the pixel."""
        pix, ok = self._decoded
        pos = self._pixel_pos
        new = dr.select(ok, mi.Vector2f(pix) + pixels.offset + 0.5, mi.Vector2f(pos))
        pos.x, pos.y = new.x, new.y

    def silhouette_paths(self, scene, sensor, sampler, edge, prep):
        """Sum of the extra paths of the ``edge`` lanes (0 elsewhere). The edge lanes are
        compacted first — a few percent of the lanes, which a masked loop over all lanes would
        carry along — and draw from a sampler of their own, seeded from this one. (Compaction
        needs ``sample()`` to run outside a symbolic scope: Mitsuba's ``render``,
        ``render_forward`` and ``render_backward`` call it there, in symbolic and wavefront
        mode and under ``dr.freeze``.)"""
        pixel_pos = mi.Vector2f(self._pixel_pos)
        index = dr.compress(edge)
        count = dr.width(index)
        total = dr.zeros(mi.Spectrum, dr.width(edge))
        if count == 0:
            return total
        seed = dr.gather(mi.UInt32, mi.UInt32(sampler.next_1d() * 4294967040.0), 0)
        sub = sampler.fork()
        sub.seed(seed, count)
        acc = self.silhouette_samples(scene, sensor, sub, dr.gather(mi.Vector2f, pixel_pos, index),
                                      dr.full(mi.Bool, True, count), prep)
        dr.scatter(total, acc, index)
        return total

    def prepare_trace(self, scene, sampler, sensor):
        """(does any texture use differentials, the camera differential's scale, the camera
        approximation, does a BSDF have an ideal specular lobe, the shapes whose textures read
        differentials (:func:`_reader_shapes`)) — computed once per ``sample()``, outside any
        symbolic loop."""
        want, specular, gate = self.scene_needs(scene)
        spp = self.total_spp or sampler.sample_count()
        # opaque: the scale changes with spp, and a literal would recompile the kernel each time
        # (but a frozen function cannot record the host → device copy; spp is part of its key)
        scale = raydiff.spp_scale(spp, self.spp_mode)
        scale = mi.Float(scale) if dr.flag(dr.JitFlag.FreezingScope) else dr.opaque(mi.Float, scale)
        return want, scale, (self.footprint(sensor) if want else None), specular, gate

    # ------------------------------------------------------------------ silhouette samples
    def _film_ray(self, sensor, pixel_pos, offset, active):
        """The camera ray through ``pixel_pos + offset`` (full-film pixel coordinates)."""
        film = sensor.film()
        size = mi.ScalarVector2f(film.crop_size())
        origin = mi.ScalarVector2f(film.crop_offset())
        pos = (pixel_pos + offset - origin) / size
        ray, _ = sensor.sample_ray_differential(mi.Float(sensor.shutter_open()), mi.Float(0.5),
                                                pos, mi.Point2f(0.5), active)
        return ray

    def silhouette_pixels(self, scene, sensor, active):
        """Lanes whose pixel's centre and corner rays disagree about the surface they hit (a
        miss, another shape, or normals more than ~25° apart): the pixel crosses a silhouette."""
        pixel_pos = mi.Vector2f(self._pixel_pos)
        hits = []
        for offset in ((0.5, 0.5), (0, 0), (1, 0), (0, 1), (1, 1)):
            ray = self._film_ray(sensor, pixel_pos, mi.Vector2f(*offset), active)
            si = scene.ray_intersect(mi.Ray3f(ray), mi.RayFlags.Minimal, True, active)
            hits.append((si.is_valid(), dr.reinterpret_array(mi.UInt32, si.shape),
                         mi.Vector3f(si.n)))
        valid0, shape0, n0 = hits[0]
        edge = mi.Bool(False)
        for valid, shape, n in hits[1:]:
            edge |= (valid != valid0) | (valid & ((shape != shape0) | (dr.dot(n, n0) < 0.9)))
        return active & edge

    @dr.syntax
    def silhouette_samples(self, scene, sensor, sampler, pixel_pos, edge, prep):
        """Sum of ``silhouette_spp`` more paths through random points of each ``edge`` lane's
        pixel ``pixel_pos`` (footprints stay the pixel's)."""
        k = mi.UInt32(0)
        acc = mi.Spectrum(0)
        while dr.hint(edge & (k < self.silhouette_spp), label='pbrt_path (silhouettes)',
                      exclude=[self, scene, sensor, pixel_pos, edge, prep]):   # read only
            ray = self._film_ray(sensor, pixel_pos, sampler.next_2d(), edge)
            L, _, _, _ = self.trace(dr.ADMode.Primal, scene, sampler, ray, None, None, edge,
                                    prep=prep)
            acc += L
            k += 1
        return acc

    @dr.syntax
    def trace(self, mode, scene, sampler, ray, δL, state_in, active, prep=None, pixels=None,
              **kwargs):
        """The path tracer. The stages are those of Mitsuba 3.9's ``prb`` (same helpers, same
        order of random numbers), plus the stages marked "differentials". ``prep``: what
        :meth:`prepare_trace` returns. ``pixels`` (Gaussian film, ``footprint="pixel"``): the
        pixel of each camera hit is decoded as the textures decode it, and left in
        ``self._decoded`` (pixel, ok)."""
        mis_weight, solid_angle_to_area_jacobian = _prb_helpers()
        primal = mode == dr.ADMode.Primal
        bsdf_ctx = mi.BSDFContext()
        want, scale, camera, specular_scene, reader_shapes = prep

        # ---- differentials: the camera ray's, scaled for the sample count --------------------
        # every sensor's rays are RayDifferential3f; batch ones hold differentials without
        # has_differentials, so each lane's own decide (RayDiff.of_camera_ray)
        if dr.hint(want and isinstance(ray, mi.RayDifferential3f), mode='scalar'):
            camera_diff = RayDiff.of_camera_ray(ray, scale)
        else:
            camera_diff = RayDiff()
        sensor = getattr(self, '_sensor', None) or scene.sensors()[0]

        # ---- loop state (as prb) -------------------------------------------------------------
        # Only what changes from bounce to bounce is loop state: the loop's inputs that it only
        # reads are excluded below, and the optional state is None where it would stay constant
        # (the ray differential where no specular lobe propagates it, the AOVs, the Gaussian
        # film's pixel, δL in primal renders). Dr.Jit re-records a loop to remove constant state
        # (always when it is narrower than the loop, under OptimizeLoops otherwise); with none
        # left but the time below, and OptimizeLoops off in primal renders (sample()), the body
        # is traced once — tracing, in Python at every render, is a large part of its cost.
        diff = camera_diff if want and specular_scene else None
        first_duv_dx = mi.Vector2f(0) if want and self.aov_list else None
        first_duv_dy = mi.Vector2f(0) if want and self.aov_list else None
        decoded = mi.Point2f(0) if pixels is not None else None
        decoded_ok = mi.Bool(False) if pixels is not None else None
        ray = mi.Ray3f(dr.detach(ray))
        # the camera rays' time is often one value: as wide as the loop, it is not state narrower
        # than the loop, which Dr.Jit removes by recording the loop again
        ray.time = ray.time + dr.zeros(mi.Float, dr.width(ray))
        depth = mi.UInt32(0)
        L = mi.Spectrum(0 if primal else state_in)
        δL = None if primal else mi.Spectrum(δL if δL is not None else 0)
        β = mi.Spectrum(1)
        η = mi.Float(1)
        active = mi.Bool(active)
        pi = scene.ray_intersect_preliminary(ray, coherent=True, reorder=False, active=active)
        ray_prev = mi.Ray3f(ray)
        pi_prev = dr.zeros(mi.PreliminaryIntersection3f)
        si_prev = dr.zeros(mi.Interaction3f)
        bsdf_pdf_prev = mi.Float(1.0)
        bsdf_delta_prev = mi.Bool(True)

        if dr.hint(self.hide_emitters, mode='scalar'):
            skip = pi.is_valid() & (pi.shape.emitter() != None) & active  # noqa: E711
            si_skip = pi.compute_surface_interaction(ray, mi.RayFlags.Minimal, skip)
            pi_after = self.skip_area_emitters(scene, si_skip.spawn_ray(ray.d), True, skip)
            pi[skip] = pi_after

        while dr.hint(active, max_iterations=self.max_depth, label=f'pbrt_path ({mode.name})',
                      exclude=[scene, self, sensor, mode, primal, bsdf_ctx, mis_weight,
                               solid_angle_to_area_jacobian, want, scale, camera,
                               specular_scene, reader_shapes, pixels, camera_diff]):
            active_next = mi.Bool(active)

            # ---- the hit, with derivative tracking in the differential phases --------------
            with dr.resume_grad(when=not primal):
                si = pi.compute_surface_interaction(ray, ray_flags=mi.RayFlags.All)
                if dr.hint(not primal, mode='scalar'):
                    if depth >= 1:
                        si_prev_diff = pi_prev.compute_surface_interaction(
                            ray_prev, ray_flags=mi.RayFlags.Minimal)
                        si_prev = dr.replace_grad(si_prev, _interaction(si_prev_diff))
                        si_detached = dr.detach(si)
                        wi_global = dr.normalize(si_prev.p - si_detached.p)
                        si.wi = dr.replace_grad(si.wi, si_detached.to_local(wi_global))

            # ---- Gaussian film: the pixel a camera hit counts in (as the textures find it) --
            if dr.hint(pixels is not None, mode='scalar'):
                at_camera = active & (depth == 0) & si.is_valid()
                pix, pix_ok = dr.if_stmt(
                    args=(at_camera,), cond=at_camera,
                    true_fn=lambda m: pixel.sample_pixel(sensor, si, pixels),
                    false_fn=lambda m: (mi.Point2f(0), mi.Bool(False)),
                    label='pbrt_path: pixel')
                decoded = dr.select(at_camera & pix_ok, pix, decoded)
                decoded_ok |= at_camera & pix_ok

            # ---- differentials: footprint of this hit → si.duv_dx, si.duv_dy ---------------
            dpdx, dpdy = mi.Vector3f(0), mi.Vector3f(0)
            if dr.hint(want, mode='scalar'):
                valid = si.is_valid()
                p_hit, n_hit = dr.detach(si.p), dr.detach(si.n)
                # each source as a symbolic conditional: a packet of lanes none of which needs
                # it skips it (camera rays have a differential; diffuse bounces do not)
                if dr.hint(specular_scene, mode='scalar'):
                    ray_diff = diff
                    use = valid & diff.valid
                else:
                    ray_diff = camera_diff  # no specular lobe: only camera rays have one
                    use = valid & camera_diff.valid & (depth == 0)
                dpdx, dpdy, ok = dr.if_stmt(
                    args=(p_hit, n_hit, use), cond=use, true_fn=ray_diff.footprint,
                    false_fn=lambda p, n, m: (mi.Vector3f(0), mi.Vector3f(0), mi.Bool(False)),
                    label='pbrt_path: differential')
                use = valid & ~ok
                if dr.hint(reader_shapes is not None, mode='scalar'):
                    # the camera approximation's only reader is the hit's own textures: none on
                    # the other shapes (camera hits keep it for the AOVs)
                    shape = dr.reinterpret_array(mi.UInt32, si.shape)
                    use &= (depth == 0) | dr.gather(
                        mi.Bool, reader_shapes, shape, use & (shape < dr.width(reader_shapes)))
                dpdx, dpdy = dr.if_stmt(
                    args=(p_hit, n_hit, use, dpdx, dpdy), cond=use,
                    true_fn=lambda p, n, m, x, y: camera.dp_dxy(p, n, scale, m),
                    false_fn=lambda p, n, m, x, y: (x, y), label='pbrt_path: camera footprint')
                duv_dx, duv_dy = raydiff.uv_partials(dr.detach(si.dp_du), dr.detach(si.dp_dv),
                                                     dpdx, dpdy)
                si.duv_dx = dr.select(valid, duv_dx, 0)
                si.duv_dy = dr.select(valid, duv_dy, 0)
                if dr.hint(bool(self.aov_list), mode='scalar'):
                    first_duv_dx = dr.select(depth == 0, si.duv_dx, first_duv_dx)
                    first_duv_dy = dr.select(depth == 0, si.duv_dy, first_duv_dy)

            bsdf = si.bsdf(ray)

            # ---- direct emission ------------------------------------------------------------
            if dr.hint(self.hide_emitters, mode='scalar'):
                active_next &= ~((depth == 0) & ~si.is_valid())
            ds = mi.DirectionSample3f(scene, si=si, ref=si_prev)
            mis = mis_weight(bsdf_pdf_prev,
                             scene.pdf_emitter_direction(si_prev, ds, ~bsdf_delta_prev))
            with dr.resume_grad(when=not primal):
                Le = β * mis * ds.emitter.eval(si, active_next)

            # ---- emitter sampling (detached sample, attached evaluation) -------------------
            active_next &= (depth + 1 < self.max_depth) & si.is_valid()
            active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
            ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(), True, active_em)
            active_em &= (ds.pdf != 0.0)
            with dr.resume_grad(when=not primal):
                if dr.hint(not primal, mode='scalar'):
                    flags = ds.emitter.flags()
                    is_surface = mi.has_flag(flags, mi.EmitterFlags.Surface)
                    is_infinite = mi.has_flag(flags, mi.EmitterFlags.Infinite)
                    textured_area_em = active_em & is_surface & mi.has_flag(
                        flags, mi.EmitterFlags.SpatiallyVarying)
                    # re-attach the sample to a (moving) textured area emitter, as prb does
                    ray_em = si.spawn_ray_to(ds.p)
                    ray_em.o = dr.fma(ray_em.d, ray_em.maxt, ray_em.o)
                    ray_em.maxt = dr.largest(ray_em.maxt)
                    si_em = scene.ray_intersect(ray_em, textured_area_em)
                    ds_diff = mi.DirectionSample3f(scene, si_em, si)
                    ds_diff = dr.select(textured_area_em, ds_diff,
                                        dr.zeros(mi.DirectionSample3f))
                    ds_diff.d = dr.select(textured_area_em, ds_diff.d,
                                          dr.normalize(ds.p - si.p))
                    ds_diff.d = dr.select(~is_infinite, ds_diff.d, ds.d)
                    ds = dr.replace_grad(ds, ds_diff)
                    J = solid_angle_to_area_jacobian(si.p, dr.detach(ds.p), dr.detach(ds.n),
                                                     active_em & is_surface)
                    em_val = scene.eval_emitter_direction(si, ds, active_em)
                    inv_pdf = dr.select(ds.pdf != 0, dr.rcp(ds.pdf), 0)
                    em_weight = dr.replace_grad(em_weight, em_val * dr.detach(inv_pdf))
                    em_weight *= dr.relative_grad(J)
                wo = si.to_local(ds.d)
                bsdf_value_em, bsdf_pdf_em = bsdf.eval_pdf(bsdf_ctx, si, wo, active_em)
                mis_em = dr.select(ds.delta, 1, mis_weight(ds.pdf, bsdf_pdf_em))
                Lr_dir = β * mis_em * bsdf_value_em * em_weight

            # ---- BSDF sampling (detached) --------------------------------------------------
            bsdf_sample, bsdf_weight = bsdf.sample(bsdf_ctx, si, sampler.next_1d(),
                                                   sampler.next_2d(), active_next)
            L = (L + Le + Lr_dir) if primal else (L - Le - Lr_dir)
            wo_world = si.to_world(bsdf_sample.wo)
            ray_next = si.spawn_ray(wo_world)

            # ---- differentials: propagate through ideal specular lobes ---------------------
            # (only in scenes that have one: elsewhere the differential is dropped here anyway)
            if dr.hint(want and specular_scene, mode='scalar'):
                # as a symbolic conditional: packets without a specular bounce skip the math
                specular = mi.has_flag(bsdf_sample.sampled_type, mi.BSDFFlags.Delta) & \
                    si.is_valid() & diff.valid
                fields = dr.if_stmt(
                    args=(specular,), cond=specular,
                    true_fn=lambda m: diff.after_specular(
                        si, bsdf_sample, wo_world, ray_next.o, dpdx, dpdy).fields(),
                    false_fn=lambda m: diff.dropped().fields(), label='pbrt_path: specular')
                diff = RayDiff(*fields)

            η *= bsdf_sample.eta
            β *= bsdf_weight
            si_prev = _interaction(dr.detach(si, True))
            bsdf_pdf_prev = bsdf_sample.pdf
            bsdf_delta_prev = mi.has_flag(bsdf_sample.sampled_type, mi.BSDFFlags.Delta)

            # ---- stopping: zero throughput, Russian roulette -------------------------------
            β_max = dr.max(mi.unpolarized_spectrum(β))
            active_next &= (β_max != 0)
            rr_prob = dr.minimum(β_max * η ** 2, .95)
            rr_active = depth >= self.rr_depth
            β[rr_active] *= dr.rcp(rr_prob)
            rr_continue = sampler.next_1d() < rr_prob
            active_next &= ~rr_active | rr_continue

            pi_next = scene.ray_intersect_preliminary(ray_next, coherent=False, reorder=False,
                                                      active=active_next)

            # ---- differential phase: replay with attached BSDF values (as prb) -------------
            if dr.hint(not primal, mode='scalar'):
                si_next = pi_next.compute_surface_interaction(ray_next,
                                                              ray_flags=mi.RayFlags.Minimal,
                                                              active=active_next)
                with dr.resume_grad():
                    J = solid_angle_to_area_jacobian(si.p, si_next.p, si_next.n,
                                                     active_next & si_next.is_valid())
                    wo_diff = dr.normalize(si_next.p - si.p)
                    wo_w = dr.replace_grad(ray_next.d,
                                           dr.select(si_next.is_valid(), wo_diff, ray_next.d))
                    bsdf_val = bsdf.eval(bsdf_ctx, si, si.to_local(wo_w), active_next)
                    Lr_ind = L * dr.relative_grad(bsdf_val) * dr.relative_grad(J)
                    Lo = Le + Lr_dir + Lr_ind
                    if dr.hint(dr.flag(dr.JitFlag.VCallRecord) and not dr.grad_enabled(Lo),
                               mode='scalar'):
                        raise Exception(
                            'pbrt_path: the contribution computed by the differential phase is '
                            'not attached to the AD graph (did you call dr.enable_grad(..) on a '
                            'scene parameter, and params.update() after it?)')
                    if dr.hint(mode == dr.ADMode.Backward, mode='scalar'):
                        dr.backward_from(δL * Lo)
                    else:
                        δL += dr.forward_to(Lo)

            # ---- reorder threads for the next iteration (as prb; CUDA only) ----------------
            reorder_hint = dr.reinterpret_array(mi.UInt32, pi_next.shape)
            reorder_hint = (reorder_hint << 1) | dr.select(active_next, 1, 0)
            depth = dr.reorder_threads(reorder_hint, 16, depth)

            depth[si.is_valid()] += 1
            active = active_next
            pi_prev = pi
            pi = pi_next
            ray_prev = ray
            ray = ray_next

        aovs = []
        for a in self.aov_list:
            v = first_duv_dx if a == 'duv_dx' else first_duv_dy
            v = mi.Vector2f(0) if v is None else v            # no texture reads them
            aovs += [v.x, v.y]
        if dr.hint(pixels is not None, mode='scalar'):
            self._decoded = (decoded, decoded_ok)
        return (L if primal else δL, depth != 0, aovs, L)


class _PixelFilm:
    """A film seen through ``footprint="pixel"`` with a Gaussian filter: everything is the
    film's, except that :meth:`create_block` gives blocks without the filter (a sample counts in
    the pixel of its position alone; ``ImageBlock`` treats a missing filter as the box)."""

    def __init__(self, film):
        self.film = film

    def __getattr__(self, name):
        return getattr(self.film, name)

    def create_block(self, *args, **kwargs):
        block = self.film.create_block(*args, **kwargs)
        return mi.ImageBlock(block.size(), block.offset(), block.channel_count(), None,
                             border=False, normalize=block.normalize(),
                             coalesce=block.coalesce(), warn_negative=block.warn_negative(),
                             warn_invalid=block.warn_invalid())


class _PixelSensor:
    """The sensor as :meth:`Plugin.pixel_view` gives it to Mitsuba's ``render`` methods: the
    sensor's own methods, the film of :class:`_PixelFilm`, and the render's ``pixels``."""

    def __init__(self, sensor, pixels):
        self.sensor = sensor
        self.pixels = pixels
        self._film = _PixelFilm(sensor.film())

    def film(self):
        return self._film

    def __getattr__(self, name):
        return getattr(self.sensor, name)


def _reader_shapes(scene, readers):
    """Which shapes have a texture that reads differentials in their BSDF or emitter (nested
    ones included): a mask over Mitsuba's shape registry ids (``si.shape``) — or None where
    there is nothing to skip: every shape has one, no texture reads differentials, or the scene
    has instances (the shapes hit inside them are not the scene's). The camera approximation
    after a bounce is computed only on the shapes it marks; a propagated ray differential is
    never affected (specular hits use the ray's own, on any shape)."""
    shapes = scene.shapes()
    if not readers or not shapes or any(s.class_name() == 'Instance' for s in shapes):
        return None
    wanted = {id(t) for t in readers}               # the readers are held by the caller
    seen = {}                                       # id → (object held, holds a reader)

    def holds(obj):
        if obj is None:
            return False
        if id(obj) not in seen:
            nodes = mi.traverse(obj).hierarchy.keys()
            seen[id(obj)] = (obj, any(id(n) in wanted for n in nodes))
        return seen[id(obj)][1]

    ids = [int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s))[0]) for s in shapes]
    marked = [i for i, s in zip(ids, shapes) if holds(s.bsdf()) or holds(s.emitter())]
    if len(marked) == len(shapes):
        return None
    table = dr.zeros(mi.Bool, max(ids) + 1)
    if marked:
        dr.scatter(table, True, mi.UInt32(marked))
    dr.eval(table)
    return table


def _state_key(obj) -> tuple:
    """(key, held): what ``obj``'s parameters are now (``mi.traverse``) — each JIT array by
    its variable indices, the others by value — and the JIT arrays themselves, to be kept with
    the key: while they live no other value can take their indices, and writing a parameter
    through ``params`` makes a new variable."""
    params = mi.traverse(obj)
    key, held = [obj.class_name()], []
    for name in params.keys():
        value = params[name]
        value = getattr(value, 'matrix', value)             # transforms: their matrix
        if dr.is_jit_v(type(value)):
            held.append(value)
            key.append((name, tuple(int(v.index) for v in _leaves(value))))
        else:
            key.append((name, repr(value)))
    return tuple(key), held


def _leaves(value):
    """The one-dimensional JIT arrays inside a (nested) Dr.Jit array."""
    if dr.depth_v(type(value)) <= 1:
        return [value]
    return [leaf for entry in value for leaf in _leaves(entry)]


def _interaction(si):
    """What the next bounce reads of a hit (the reference point of its emitter MIS weight):
    an ``Interaction3f`` — fewer loop variables to trace than a whole SurfaceInteraction."""
    return mi.Interaction3f(si.t, si.time, si.wavelengths, si.p, si.n)
