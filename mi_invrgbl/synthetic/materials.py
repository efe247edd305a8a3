"""The true material of every mesh, and the road's texture.

Each mesh of the street carries exactly one :class:`Material`. By default the
renders use Mitsuba's stock ``roughplastic`` BSDF (GGX with ``alpha = roughness``, inner
IOR 1.5 so that its Fresnel reflectance at normal incidence is 0.04 = ``f0``):
it has the paper's two lobes, a Lambertian base of albedo ``albedo`` and a
GGX specular coat. (Its diffuse lobe is additionally scaled by the rough
coat's transmittance in and out and by the light recycled under the coat,
which depend on the roughness: 0.97 of a Lambertian lobe lit and seen
head-on at alpha 0.05, 0.44 at alpha 0.8, and less towards grazing angles;
``fit --diffuse-fresnel`` models it, see :mod:`mi_invrgbl.physics.coat`. Its
Smith shadowing dims the specular lobe at grazing angles more than the
paper's V-cavity term does; the recorded ``albedo`` is the BSDF's
``diffuse_reflectance``, the value a fit should recover up to scale.)
``make-scene --bsdf cooktorrance`` renders with the paper's own model instead
(the ``cooktorrance`` plugin), so that the truth lies in the family ``fit``
searches: what remains then is the inverse problem, not a model mismatch.

``lidar_albedo`` is the reflectance at the LiDAR's near-infrared wavelength.
It differs from the RGB albedo on purpose (vegetation is bright in the
infrared, lane paint is retro-reflective) so that a fit cannot copy one into
the other.
"""

from __future__ import annotations

import dataclasses

import numpy as np

#: Fresnel reflectance at normal incidence for every material (IOR 1.5).
F0 = 0.04
#: Inner IOR that gives ``F0`` for ``roughplastic``: ((n-1)/(n+1))^2 = 0.04.
INT_IOR = 1.5

#: Road texture: one period along the street (metres) and the road width.
ROAD_PERIOD = 6.0
ROAD_WIDTH = 10.0
#: Texture resolution (metres per texel).
TEXEL = 0.05


@dataclasses.dataclass
class Material:
    """True reflectance of one mesh (what ``materials.json`` records)."""

    name: str
    albedo: tuple          #: linear RGB diffuse albedo (mean, if textured)
    roughness: float       #: the paper's tau = GGX alpha
    lidar_albedo: float    #: near-infrared diffuse albedo (mean, if textured)
    f0: float = F0
    albedo_texture: str | None = None   #: PNG (sRGB) relative to the scene files
    lidar_texture: str | None = None    #: PNG (linear, 8-bit grey) relative to the scene files

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        d["albedo"] = [float(c) for c in self.albedo]
        return d

    def bsdf_xml(self, kind: str = "roughplastic") -> str:
        """The BSDF that renders this material, as XML: Mitsuba's stock
        ``roughplastic`` (default) or the paper's own ``cooktorrance``."""
        name = "diffuse_reflectance" if kind == "roughplastic" else "albedo"
        if self.albedo_texture:
            diffuse = ('<texture type="bitmap" name="%s">'
                       '<string name="filename" value="%s"/>'
                       '<string name="filter_type" value="bilinear"/></texture>'
                       % (name, self.albedo_texture))
        else:
            diffuse = '<rgb name="%s" value="%.6f %.6f %.6f"/>' % ((name,) + tuple(self.albedo))
        if kind == "cooktorrance":
            return ('<bsdf type="cooktorrance" id="mat_%s">'
                    '<float name="roughness" value="%.6f"/><float name="f0" value="%.6f"/>'
                    '<float name="lidar_albedo" value="%.6f"/>%s</bsdf>'
                    % (self.name, max(self.roughness, 1e-3), self.f0, self.lidar_albedo, diffuse))
        return ('<bsdf type="roughplastic" id="mat_%s">'
                '<string name="distribution" value="ggx"/>'
                '<float name="alpha" value="%.6f"/>'
                '<float name="int_ior" value="%.3f"/><float name="ext_ior" value="1.0"/>'
                '%s</bsdf>' % (self.name, max(self.roughness, 1e-3), INT_IOR, diffuse))


