"""pbrt_path — a differentiable path tracer that gives textures pbrt-v4's differentials everywhere.

Mitsuba's own integrators leave ``si.duv_dx = si.duv_dy = 0`` in the JIT variants, so every
filtered texture degenerates to a point sample under them. ``pbrt_path`` is Mitsuba 3.9's ``prb``
(path replay: primal, forward and backward modes through ``mi.render``/``dr.backward``/
``dr.forward``; emitter sampling with MIS, BSDF sampling, Russian roulette) that also computes the
uv partials of every hit before its BSDF is evaluated or sampled.

| parameter | type | default | meaning | differentiable |
|---|---|---|---|---|
| max_depth | integer | 6 | longest path depth (-1: unbounded; at most 2^31 - 1; 0 renders as 1, as Mitsuba's `prb` does) | no |
| rr_depth | integer | 5 | depth at which Russian roulette starts (1 to 2^31 - 1) | no |
| hide_emitters | boolean | false | hide directly visible emitters | no |
| texture_differentials | boolean | true | compute differentials (also needs a texture that uses them) | no |
| spp_scale | string or float | pbrt | footprint scale: `pbrt` = max(1/8, 1/√spp) (pbrt-v4), `none` = one pixel, or a positive number | no |
| footprint | string | sample | camera hits' texture footprint: `sample` (around each sample, as pbrt) or `pixel` (the pixel's own footprint, for textures that opt in; needs a `perspective` sensor and a `box` or `gaussian` film filter) | no |
| silhouette_spp | integer | 0 | `footprint="pixel"` (0 to 65536): this many more paths in each pixel whose centre and corner rays disagree about the surface they hit (silhouettes, the horizon), averaged with the sample's; with a `gaussian` film through offsets drawn from the filter (corners ±1.5 pixels), in scenes with a texture that filters the film's kernel (`pbrt_imagemap` `box`); primal renders only; no effect where pixel footprints do not apply | no |
| samples_per_pass | integer | (none) | accepted (1 or more) as Mitsuba's `path` accepts it, so that its scenes load, but without effect (with a warning): a render is one pass, as `prb`'s | no |
| timeout | float | (none) | accepted as Mitsuba's `path` accepts it, without effect (with a warning): no time limit, as `prb` | no |
| aovs | string | (none) | comma-separated extra outputs: `duv_dx`, `duv_dy` (the uv partials at the first hit, scaled by `spp_scale`, as a texture there reads them — also on a shape without a texture, e.g. a mirror: the partials of its own uv, not those a texture seen in it gets; 0 in a scene where no texture reads them or with `texture_differentials` false; 2 channels each) | no |

Where the differentials come from (:mod:`mitsuba_pbrt_tex.raydiff`): at camera hits the sensor's
ray differentials (one pixel) scaled by ``spp_scale``, intersected with the tangent plane (rays
that another integrator hands ``sample()`` — Mitsuba's ``moment``, ``aov`` — come as Mitsuba's
``SamplingIntegrator`` passes them, already scaled by 1/√spp, and get the rest of the scale); after
an ideal specular reflection or transmission, the ray differential propagated (dropped if an
offset exceeds 1e16); everywhere else pbrt-v4's camera approximation, on the shapes whose
textures read differentials. The partials are least-squares solved in the tangent frame, made
finite, clamped to ±1e8 and written to ``si.duv_dx``/``si.duv_dy``, so any texture — ours,
Mitsuba's, a user's Python texture — reads them. A scene in which no texture reads them
(:mod:`mitsuba_pbrt_tex.scene_needs`) computes nothing.

How it differs from ``prb`` (:meth:`Plugin.trace` follows ``prb.sample`` stage by stage and
imports its helpers, ``mis_weight`` and ``solid_angle_to_area_jacobian``, from the current
variant's ``mitsuba.python.ad.integrators.common``; with no texture that reads differentials it
renders and differentiates exactly as ``prb``, same random numbers):

* each hit gets ``si.duv_dx``/``si.duv_dy`` before ``si.bsdf()``; an emitter hit that emitter
  sampling also reaches is evaluated without them, as emitter sampling evaluates it (both MIS
  strategies then estimate the same radiance; :func:`_as_emitter_sampled`);
* the ray differential (:class:`~mitsuba_pbrt_tex.raydiff.RayDiff`) is loop state only in scenes
  with an ideal specular lobe; the previous hit is an ``Interaction3f`` (``prb``: a whole
  ``SurfaceInteraction3f``);
* the loop state is only what changes from bounce to bounce (read-only inputs excluded,
  optional state ``None`` where it would stay constant, the rays' time broadcast) and primal
  renders turn ``OptimizeLoops`` off, so Dr.Jit records the loop once (``prb``: twice);
* primal bounces ask each BSDF instance for the emitter sample's value and for a sampled
  direction in one ``dr.dispatch`` (:func:`bsdf_queries`, same random numbers), so that a
  texture both queries read computes its value at the hit once (``prb``, as Mitsuba's BSDFs'
  ``eval_pdf_sample``, evaluates it in each);
* optional AOVs with the first hit's uv partials;
* ``footprint="pixel"``: the render is one :class:`~mitsuba_pbrt_tex.render_scope.RenderScope`,
  published to the textures while the loop is traced (:mod:`mitsuba_pbrt_tex.pixel` computes
  the pixel's footprint from each camera hit); with a Gaussian film the camera samples are
  placed and counted by :mod:`mitsuba_pbrt_tex.film_view`; ``silhouette_spp`` adds paths in
  silhouette pixels (:mod:`mitsuba_pbrt_tex.silhouettes`);
* under ``dr.freeze`` the spp scale is a literal (the host → device copy of ``dr.opaque`` cannot
  be recorded; spp is part of the frozen function's key).

Samples per pixel: the footprint uses the spp of the ``mi.render`` call, or the total set with
``set_total_spp(n)`` (``python -m mitsuba_pbrt_tex render`` does this when it renders in passes).
"""

