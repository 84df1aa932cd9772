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
| aovs | string | (none) | comma-separated extra outputs: `duv_dx`, `duv_dy` (uv partials at the first hit; 2 channels each) | no |

Where the differentials come from:

* camera hits: the sensor's ray differentials (one pixel), scaled by ``spp_scale``, intersected
  with the tangent plane;
* after an ideal specular reflection or transmission (a delta lobe): the ray differential is
  propagated (pbrt-v4's formulas with shading-normal derivatives; the transmission formula is
  corrected, see :mod:`mitsuba_pbrt_tex.raydiff`) and dropped if an offset exceeds 1e16;
* everywhere else (after diffuse/glossy bounces, or when a propagated differential is lost):
  pbrt-v4's camera approximation — the footprint a camera ray would have at that point.

The partials are least-squares solved in the tangent frame, made finite and clamped to ±1e8, and
written to ``si.duv_dx``/``si.duv_dy``, so any texture — ours, Mitsuba's, or a Python texture of
the user's — reads them. Before rendering, the integrator asks the scene's textures whether any
uses differentials (``prepare_differentials()``; Mitsuba's C++ textures never do, a user's Python
texture is assumed to); if none does, nothing is computed and the cost is that of a plain path
tracer.

Samples per pixel: the footprint uses the spp of the ``mi.render`` call, or the total set with
``set_total_spp(n)`` (``python -m mitsuba_pbrt_tex render`` does this when it renders in passes).
"""

import drjit as dr
import mitsuba as mi

from mitsuba_pbrt_tex import raydiff, variants
from mitsuba_pbrt_tex.params import Params
from mitsuba_pbrt_tex.texture import uses_differentials

#: depths are UInt32 in the loop and int32 in Mitsuba's C++ (-1 means unbounded)
MAX_DEPTH = 2**31 - 1

AOV_CHANNELS = {'duv_dx': ('duv_dx.u', 'duv_dx.v'), 'duv_dy': ('duv_dy.u', 'duv_dy.v')}


def _mis_weight(pdf_a, pdf_b):
    """Power heuristic (β = 2), 0 where both pdfs vanish (as Mitsuba's ``mis_weight``)."""
    a2 = pdf_a * pdf_a
    w = a2 / (a2 + pdf_b * pdf_b)
    return dr.select(dr.isfinite(w), w, 0)


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
                f'{self.texture_differentials}, spp_scale={self.spp_mode}, aovs={self.aov_list}]')

    def set_total_spp(self, spp):
        """Use ``spp`` (not the spp of each ``mi.render`` call) for the footprint scale."""
        self.total_spp = None if spp is None else int(spp)

    # ------------------------------------------------------------------ what the scene needs
    def needs_differentials(self, scene) -> bool:
        """Does any texture of the scene use differentials? (Also prepares them.)

        Asked at every render, not cached: Mitsuba objects admit no weak references, an id()
        may be reused by the next scene, and the traversal takes ~0.2 ms."""
        if not self.texture_differentials:
            return False
        nodes = mi.traverse(scene).hierarchy.keys()
        textures = [n for n in nodes if isinstance(n, mi.Texture)]
        return any([uses_differentials(t) for t in textures])      # prepares every one

    def footprint(self, sensor) -> raydiff.CameraFootprint:
        """The camera approximation's minimum differentials, found anew at every render (the
        camera may have moved; 512 rays)."""
        with dr.suspend_grad():
            return raydiff.CameraFootprint(sensor)

    def sample_rays(self, scene, sensor, sampler):
        """The base class's camera rays; remembers the sensor for the camera approximation."""
        self._sensor = sensor
        return self._pbrt_base.sample_rays(self, scene, sensor, sampler)

    # ------------------------------------------------------------------ the path tracer
    @dr.syntax
    def sample(self, mode, scene, sampler, ray, δL, state_in, active, **kwargs):
        """See ``ADIntegrator.sample()``; stages below follow Mitsuba's ``prb``, plus the
        differentials (marked "differentials")."""
        primal = mode == dr.ADMode.Primal
        bsdf_ctx = mi.BSDFContext()
        want = self.needs_differentials(scene)

        # ---- differentials: the camera ray's offsets, scaled for the sample count --------------
        sensor = getattr(self, '_sensor', None) or scene.sensors()[0]
        spp = self.total_spp or sampler.sample_count()
        # opaque: the scale changes with spp, and a literal would recompile the kernel each time
        scale = dr.opaque(mi.Float, raydiff.spp_scale(spp, self.spp_mode))
        has_diff_in = bool(getattr(ray, 'has_differentials', False)) and want
        if dr.hint(has_diff_in, mode='scalar'):
            o, d = mi.Point3f(dr.detach(ray.o)), mi.Vector3f(dr.detach(ray.d))
            o_x = dr.fma(mi.Point3f(dr.detach(ray.o_x)) - o, scale, o)
            o_y = dr.fma(mi.Point3f(dr.detach(ray.o_y)) - o, scale, o)
            d_x = dr.fma(mi.Vector3f(dr.detach(ray.d_x)) - d, scale, d)
            d_y = dr.fma(mi.Vector3f(dr.detach(ray.d_y)) - d, scale, d)
            has_diff = mi.Bool(True)
        else:
            o_x, o_y = mi.Point3f(0), mi.Point3f(0)
            d_x, d_y = mi.Vector3f(0), mi.Vector3f(0)
            has_diff = mi.Bool(False)
        camera = self.footprint(sensor) if want else None
        first_duv_dx, first_duv_dy = mi.Vector2f(0), mi.Vector2f(0)

        # ---- loop state (as prb) -------------------------------------------------------------
        ray = mi.Ray3f(dr.detach(ray))
        depth = mi.UInt32(0)
        L = mi.Spectrum(0 if primal else state_in)
        δL = mi.Spectrum(δL if δL is not None else 0)
        β = mi.Spectrum(1)
        η = mi.Float(1)
        active = mi.Bool(active)
        pi = scene.ray_intersect_preliminary(ray, coherent=True, reorder=False, active=active)
        ray_prev = mi.Ray3f(ray)
        pi_prev = dr.zeros(mi.PreliminaryIntersection3f)
        si_prev = dr.zeros(mi.SurfaceInteraction3f)
        bsdf_pdf_prev = mi.Float(1.0)
        bsdf_delta_prev = mi.Bool(True)

        if dr.hint(self.hide_emitters, mode='scalar'):
            skip = pi.is_valid() & (pi.shape.emitter() != None) & active  # noqa: E711
            si_skip = pi.compute_surface_interaction(ray, mi.RayFlags.Minimal, skip)
            pi_after = self.skip_area_emitters(scene, si_skip.spawn_ray(ray.d), True, skip)
            pi[skip] = pi_after

        while dr.hint(active, max_iterations=self.max_depth, label=f'pbrt_path ({mode.name})'):
            active_next = mi.Bool(active)

            # ---- the hit, with derivative tracking in the differential phases --------------
            with dr.resume_grad(when=not primal):
                si = pi.compute_surface_interaction(ray, ray_flags=mi.RayFlags.All)
                if (not primal) & mi.Bool(depth >= 1):
                    si_prev_diff = pi_prev.compute_surface_interaction(
                        ray_prev, ray_flags=mi.RayFlags.Minimal)
                    si_prev = dr.replace_grad(si_prev, si_prev_diff)
                    si_detached = dr.detach(si)
                    wi_global = dr.normalize(si_prev.p - si_detached.p)
                    si.wi = dr.replace_grad(si.wi, si_detached.to_local(wi_global))

            # ---- differentials: footprint of this hit → si.duv_dx, si.duv_dy ---------------
            dpdx, dpdy = mi.Vector3f(0), mi.Vector3f(0)
            if dr.hint(want, mode='scalar'):
                valid = si.is_valid()
                p_hit, n_hit = dr.detach(si.p), dr.detach(si.n)
                dpdx, dpdy, ok = raydiff.tangent_plane_offsets(p_hit, n_hit, o_x, d_x, o_y, d_y,
                                                               valid & has_diff)
                ax, ay = camera.dp_dxy(p_hit, n_hit, scale, valid & ~ok)
                dpdx = dr.select(ok, dpdx, ax)
                dpdy = dr.select(ok, dpdy, ay)
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
            mis = _mis_weight(bsdf_pdf_prev,
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
                    em_val = scene.eval_emitter_direction(si, ds, active_em)
                    inv_pdf = dr.select(ds.pdf != 0, dr.rcp(ds.pdf), 0)
                    em_weight = dr.replace_grad(em_weight, em_val * dr.detach(inv_pdf))
                wo = si.to_local(ds.d)
                bsdf_value_em, bsdf_pdf_em = bsdf.eval_pdf(bsdf_ctx, si, wo, active_em)
                mis_em = dr.select(ds.delta, 1, _mis_weight(ds.pdf, bsdf_pdf_em))
                Lr_dir = β * mis_em * bsdf_value_em * em_weight

            # ---- BSDF sampling (detached) --------------------------------------------------
            bsdf_sample, bsdf_weight = bsdf.sample(bsdf_ctx, si, sampler.next_1d(),
                                                   sampler.next_2d(), active_next)
            L = (L + Le + Lr_dir) if primal else (L - Le - Lr_dir)
            wo_world = si.to_world(bsdf_sample.wo)
            ray_next = si.spawn_ray(wo_world)

            # ---- differentials: propagate through ideal specular lobes ---------------------
            if dr.hint(want, mode='scalar'):
                o_x, d_x, o_y, d_y, has_diff = self._propagate(
                    si, bsdf_sample, ray, ray_next, wo_world, dpdx, dpdy, o_x, d_x, o_y, d_y,
                    has_diff)

            η *= bsdf_sample.eta
            β *= bsdf_weight
            si_prev = dr.detach(si, True)
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
                    wo_diff = dr.normalize(si_next.p - si.p)
                    wo_w = dr.replace_grad(ray_next.d,
                                           dr.select(si_next.is_valid(), wo_diff, ray_next.d))
                    bsdf_val = bsdf.eval(bsdf_ctx, si, si.to_local(wo_w), active_next)
                    Lr_ind = L * dr.relative_grad(bsdf_val)
                    Lo = Le + Lr_dir + Lr_ind
                    if dr.hint(mode == dr.ADMode.Backward, mode='scalar'):
                        dr.backward_from(δL * Lo,
                                         flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
                    else:
                        δL += dr.forward_to(Lo, flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)

            depth[si.is_valid()] += 1
            active = active_next
            pi_prev = pi
            pi = pi_next
            ray_prev = ray
            ray = ray_next

        aovs = []
        for a in self.aov_list:
            v = first_duv_dx if a == 'duv_dx' else first_duv_dy
            aovs += [v.x, v.y]
        return (L if primal else δL, depth != 0, aovs, L)

    def _propagate(self, si, bs, ray, ray_next, wo_world, dpdx, dpdy, o_x, d_x, o_y, d_y,
                   has_diff):
        """New ray differential after the sampled lobe (pbrt-v4 ``SpawnRay``), or none.

        The offset rays start at the *spawned* origin of the main ray plus the footprint offsets:
        Mitsuba offsets spawned origins along the normal by ~1e-4·|p|, and starting the offset
        rays from the un-offset hit (as pbrt does) would add that displacement to the next
        footprint (a 0.2% error in the mirror test)."""
        reflect = mi.has_flag(bs.sampled_type, mi.BSDFFlags.DeltaReflection)
        transmit = mi.has_flag(bs.sampled_type, mi.BSDFFlags.DeltaTransmission)
        specular = (reflect | transmit) & si.is_valid()
        si_d = dr.detach(si)
        wo = -mi.Vector3f(dr.detach(ray.d))                 # pbrt's wo: towards the origin
        wi = dr.detach(wo_world)
        n = mi.Vector3f(si_d.sh_frame.n)
        duv_dx, duv_dy = si_d.duv_dx, si_d.duv_dy
        dndx = si_d.dn_du * duv_dx.x + si_d.dn_dv * duv_dx.y
        dndy = si_d.dn_du * duv_dy.x + si_d.dn_dv * duv_dy.y
        dwodx = -d_x - wo
        dwody = -d_y - wo
        flip = dr.dot(wo, n) < 0
        n_t = dr.select(flip, -n, n)
        dndx_t, dndy_t = dr.select(flip, -dndx, dndx), dr.select(flip, -dndy, dndy)
        eta = dr.detach(bs.eta)
        rx = dr.select(reflect, raydiff.reflect_differential(wo, wi, n, dndx, dwodx),
                       raydiff.refract_differential(wo, wi, n_t, dndx_t, dwodx, eta))
        ry = dr.select(reflect, raydiff.reflect_differential(wo, wi, n, dndy, dwody),
                       raydiff.refract_differential(wo, wi, n_t, dndy_t, dwody, eta))
        base = mi.Point3f(dr.detach(ray_next.o))
        new_o_x = base + dpdx
        new_o_y = base + dpdy
        squash = ((dr.squared_norm(rx) > raydiff.SQUASH_LIMIT)
                  | (dr.squared_norm(ry) > raydiff.SQUASH_LIMIT)
                  | (dr.squared_norm(new_o_x) > raydiff.SQUASH_LIMIT)
                  | (dr.squared_norm(new_o_y) > raydiff.SQUASH_LIMIT)
                  | ~dr.all(dr.isfinite(rx)) | ~dr.all(dr.isfinite(ry)))
        # Without an incoming differential there is none to propagate (pbrt-v4): the next hit
        # uses the camera approximation.
        keep = specular & has_diff & ~squash
        return (dr.select(keep, new_o_x, o_x), dr.select(keep, rx, d_x),
                dr.select(keep, new_o_y, o_y), dr.select(keep, ry, d_y), keep)
