"""The ``invrgbl`` integrator: physically based camera rendering of Gaussians + meshes."""

from __future__ import annotations

import numpy as np
import drjit as dr
import mitsuba as mi

from ..physics import brdf, coat, hits as hitlib, specular_albedo
from ..physics.lighting import (MAX_BOUNCES, GaussianLighting, GaussianTable, LightingCache,
                                fibonacci_direction, geometry_key, hash_rotation_of, moving_shadows,
                                point_lights, transmittance)

_variant = mi.variant()

AOV_NAMES = ["albedo.R", "albedo.G", "albedo.B", "normal.X", "normal.Y", "normal.Z",
             "roughness", "lidar_albedo", "depth", "alpha"]


class InvRGBLIntegrator(hitlib.ad_integrator_base()):
    r"""
    .. _integrator-invrgbl:

    InvRGB+L camera integrator (:monosp:`invrgbl`)
    ----------------------------------------------

    .. pluginparameters::

     * - samples
       - |int|
       - M, sky directions per Gaussian (cosine-weighted Fibonacci spiral around
         its normal). The paper trains with 16 and renders with 128. (Default: 64)
     * - bounces
       - |int|
       - Diffuse bounces of light between Gaussians: a sky direction another
         Gaussian blocks brings the light that Gaussian reflects diffusely,
         to the diffuse term and to the specular lobe (see
         :mod:`mi_invrgbl.physics.lighting`). 0: direct sky and sun light
         only, as in the paper. (Default: 0)
     * - max_hits
       - |int|
       - Most Gaussians blended per camera ray. (Default: 64)
     * - min_transmittance
       - |float|
       - A ray stops once its transmittance falls below this. (Default: 1e-3)
     * - sun_visibility
       - |string|
       - ``trace``: trace each Gaussian's shadow ray to the sun (shadows follow
         a moved sun); ``attribute``: use the per-Gaussian ``sun_visibility``
         field (the fitted value). (Default: ``trace``)
     * - moving
       - |string|
       - Ids of the shapes that move between frames (space-separated), used
         with ``sun_visibility = attribute``: the learned field holds the
         shadows of the static scene, and each render multiplies it by the
         sun's transmittance through these shapes where they stand now, so
         their shadows move with them
         (:func:`~mi_invrgbl.physics.lighting.moving_shadows`). Ignored
         with ``trace``, which traces through every shape. (Default: none)
     * - f0
       - |float|
       - Fresnel reflectance at normal incidence of the Gaussians. (Default: 0.04)
     * - shadowing
       - |string|
       - Shadowing-masking term of the Gaussians' specular lobe: ``vcavity``
         (the paper's Cook-Torrance V-cavity) or ``smith`` (Smith's GGX term,
         as Mitsuba's microfacet BSDFs; it reflects about half as much near
         grazing, see :mod:`mi_invrgbl.physics.brdf`). (Default: ``vcavity``)
     * - diffuse_fresnel
       - |bool|
       - The diffuse light passes a rough dielectric coat (reflectance
         ``f0``, GGX alpha = the Gaussian's roughness) on the way in and out:
         the Lambertian term is weighted by the coat's transmittance at the
         light's and at the viewer's angle and by the light that bounces
         under it, as Mitsuba's ``roughplastic`` weights its diffuse lobe
         (:mod:`mi_invrgbl.physics.coat`). false: the paper's plain
         Lambertian term. (Default: false)
     * - hide_emitters
       - |bool|
       - Show the background as black instead of the sky. (Default: false)

    Gaussians (``gaussians`` or any ``ellipsoids`` shape) are alpha-blended
    front to back along each camera ray, in the order of their response
    peaks along the ray (not of where the ray enters them). Each Gaussian's colour is the
    paper's physically based shading with its normal, RGB albedo and
    roughness (``cooktorrance``'s BRDF):

    .. math::

        c(w_o) = \sum_{lights} v_l\, f_r(w_l, w_o)\, E_l \cos\theta_l
               + \frac{\pi}{M} \sum_{i=1}^{M} v(w_i)\, f_r(w_i, w_o)\, L_{sky}(w_i)
               + \rho\, E_{bounce} / \pi

    with visibilities ``v`` traced from the Gaussian's centre through the
    other Gaussians and the meshes. Where the paper is loose, this is
    stricter: the sun term includes the BRDF (the paper multiplies the sun's
    irradiance by ``n . w_sun`` alone), the sky estimator is an unbiased
    cosine-weighted quadrature (``pi / M`` weight), and every point or spot
    light of the scene lights the Gaussians with its ``1/d^2`` falloff.

    The visibilities are traced once and cached while the geometry and the
    lights stay put. The ``w_i`` are cosine-weighted about each Gaussian's
    normal, so a render after normals were edited (``mi.traverse``)
    re-traces the sky directions of the Gaussians whose normal changed
    (:func:`~mi_invrgbl.physics.lighting.retrace_turned`) and renders as a
    fresh load of the edited scene would. Moving a node or a mesh (a frame's
    objects placed, an inserted car on its track) re-traces the moved
    Gaussians' sky directions and the others' that meet the moved shape's
    bounds, before or after the move
    (:func:`~mi_invrgbl.physics.lighting.retrace_moved`); where the moved
    nodes hold more than half of the Gaussians, the whole sky.

    A mesh behind the Gaussians (or alone) is shaded with its own BSDF (any
    Mitsuba BSDF) by direct lighting: one emitter sample and one BSDF sample
    per camera sample, combined by multiple importance sampling; shadow rays
    see the Gaussians' transmittance.

    AOVs, in this order: ``albedo`` (RGB), ``normal`` (world), ``roughness``,
    ``lidar_albedo``, ``depth`` (distance along the ray), ``alpha``
    (accumulated opacity). Material AOVs are alpha-blended like the colour,
    i.e. not divided by ``alpha``.

    .. code-block:: xml

        <integrator type="invrgbl">
            <integer name="samples" value="16"/>
        </integrator>
    """

    def __init__(self, props):
        super().__init__(props)
        self.samples = int(props.get("samples", 64))
        self.bounces = int(props.get("bounces", 0))
        self.max_hits = int(props.get("max_hits", 64))
        self.min_transmittance = float(props.get("min_transmittance", 1e-3))
        self.sun_visibility = str(props.get("sun_visibility", "trace"))
        self.f0 = float(props.get("f0", brdf.F0_DEFAULT))
        self.diffuse_fresnel = bool(props.get("diffuse_fresnel", False))
        self.hide_emitters = bool(props.get("hide_emitters", False))
        self.shadowing = str(props.get("shadowing", "vcavity"))
        if self.shadowing not in brdf.SHADOWING:
            raise ValueError("invrgbl: shadowing must be one of %s (got %r)"
                             % (", ".join(brdf.SHADOWING), self.shadowing))
        if self.samples < 1:
            raise ValueError("invrgbl: samples must be >= 1")
        if self.max_hits < 1:
            raise ValueError("invrgbl: max_hits must be >= 1")
        if not 0 <= self.bounces <= MAX_BOUNCES:
            raise ValueError("invrgbl: bounces must be in 0..%d (got %d)" % (MAX_BOUNCES, self.bounces))
        if self.sun_visibility not in ("trace", "attribute"):
            raise ValueError("invrgbl: sun_visibility must be 'trace' or 'attribute'")
        self.moving = str(props.get("moving", "")).replace(",", " ").split()
        self.cache = LightingCache()

    def moving_transmittance(self, scene, nodes):
        """Per light, the moving shapes' shadow factor on the learned sun
        visibility (``None`` where there is none): traced when the geometry
        or a sun has moved since the last render."""
        if self.sun_visibility != "attribute" or not self.moving:
            return None
        by_name = {s.id(): s for s in scene.shapes()}
        missing = [m for m in self.moving if m not in by_name or not by_name[m].is_ellipsoids()]
        if missing:
            raise ValueError("invrgbl: moving names no Gaussian shape of the scene: %s"
                             % ", ".join(missing))
        ids = {hitlib.shape_id(by_name[m]) for m in self.moving}
        lights = point_lights(scene)
        suns = [tuple(np.array(dr.detach(e.sun_direction_world())).ravel().round(7))
                if kind == "sun" else None for kind, e in lights]
        key = (geometry_key(nodes), tuple(suns))
        cache = self.cache
        if cache.moving_key != key:
            with dr.suspend_grad():
                table = GaussianTable.build(nodes).load_geometry()
                cache.moving_visibility = [None if d is None else moving_shadows(nodes, table, d, ids)
                                           for d in suns]
            cache.moving_key = key
        return cache.moving_visibility

    def settings(self):
        """Every parameter of this integrator as a ``mi.load_dict``
        dictionary: a copy with some replaced (eval's relighting traces the
        sun's shadows of a fit that learned them) keeps the rest, the coat
        and the shadowing term included."""
        return {"type": "invrgbl", "samples": self.samples, "bounces": self.bounces,
                "max_hits": self.max_hits, "min_transmittance": self.min_transmittance,
                "sun_visibility": self.sun_visibility, "f0": self.f0,
                "diffuse_fresnel": self.diffuse_fresnel, "hide_emitters": self.hide_emitters,
                "shadowing": self.shadowing, "moving": " ".join(self.moving)}

    def aov_names(self):
        return list(AOV_NAMES)

    # ------------------------------------------------------------ Gaussians
    def shade_gaussian_hits(self, lighting, nodes, rays, hit_list, g):
        """Per-hit colour and materials (flat arrays, differentiable)."""
        active = g.active
        ids, prims = g.node_ids, g.prims
        albedo = mi.Color3f(hitlib.gather_attribute(nodes, "albedo", ids, prims, active))
        tau = hitlib.gather_attribute(nodes, "roughness", ids, prims, active)
        rho_l = hitlib.gather_attribute(nodes, "lidar_albedo", ids, prims, active)
        gidx = lighting.table.global_index(ids, prims)
        n = dr.gather(mi.Vector3f, lighting.table.normal, gidx, active)
        _, d = hitlib.expand_rays(rays, hit_list)
        wo_world = -d
        frame = mi.Frame3f(n)
        wo = frame.to_local(wo_world)

        # Diffuse: albedo * E / pi (sky, lights and bounce; per Gaussian).
        irradiance_pi = dr.gather(mi.Color3f, lighting.diffuse, gidx, active)
        specular = mi.Color3f(0.0)
        for d_l, e_l in zip(lighting.light_dir, lighting.light_irr):
            wl = frame.to_local(dr.gather(mi.Vector3f, d_l, gidx, active))
            e = dr.gather(mi.Color3f, e_l, gidx, active)
            cos_l = dr.maximum(mi.Frame3f.cos_theta(wl), 0.0)
            specular += e * cos_l * brdf.specular(wl, wo, tau, self.f0, self.shadowing)
        # Specular sky: the lobe's albedo times the lobe-weighted mean of the
        # Gaussian's M sky samples (specular_albedo.sky_specular; a plain
        # pi/M sum misses a glossy lobe between the samples). The sample
        # directions are a fixed spiral in each Gaussian's normal frame
        # (lighting.sky_dirs = frame.to_world(spiral)); recomputing the local
        # direction is exact and saves a differentiable gather per sample.
        M = lighting.samples
        if M:
            rot = hash_rotation_of(gidx, lighting.pattern)
            specular += specular_albedo.sky_specular(
                lambda i: fibonacci_direction(mi.Float(i), M, rot),
                lambda i: dr.gather(mi.Color3f, lighting.reflected_radiance, gidx * M + i, active),
                wo, tau, M, self.f0, self.shadowing)
        if lighting.diffuse_fresnel:
            # Diffuse light leaves through the coat too (the way in is in
            # the lighting's diffuse term); the transmission is two-sided,
            # as the diffuse term is lit whichever side the viewer is on.
            irradiance_pi = irradiance_pi * coat.way_out(mi.Frame3f.cos_theta(wo), tau,
                                                         lighting.f0)
        colour = albedo * irradiance_pi + specular
        colour = dr.select(active & dr.all(dr.isfinite(colour)), colour, 0.0)
        return colour, albedo, n, tau, rho_l

    # --------------------------------------------------------------- meshes
    def shade_surface(self, scene, sampler, si, nodes, active):
        """Direct lighting at mesh hits: emitter + BSDF sample with MIS."""
        bsdf = si.bsdf()
        ctx = mi.BSDFContext()
        result = mi.Color3f(0.0)
        # Emitted radiance of area lights seen directly.
        result += mi.Color3f(si.emitter(scene).eval(si, active))

        # Emitter sampling.
        ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(), False, active)
        em_active = active & (ds.pdf != 0)
        wo = si.to_local(ds.d)
        f_em, pdf_bsdf = bsdf.eval_pdf(ctx, si, wo, em_active)
        vis = transmittance(scene, si.spawn_ray(ds.d).o, ds.d,
                            dr.select(dr.isfinite(ds.dist), ds.dist * (1 - 1e-4), dr.inf), nodes)
        mis = dr.select(ds.delta, 1.0, ds.pdf / dr.maximum(ds.pdf + pdf_bsdf, 1e-20))
        result += dr.select(em_active, mi.Color3f(f_em) * mi.Color3f(em_weight) * vis * mis, 0.0)

        # BSDF sampling towards the environment and area lights.
        bs, bsdf_weight = bsdf.sample(ctx, si, sampler.next_1d(), sampler.next_2d(), active)
        bs_active = active & (bs.pdf > 0)
        ray = si.spawn_ray(si.to_world(bs.wo))
        si2 = scene.ray_intersect(ray, bs_active)
        emitter = si2.emitter(scene, bs_active)
        hit_light = bs_active & (emitter != None)  # noqa: E711  (Dr.Jit pointer test)
        ds2 = mi.DirectionSample3f(scene, si2, si)
        pdf_em = scene.pdf_emitter_direction(si, ds2, hit_light & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta))
        mis2 = dr.select(mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta), 1.0,
                         bs.pdf / dr.maximum(bs.pdf + pdf_em, 1e-20))
        # Gaussians in front of the light dim it; meshes already stopped si2.
        vis2 = transmittance(scene, ray.o, ray.d, dr.select(si2.is_valid(), si2.t, dr.inf), nodes)
        result += dr.select(hit_light, mi.Color3f(bsdf_weight) * mi.Color3f(emitter.eval(si2, hit_light))
                            * mis2 * vis2, 0.0)
        return result

    def surface_materials(self, scene, si, active):
        albedo, tau, rho_l = mi.Color3f(0.0), mi.Float(0.0), mi.Float(0.0)
        ptr = si.bsdf()
        for bsdf in hitlib.surface_bsdfs(scene):
            m = active & (ptr == mi.BSDFPtr(bsdf))
            material = getattr(bsdf, "material", None)
            if material is not None:
                a, t, r = material(si, m)
            else:
                a = mi.Color3f(bsdf.eval_diffuse_reflectance(si, m))
                t, r = mi.Float(1.0), mi.luminance(a)
            albedo = dr.select(m, a, albedo)
            tau = dr.select(m, t, tau)
            rho_l = dr.select(m, r, rho_l)
        return albedo, tau, rho_l

    # ---------------------------------------------------------------- main
    def sample(self, mode, scene, sampler, ray, depth=None, δL=None, δaovs=None,
               state_in=None, active=True, **kwargs):
        rays = mi.Ray3f(dr.detach(ray))
        nodes = hitlib.gaussian_nodes(scene)
        hit_list = hitlib.trace(scene, rays, self.max_hits, self.min_transmittance, nodes)
        n_rays = dr.width(rays.o)

        g = hitlib.eval_gaussian_hits(nodes, rays, hit_list)
        w, t_after = hitlib.blend_weights(g)
        if nodes:
            lighting = GaussianLighting(scene, nodes, self.samples, self.cache, follow_normals=True,
                                        trace_sun=self.sun_visibility == "trace",
                                        bounces=self.bounces, diffuse_fresnel=self.diffuse_fresnel,
                                        f0=self.f0,
                                        light_transmittance=self.moving_transmittance(scene, nodes))
            colour, albedo, n, tau, rho_l = self.shade_gaussian_hits(lighting, nodes, rays, hit_list, g)
        else:
            colour, albedo, n, tau, rho_l = mi.Color3f(0), mi.Color3f(0), mi.Vector3f(0), 0.0, 0.0
        per_hit = {"rgb": colour, "albedo": albedo, "normal": n, "roughness": tau,
                   "lidar_albedo": rho_l, "depth": g.t, "alpha": 1.0}

        # Behind the Gaussians: a mesh shaded with its own BSDF, else the sky.
        si = hit_list.surface_interaction(rays)
        surf = hit_list.surface_valid & si.is_valid()
        behind = {"rgb": dr.zeros(mi.Color3f, n_rays)}
        if dr.any(surf):
            a, t, r = self.surface_materials(scene, si, surf)
            behind = {"rgb": self.shade_surface(scene, sampler, si, nodes, surf),
                      "albedo": dr.select(surf, a, 0.0), "normal": dr.select(surf, si.sh_frame.n, 0.0),
                      "roughness": dr.select(surf, t, 0.0), "lidar_albedo": dr.select(surf, r, 0.0),
                      # si.t is inf off the surface: 0 * inf = NaN
                      "depth": dr.select(surf, si.t, 0.0), "alpha": dr.select(surf, 1.0, 0.0)}
            behind["rgb"] = dr.select(surf, behind["rgb"], 0.0)
        env = scene.environment()
        if env is not None and not self.hide_emitters:
            bg = dr.zeros(mi.SurfaceInteraction3f, n_rays)
            bg.wi = -rays.d
            behind["rgb"] = dr.select(surf, behind["rgb"], mi.Color3f(env.eval(bg, ~surf)))
        c = hitlib.composite_front_to_back(g, w, t_after, per_hit, behind)
        L, albedo_aov, normal_aov = c["rgb"], c["albedo"], c["normal"]
        tau_aov, rho_aov, depth_aov, alpha = c["roughness"], c["lidar_albedo"], c["depth"], c["alpha"]

        aovs = [albedo_aov.x, albedo_aov.y, albedo_aov.z, normal_aov.x, normal_aov.y,
                normal_aov.z, tau_aov, rho_aov, depth_aov, alpha]
        valid = mi.Bool(True)
        return mi.Spectrum(L), valid, aovs, None

    def to_string(self):
        return "InvRGBLIntegrator[samples=%d, bounces=%d, max_hits=%d]" % (
            self.samples, self.bounces, self.max_hits)


def register():
    mi.register_integrator("invrgbl", lambda props: InvRGBLIntegrator(props))