from __future__ import annotations

import contextlib
import math
from typing import NamedTuple

import drjit as dr
import mitsuba as mi

from mitsuba_pbrt_tex import film_view, pixel, raydiff, registry, silhouettes, variants
from mitsuba_pbrt_tex.params import Params, PluginError
from mitsuba_pbrt_tex.raydiff import RayDiff
from mitsuba_pbrt_tex.render_scope import (RenderScope, published, shared_lookups,
                                           silhouette_paths)
from mitsuba_pbrt_tex.scene_needs import SceneCache, SceneNeeds, TraceInputs

#: depths are UInt32 in the loop and int32 in Mitsuba's C++ (-1 means unbounded)
MAX_DEPTH = 2**31 - 1
#: Most extra paths per silhouette pixel (each is a whole path: 64 already reaches the noise
#: floor on the bench's far edges; the loop counts them in 32 bits).
MAX_SILHOUETTE_SPP = 65536


def bsdf_queries(bsdf, ctx, si, wo, active_em, sample1, sample2, active):
    """A primal bounce's two BSDF queries — value and density towards the emitter sample
    ``wo`` (lanes ``active_em``) and a sampled direction (lanes ``active``) — as one call per
    BSDF instance, inside which a texture both queries read at the hit computes its value once
    (:func:`~mitsuba_pbrt_tex.render_scope.shared_lookups`; Mitsuba's ``eval_pdf_sample``
    evaluates it twice). Returns (value, density, BSDFSample3f, weight)."""
    def both(instance, si, wo, active_em, sample1, sample2, active):
        with shared_lookups():
            value, pdf = instance.eval_pdf(ctx, si, wo, active_em)
            bs, weight = instance.sample(ctx, si, sample1, sample2, active)
        return value, pdf, bs, weight

    return dr.dispatch(bsdf, both, si, wo, active_em, sample1, sample2, active=active)


def _ray_ids(ray) -> tuple:
    """The JIT variables a ray is made of (what tells this integrator's rays from others')."""
    return tuple(dr.detail.collect_indices(ray))