def road_textures(rng: np.random.Generator):
    """Road albedo (linear RGB) and LiDAR albedo textures with lane markings.

    Rows run across the road (v), columns along it (u, one ``ROAD_PERIOD``
    that repeats). Markings: solid edge lines 0.2 m inside each road edge and
    a dashed centre line (3 m paint, 3 m gap), each 0.15 m wide. Asphalt gets
    low-frequency patches and per-texel grain so that the camera sees texture
    along the street.
    """
    nu = int(round(ROAD_PERIOD / TEXEL))
    nv = int(round(ROAD_WIDTH / TEXEL))
    u = (np.arange(nu) + 0.5) * TEXEL                      # metres along the street
    v = (np.arange(nv) + 0.5) * TEXEL - ROAD_WIDTH / 2     # metres across, 0 = centre
    uu, vv = np.meshgrid(u, v)
    half = 0.075
    edge = (np.abs(np.abs(vv) - (ROAD_WIDTH / 2 - 0.2)) < half)
    centre = (np.abs(vv) < half) & (uu < ROAD_PERIOD / 2)
    paint = (edge | centre).astype(np.float32)

    # Patches: a smooth random field built from a few periodic cosines so the
    # texture tiles seamlessly along the street.
    patch = np.zeros_like(uu)
    for _ in range(4):
        ku = rng.integers(1, 4) * 2 * np.pi / ROAD_PERIOD
        kv = rng.uniform(0.5, 2.0)
        patch += np.cos(ku * uu + kv * vv + rng.uniform(0, 2 * np.pi))
    patch = patch / 4.0
    grain = rng.normal(0.0, 1.0, size=uu.shape)
    asphalt = np.clip(0.10 + 0.015 * patch + 0.01 * grain, 0.04, 0.2)
    asphalt_rgb = asphalt[..., None] * np.array([1.0, 1.0, 1.05])
    paint_rgb = np.array([0.75, 0.75, 0.72])
    albedo = (asphalt_rgb * (1 - paint[..., None]) + paint_rgb * paint[..., None]).astype(np.float32)
    lidar = (np.clip(0.12 + 0.02 * patch, 0.05, 0.3) * (1 - paint) + 0.6 * paint).astype(np.float32)
    return albedo, lidar


#: Facade colours (linear RGB) buildings draw from; LiDAR albedo drawn separately.
FACADE_COLOURS = (
    (0.55, 0.45, 0.35), (0.62, 0.60, 0.55), (0.45, 0.30, 0.22), (0.70, 0.65, 0.50),
    (0.35, 0.38, 0.42), (0.60, 0.40, 0.30), (0.50, 0.55, 0.50), (0.72, 0.70, 0.68),
)


def fixed_materials() -> dict[str, Material]:
    """Materials of the street's fixed furniture (buildings are drawn per seed)."""
    mats = [
        Material("road", (0.10, 0.10, 0.105), 0.9, 0.15,
                 albedo_texture="textures/road_albedo.png",
                 lidar_texture="textures/road_lidar.png"),
        Material("sidewalk", (0.42, 0.40, 0.37), 0.8, 0.35),
        Material("windows", (0.04, 0.05, 0.06), 0.08, 0.05),
        Material("poles", (0.22, 0.24, 0.25), 0.4, 0.30),
        Material("tree_trunk", (0.22, 0.15, 0.09), 0.9, 0.40),
        Material("tree_crown", (0.10, 0.25, 0.06), 0.9, 0.60),
        Material("parked_car", (0.55, 0.04, 0.03), 0.15, 0.30),
        Material("wheels", (0.03, 0.03, 0.03), 0.7, 0.05),
        Material("moving_car", (0.05, 0.12, 0.45), 0.2, 0.25),
        Material("wall", (0.60, 0.55, 0.45), 0.9, 0.50),
        Material("canopy", (0.30, 0.30, 0.32), 0.6, 0.30),
    ]
    return {m.name: m for m in mats}


def facade_material(index: int, rng: np.random.Generator) -> Material:
    """A building's facade: colour from the palette, rough, its own LiDAR albedo."""
    colour = FACADE_COLOURS[int(rng.integers(len(FACADE_COLOURS)))]
    return Material("building_%02d" % index, tuple(colour),
                    float(round(rng.uniform(0.6, 0.95), 3)),
                    float(round(rng.uniform(0.2, 0.6), 3)))