def _as_emitter_sampled(si, sampled):
    """``si`` without its footprint in lanes ``sampled``: where emitter sampling also reaches
    the emitter a ray hit (its MIS weight is below 1), the emitter is evaluated as emitter
    sampling evaluates it — without differentials (Mitsuba's emitter samples carry none) — so
    that both strategies of the MIS sum estimate the same radiance. A filtered value on one
    side only is a bias: where the texels are dark, emitter sampling rarely goes, the BSDF
    sample's weight is near 1, and its filtered (brighter) value adds light that nothing takes
    away (+4–6% on a checker-textured area light, +26% with ``spp_scale="none"``). Camera rays
    and bounces off delta lobes, which emitter sampling cannot reach, keep the footprint."""
    out = mi.SurfaceInteraction3f(si)
    out.duv_dx = dr.select(sampled, 0, si.duv_dx)
    out.duv_dy = dr.select(sampled, 0, si.duv_dy)
    return out


def _prb_helpers():
    """Mitsuba's own AD-integrator helpers, the current variant's."""
    common = registry.ad_integrators_common()
    return common.mis_weight, common.solid_angle_to_area_jacobian


FOOTPRINTS = ('sample', 'pixel')
PIXEL_SENSORS = ('PerspectiveCamera',)
PIXEL_FILTERS = ('BoxFilter', 'GaussianFilter')
AOV_CHANNELS = {'duv_dx': ('duv_dx.u', 'duv_dx.v'), 'duv_dy': ('duv_dy.u', 'duv_dy.v')}


class PathResult(NamedTuple):
    """What :meth:`Plugin.trace` returns: Mitsuba's ``sample()`` result and, with a Gaussian
    film and pixel footprints, the pixel each camera hit decoded to (else None)."""
    L: object
    valid: object
    aovs: list
    state: object
    pixel: object = None
    pixel_ok: object = None


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
        Plugin._pass_options(p)

    def setup(self, props):
        variants.require_supported(self.NAME)
        p = Params(self.NAME, props)
        max_depth = p.int('max_depth', 6, lo=-1, hi=MAX_DEPTH)
        self.max_depth = 0xffffffff if max_depth == -1 else max_depth
        self.rr_depth = p.int('rr_depth', 5, lo=1, hi=MAX_DEPTH)
        self.hide_emitters = p.bool('hide_emitters', False)
        given = self._pass_options(p)
        if given:
            verb = 'have' if len(given) > 1 else 'has'
            mi.Log(mi.LogLevel.Warn, f'{self.NAME}: {" and ".join(given)} {verb} no effect: '
                   f'{self.NAME} renders all samples in one pass, with no time limit (as '
                   f'Mitsuba\'s prb does)')
        self.texture_differentials = p.bool('texture_differentials', True)
        self.spp_mode = self._spp_mode(p)
        self.footprint_mode = p.enum('footprint', 'sample', FOOTPRINTS)
        self.silhouette_spp = p.int('silhouette_spp', 0, lo=0, hi=MAX_SILHOUETTE_SPP)
        text = p.string('aovs', '') or ''
        self.aov_list = [a.strip() for a in text.split(',') if a.strip()]
        for a in self.aov_list:
            if a not in AOV_CHANNELS:
                raise p.error('aovs', f'unknown output "{a}"; accepted values: '
                                      f'{", ".join(AOV_CHANNELS)}')
            if self.aov_list.count(a) > 1:          # the film refuses repeated channel names
                raise p.error('aovs', f'output "{a}" is named twice; accepted values (each at '
                                      f'most once): {", ".join(AOV_CHANNELS)}')
        p.finish()
        self.total_spp = None
        self.cache = SceneCache()       # what the last scene and sensor need (scene_needs)
        self._handover = None           # sample_rays → sample(): see render_scope

    @staticmethod
    def _pass_options(p) -> list:
        """``samples_per_pass`` and ``timeout``, which Mitsuba's ``SamplingIntegrator`` reads
        (the ones given): accepted, so that a ``path`` scene loads with ``pbrt_path`` in its
        place, but without effect — a render is one pass with no time limit, as Mitsuba's
        ``prb`` renders (it ignores them silently; :meth:`setup` warns)."""
        given = [name for name in ('samples_per_pass', 'timeout') if p.has(name)]
        p.int('samples_per_pass', 1, lo=1, strict=True)
        p.float('timeout', -1.0)
        return given

    def _spp_mode(self, p):
        if not p.has('spp_scale'):
            return 'pbrt'
        kind = str(p.props.type('spp_scale')).split('.')[-1]
        if kind in ('Float', 'Integer'):
            return p.float('spp_scale', 1.0, lo=0.0, lo_open=True)
        if kind != 'String':                            # the enum's error names the type
            return p.enum('spp_scale', 'pbrt', ('pbrt', 'none'))
        text = p.string('spp_scale', 'pbrt')
        if text in ('pbrt', 'none'):
            return text
        try:                    # a number given as a string (a <default> in a <string>)
            value = float(text)
        except ValueError:
            value = math.nan
        if not value > 0:                               # (NaN too)
            raise p.error('spp_scale', f'unknown value "{text}"; accepted values: pbrt, none, '
                                       f'or a number > 0')
        p.check_range('spp_scale', value, lo=0.0, lo_open=True)     # as a <float> would be
        return value

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
    def scene_needs(self, scene) -> SceneNeeds:
        """What this scene needs computed (:class:`~mitsuba_pbrt_tex.scene_needs.SceneNeeds`;
        found once per scene; the textures that read differentials are prepared)."""
        if not self.texture_differentials:
            return SceneNeeds()
        return self.cache.needs(scene)

    def trace_inputs(self, scene, sampler, sensor, own_rays: bool = True) -> TraceInputs:
        """What one ``sample()`` hands its path loop, computed outside any symbolic loop.
        ``own_rays``: the camera rays are this integrator's (:meth:`sample_rays`), one pixel
        wide; else they are another integrator's, passed as Mitsuba's ``SamplingIntegrator``
        passes them (``moment``, ``aov``): already scaled by 1/√spp, so only the rest of the
        spp scale is applied."""
        needs = self.scene_needs(scene)
        spp = self.total_spp or sampler.sample_count()
        # opaque: the scale changes with spp, and a literal would recompile the kernel each time
        # (but a frozen function cannot record the host → device copy; spp is part of its key)
        scale = raydiff.spp_scale(spp, self.spp_mode)
        if not own_rays:
            scale *= math.sqrt(max(sampler.sample_count(), 1))
        scale = mi.Float(scale) if dr.flag(dr.JitFlag.FreezingScope) else dr.opaque(mi.Float, scale)
        camera = self.cache.camera(sensor) if needs.differentials else None
        return TraceInputs(needs, scale, camera)

    # ------------------------------------------------------------------ rendering
    @contextlib.contextmanager
    def _rendering(self, scene, sensor, seed):
        """:meth:`begin`'s view of the sensor for one of Mitsuba's ``render`` methods; after it
        a ``sample()`` from elsewhere gets foreign rays."""
        try:
            yield self.begin(scene, sensor, seed)
        finally:
            self._handover = None

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        """``ADIntegrator.render`` on :meth:`begin`'s view of the sensor."""
        with self._rendering(scene, sensor, seed) as view:
            return self._pbrt_base.render(self, scene, view, seed, spp, develop, evaluate)

    def render_forward(self, scene, params, sensor=0, seed=0, spp=0):
        """``RBIntegrator.render_forward`` on :meth:`begin`'s view of the sensor, with the
        texels' forward derivatives carried into their pyramids where Dr.Jit's traversal did
        not (``carry_forward_gradient``: ``dr.forward`` called after ``mi.render``)."""
        carried = [v for node in mi.traverse(scene).hierarchy.keys()
                   if hasattr(node, 'carry_forward_gradient')
                   for v in node.carry_forward_gradient()]
        try:
            with self._rendering(scene, sensor, seed) as view:
                return self._pbrt_base.render_forward(self, scene, params, view, seed, spp)
        finally:
            for v in carried:
                dr.clear_grad(v)

    def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
        """``RBIntegrator.render_backward`` on :meth:`begin`'s view of the sensor."""
        with self._rendering(scene, sensor, seed) as view:
            return self._pbrt_base.render_backward(self, scene, params, grad_in, view, seed, spp)

    def begin(self, scene, sensor, seed=0):
        """Where a render starts: its :class:`~mitsuba_pbrt_tex.render_scope.RenderScope`, and
        the sensor Mitsuba's ``render`` methods are given — the sensor itself, except with
        ``footprint="pixel"``, a Gaussian film filter and a texture that filters its kernel
        (``pbrt_imagemap`` ``box``): then the render's offsets
        (:class:`~mitsuba_pbrt_tex.film_view.FilterPixels`) and a view of the sensor that counts
        each sample in the pixel it decodes to (:class:`~mitsuba_pbrt_tex.film_view.PixelSensor`,
        carrying the scope). Without such a texture a Gaussian film renders as Mitsuba's, each
        sample splatted by the film: counting it in one pixel would cost noise for nothing."""
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        needs = self.scene_needs(scene)
        if self.footprint_mode != 'pixel' or not needs.differentials:
            return sensor
        self.pixel_sensor(sensor)       # the errors, in our words (only textures that read
        #                                 the footprint make the sensor and film matter)
        film = sensor.film()
        if film.rfilter().class_name() == 'BoxFilter' or not needs.film_kernel:
            return sensor
        return film_view.PixelSensor(RenderScope(sensor, film_view.FilterPixels(film, seed)))

    def sample_rays(self, scene, sensor, sampler):
        """The base class's camera rays (with a Gaussian film and pixel footprints, through the
        render's shared offsets: :meth:`~mitsuba_pbrt_tex.film_view.FilterPixels.rays`). Their
        positions complete the render's scope, which is handed over to :meth:`sample`
        (Mitsuba's ``render`` calls it next, without the sensor)."""
        scope = getattr(sensor, 'scope', None) or RenderScope(sensor)
        ray, weight, pos = self._pbrt_base.sample_rays(self, scene, scope.sensor, sampler)
        if scope.pixels is not None:
            ray, weight, pos = scope.pixels.rays(scope.sensor, ray, pos, sampler.sample_count())
        elif self.footprint_mode == 'pixel' and scope.sensor.class_name() in PIXEL_SENSORS and \
                scope.sensor.film().rfilter().class_name() == 'BoxFilter' and \
                self.scene_needs(scene).differentials:
            # (where no texture reads the footprint the rays stay prb's)
            ray = pixel.inset_camera_rays(scope.sensor, ray, pos)
        scope.positions = pos         # box filter: the sample's pixel; Gaussian: its centre
        scope.rays = _ray_ids(ray)
        self._handover = scope
        return ray, weight, pos

    def _foreign_rays(self, need: str, where: str) -> bool:
        """Camera rays that are not this integrator's render's (Mitsuba's ``aov``, ``moment``,
        a ``sample()`` called directly) where pixel footprints cannot apply: the textures keep
        the sample's footprint, with a warning (not silently). Returns False (no pixel
        footprints)."""
        mi.Log(mi.LogLevel.Warn, f'{self.NAME}: footprint="pixel" {need}; these come from '
               f'elsewhere (another integrator, such as Mitsuba\'s aov or moment, or sample() '
               f'called directly) {where}, so camera hits keep the sample\'s footprint')
        return False

    def pixel_sensor(self, sensor):
        """The sensor whose pixels textures centre on for ``footprint="pixel"`` (None for
        ``sample``); an error names what does not fit."""
        if self.footprint_mode != 'pixel':
            return None
        kind = sensor.class_name()
        if kind not in PIXEL_SENSORS:
            raise PluginError(f'{self.NAME}: parameter "footprint": value "pixel" needs a '
                              f'perspective sensor, got {kind}; with this sensor use "sample" '
                              f'(accepted values: {", ".join(FOOTPRINTS)})')
        rfilter = sensor.film().rfilter().class_name()
        if rfilter not in PIXEL_FILTERS:
            raise PluginError(f'{self.NAME}: parameter "footprint": value "pixel" needs the '
                              f'film filter "box" or "gaussian", got {rfilter}; with this '
                              f'filter use "sample" (accepted values: {", ".join(FOOTPRINTS)})')
        return sensor

    # ------------------------------------------------------------------ the path tracer
    def sample(self, mode, scene, sampler, ray, δL, state_in, active, **kwargs):
        """See ``ADIntegrator.sample()``: :meth:`trace`, with the render published to opting-in
        textures for ``footprint="pixel"``, and extra paths in silhouette pixels
        (``silhouette_spp``)."""
        # Primal renders record trace()'s loop once: its loop state holds nothing constant but
        # the rays' time (see trace()), so OptimizeLoops' second recording, which would remove
        # such state, costs more tracing than it saves. Differentiable renders keep it (its
        # literal propagation prunes derivative code).
        optimize = dr.flag(dr.JitFlag.OptimizeLoops) and mode != dr.ADMode.Primal
        with dr.scoped_set_flag(dr.JitFlag.OptimizeLoops, optimize):
            # the rays of this integrator's sample_rays, or another's (moment, aov, a user's)
            own = self._handover is not None and _ray_ids(ray) == self._handover.rays
            scope = self._handover if own else RenderScope(scene.sensors()[0])
            inputs = self.trace_inputs(scene, sampler, scope.sensor, own_rays=own)
            pixels = inputs.needs.differentials and self.pixel_sensor(scope.sensor) is not None
            gaussian = scope.sensor.film().rfilter().class_name() != 'BoxFilter'
            if pixels and gaussian and not inputs.needs.film_kernel:
                pixels = False          # (no texture filters the film's kernel: see begin())
            elif pixels and not own and len(scene.sensors()) > 1:
                # rays from elsewhere, and no telling which sensor's: said, not guessed
                pixels = self._foreign_rays('needs to know the sensor of the camera rays', 'in '
                                            f'a scene of {len(scene.sensors())} sensors')
            elif pixels and scope.pixels is None and gaussian:
                # a Gaussian film, but the rays are not ours (sample() called without render())
                pixels = self._foreign_rays(f'with a gaussian film needs the camera rays of '
                                            f'{self.NAME}\'s own render()',
                                            '(a box film keeps pixel footprints there)')
            if not pixels:
                return self.trace(mode, scene, sampler, ray, δL, state_in, active, inputs,
                                  RenderScope(scope.sensor))[:4]
            extra = self.silhouette_spp
            if extra and mode != dr.ADMode.Primal:
                raise PluginError(f'{self.NAME}: parameter "silhouette_spp": value {extra} is for '
                                  f'primal renders; differentiable renders need 0')
            with published(scope):
                out = self.trace(mode, scene, sampler, ray, δL, state_in, active, inputs, scope)
                if scope.pixels is not None:
                    scope.count_at_decoded(out.pixel, out.pixel_ok)
                if extra:
                    out = self._with_silhouette_paths(scene, sampler, out, scope, inputs,
                                                      mi.Bool(active))
                return out[:4]

    def _with_silhouette_paths(self, scene, sampler, out, scope, inputs, active):
        """``out`` with ``silhouette_spp`` more paths averaged in, in the pixels that cross a
        silhouette (:mod:`mitsuba_pbrt_tex.silhouettes`). Box film: through points of the
        pixel (a randomly shifted (0, 2)-sequence), whose textures centre on it; Gaussian film: through film offsets drawn from
        the filter, each a point estimate of the pixel's filtered value (their hits are not at
        the render's shared offsets, so their textures keep the sample's footprint). What these
        paths estimate is mostly coverage: box-filtered image textures read EWA over the same
        footprint in them (:func:`~mitsuba_pbrt_tex.render_scope.silhouette_paths`)."""
        gaussian = scope.pixels is not None
        plain = RenderScope(scope.sensor)

        def trace(sub, ray, edge):
            with silhouette_paths():
                if not gaussian:
                    return self.trace(dr.ADMode.Primal, scene, sub, ray, None, None, edge,
                                      inputs, scope).L
                with published(None):
                    return self.trace(dr.ADMode.Primal, scene, sub, ray, None, None, edge,
                                      inputs, plain).L

        probes = silhouettes.FILTER_PROBES if gaussian else silhouettes.PROBES
        edge = silhouettes.edge_pixels(scene, scope.sensor, scope.positions, active, probes)
        acc = silhouettes.extra_paths(trace, scope.sensor, sampler, scope.positions, edge,
                                      self.silhouette_spp,
                                      scope.pixels.filter_offset if gaussian else None)
        L = dr.select(edge, (out.L + acc) * (1.0 / (self.silhouette_spp + 1)), out.L)
        return out._replace(L=L, state=L)

    @dr.syntax
    def trace(self, mode, scene, sampler, ray, δL, state_in, active, inputs: TraceInputs,
              scope: RenderScope, **kwargs) -> PathResult:
        """The path tracer. The stages are those of Mitsuba 3.9's ``prb`` (same helpers, same
        order of random numbers), plus the stages marked "differentials". With a Gaussian film
        and pixel footprints (``scope.pixels``) the pixel of each camera hit is decoded as the
        textures decode it, and returned."""
        mis_weight, solid_angle_to_area_jacobian = _prb_helpers()
        primal = mode == dr.ADMode.Primal
        bsdf_ctx = mi.BSDFContext()
        want, scale, camera = inputs.needs.differentials, inputs.scale, inputs.camera
        specular_scene, reader_shapes = inputs.needs.specular, inputs.needs.reader_shapes
        sensor, pixels = scope.sensor, scope.pixels

        # ---- differentials: the camera ray's, scaled for the sample count --------------------
        # every sensor's rays are RayDifferential3f; batch ones hold differentials without
        # has_differentials, so each lane's own decide (RayDiff.of_camera_ray)
        if dr.hint(want and isinstance(ray, mi.RayDifferential3f), mode='scalar'):
            camera_diff = RayDiff.of_camera_ray(ray, scale)
        else:
            camera_diff = RayDiff()

        # ---- loop state (as prb) -------------------------------------------------------------
        # Only what changes from bounce to bounce is loop state: the loop's inputs that it only
        # reads are excluded below, and the optional state is None where it would stay constant
        # (the ray differential where no specular lobe propagates it, the AOVs, the Gaussian
        # film's pixel, δL in primal renders). Dr.Jit re-records a loop to remove constant state
        # (always when it is narrower than the loop, under OptimizeLoops otherwise); with none
        # left but the time below, and OptimizeLoops off in primal renders (sample()), the body
        # is traced once — tracing, in Python at every render, is a large part of its cost.
        diff = camera_diff if want and specular_scene else None
        # the hits' shading-normal derivatives (RayFlags.All leaves them out, as 0) curve the
        # differentials propagated through specular lobes: asked only where they are read
        hit_flags = mi.RayFlags.All | mi.RayFlags.dNSdUV if diff is not None else \
            mi.RayFlags.All
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
                               specular_scene, reader_shapes, pixels, camera_diff,
                               hit_flags]):
            active_next = mi.Bool(active)

            # ---- the hit, with derivative tracking in the differential phases --------------
            with dr.resume_grad(when=not primal):
                si = pi.compute_surface_interaction(ray, ray_flags=hit_flags)
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
            em_pdf = scene.pdf_emitter_direction(si_prev, ds, ~bsdf_delta_prev)
            mis = mis_weight(bsdf_pdf_prev, em_pdf)
            with dr.resume_grad(when=not primal):
                Le = β * mis * ds.emitter.eval(_as_emitter_sampled(si, em_pdf > 0), active_next)

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
                if dr.hint(primal, mode='scalar'):
                    # with the BSDF sample (same random numbers): the textures look up once
                    bsdf_value_em, bsdf_pdf_em, bsdf_sample, bsdf_weight = bsdf_queries(
                        bsdf, bsdf_ctx, si, wo, active_em, sampler.next_1d(),
                        sampler.next_2d(), active_next)
                else:
                    bsdf_value_em, bsdf_pdf_em = bsdf.eval_pdf(bsdf_ctx, si, wo, active_em)
                mis_em = dr.select(ds.delta, 1, mis_weight(ds.pdf, bsdf_pdf_em))
                Lr_dir = β * mis_em * bsdf_value_em * em_weight

            # ---- BSDF sampling (detached) --------------------------------------------------
            if dr.hint(not primal, mode='scalar'):
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
        return PathResult(L if primal else δL, depth != 0, aovs, L, decoded, decoded_ok)


def _interaction(si):
    """What the next bounce reads of a hit (the reference point of its emitter MIS weight):
    an ``Interaction3f`` — fewer loop variables to trace than a whole SurfaceInteraction."""
    return mi.Interaction3f(si.t, si.time, si.wavelengths, si.p, si.n)
