"""Stage 2's starting point: the sun's irradiance, and albedo that reproduces stage 1.

Stage 1 leaves a view-independent colour ``c`` per Gaussian. Stage 2 explains
it as albedo times shading; the Lambertian part of ``invrgbl``'s shading is

    c = a (D + E v cos / pi)

with ``D`` the Gaussian's ambient term (mean of sky radiance times traced sky
visibility over its samples, plus, with bounces, the light its neighbours
pass on), ``v`` its sun visibility, ``cos`` the sun's
incidence and ``E`` the sun's irradiance.

With free per-Gaussian albedo every ``E`` fits the images equally well, so
``E`` must come from where albedo is shared, or known: the LiDAR albedo sees
no shadows. Among Gaussians facing the same way, the sunlit and the shadowed
groups' colours (divided by their LiDAR albedo) give

    E = pi (c_lit / c_shadow * D_shadow - D_lit) / cos_lit

with medians per group and per channel. Groups are whole facings, not small
patches: a sun direction a few degrees off moves shadow edges by metres, so
Gaussians near an edge are often in the wrong group, while the bulk of open
sun and deep shadow is not.

The albedo then starts at ``c / (D + E v cos / pi)``, so stage 2 starts from
an image that already matches stage 1 instead of first fighting a wrong level;
where that albedo would clip at 1 for many Gaussians, sky and sun are raised
first (:func:`light_scale`).
"""

from __future__ import annotations

import numpy as np

from ..physics.colour import LUMINANCE
from .selection import PatchRegression, surface_patches

#: Most rounds of visibility correction and re-estimation at stage 2's start,
#: and the relative change of the sun's irradiance (luminance) that ends them.
MAX_ROUNDS = 6
SETTLED = 0.01
#: Visibility thresholds of the sunlit and shadowed groups compared.
LIT, SHADOW = 0.7, 0.3
#: Least Gaussians per group for a facing to count.
MIN_GROUP = 20


def seen_weight(table, frozen_hits):
    """Per global Gaussian: the blend weight it gets summed over camera hits.

    ``frozen_hits``: per frame, its frozen hits, or ``(hits, valid)`` with
    ``valid`` a bool per pixel (hits on the other pixels do not count)."""
    w = np.zeros(table.total, np.float64)
    for item in frozen_hits:
        fh, valid = item if isinstance(item, tuple) else (item, None)
        g = np.array(table.global_index(fh.node_ids, fh.prims))
        weight = np.array(fh.weight, np.float64)
        if valid is not None:
            weight = np.where(np.asarray(valid, bool)[np.array(fh.ray)], weight, 0.0)
        w += np.bincount(g, weight, minlength=table.total)
    return w


def estimate_sun_irradiance(colour, sky_term, visibility, cos, normals, seen, lidar_albedo=None):
    """Per-channel sun irradiance from sunlit/shadowed colour ratios.

    Gaussians are grouped by facing (dominant normal axis); in each facing
    with enough sunlit and shadowed Gaussians the ratio of median colours
    gives an estimate, and the count-weighted median over facings is kept.
    Dividing the colour by the LiDAR albedo first (shading-free, the paper's
    premise) removes most of the albedo differences between the two groups.

    Returns ``(E (3,), groups used)``; ``E`` is None when no facing holds
    enough of both.
    """
    ok = seen & np.all(np.isfinite(colour), axis=1) & np.all(colour > 1e-4, axis=1)
    shading = colour if lidar_albedo is None else colour / np.maximum(lidar_albedo, 0.05)[:, None]
    facing = surface_patches(np.zeros_like(normals), normals, size=1.0)
    lit = ok & (visibility >= LIT) & (cos > 0.2)
    shadow = ok & (visibility <= SHADOW)
    estimates, counts = [], []
    for f in np.unique(facing[ok]):
        a, b = lit & (facing == f), shadow & (facing == f)
        if a.sum() < MIN_GROUP or b.sum() < MIN_GROUP:
            continue
        ratio = np.median(shading[a], axis=0) / np.median(shading[b], axis=0)
        d_lit, d_sh = np.median(sky_term[a], axis=0), np.median(sky_term[b], axis=0)
        estimates.append(np.pi * (ratio * d_sh - d_lit) / np.median(cos[a]))
        counts.append(min(a.sum(), b.sum()))
    if not estimates:
        return None, 0
    est, w = np.array(estimates), np.array(counts, np.float64)
    out = np.empty(3)
    for c in range(3):   # weighted median per channel
        order = np.argsort(est[:, c])
        cum = np.cumsum(w[order])
        out[c] = est[order[np.searchsorted(cum, 0.5 * cum[-1])], c]
    return np.maximum(out, 0.0), len(estimates)


#: Factor (in luminance) by which the facing-based sun irradiance may fall
#: below the lighting selection's level before the selection's level is used.
MAX_DISAGREEMENT = 4.0
#: Factor by which it may exceed that level. The selection's sun/sky ratio
#: is a regression slope on traced shadows, and every shadow the stage-1
#: geometry casts wrongly pulls it towards 0 (errors in the regressor): on
#: the street (true sun 3.9 in luminance) the selection's level was
#: 0.39-0.72 where the facings gave 1.8-3.3; with the same options a fit
#: started from the facings relit 0.5 dB better (20.63 against 20.13 dB).
MAX_EXCESS = 10.0


#: The sun levels one start may be told to keep (:func:`reconcile_sun_irradiance`'s
#: ``keep``): None lets the two rules below decide.
SUN_LEVELS = (None, "facings", "selection")


def reconcile_sun_irradiance(estimate, selection_level, keep=None):
    """The sun irradiance stage 2 starts from: the facing estimate
    (:func:`estimate_sun_irradiance`) where it agrees with the lighting
    selection's level (``pi x`` its sun/sky ratio ``x`` the sky term),
    at most :data:`MAX_DISAGREEMENT` below it or :data:`MAX_EXCESS` above it
    (the selection's level is biased low); otherwise its colour at the
    selection's level. The facing estimate rests on a median over a few facings and can
    collapse (one KITTI fit started from a sun of 0.09 against a selection
    level near 2, and stage 2 fell to 8 dB); the selection's ratio comes
    from every seen Gaussian.

    ``keep`` (one of :data:`SUN_LEVELS`) overrides the rules: "facings"
    keeps the facing estimate whatever the selection says (the selection's
    level only where there is none); "selection" takes the selection's
    level even where the two agree. A start made again under other
    roughness re-estimates the facings, and near a bound the rules could
    flip: ``keep`` holds the decision made once per sun. Returns
    ``(E (3,), source)``.
    """
    if keep not in SUN_LEVELS:
        raise ValueError("keep: %r is none of %s" % (keep, SUN_LEVELS))
    level = float(selection_level)
    if estimate is None:
        return np.full(3, max(level, 1e-3)), "selection (no facing with lit and shadowed Gaussians)"
    e = float(np.asarray(estimate) @ LUMINANCE)
    agree = level <= 0 or level / MAX_DISAGREEMENT <= e <= level * MAX_EXCESS
    if keep == "selection" or (keep is None and not agree):
        colour = np.asarray(estimate, np.float64) / e if e > 1e-6 else np.ones(3)
        return np.maximum(colour * level, 1e-3), "selection (facings gave %.3g)" % e
    return np.maximum(np.asarray(estimate, np.float64), 1e-3), "facings"


def kept_sun_level(source):
    """The ``keep`` (:data:`SUN_LEVELS`) that makes a start again with the
    sun level a start's ``source`` says it took: "facings", "selection"
    where the facings were overruled, None where there was no facing
    estimate to choose from."""
    if source == "facings":
        return "facings"
    return "selection" if facings_overruled(source) else None


def facings_overruled(source):
    """Whether :func:`reconcile_sun_irradiance` (its ``source``) replaced the
    facings' estimate with the selection's level."""
    return str(source).startswith("selection (facings gave")


def lidar_albedo_scale(c, shading, rho, usable):
    """The spectral scale ``k`` (luminance) that takes the LiDAR albedo
    ``rho`` to the RGB albedo: the median of ``c / (rho shading)`` (colour
    and shading in luminance) over the ``usable`` Gaussians. None where
    fewer than :data:`MIN_GROUP` are."""
    if usable.sum() < MIN_GROUP:
        return None
    return float(np.median(c[usable] / (rho[usable] * np.maximum(shading[usable], 1e-12))))


def visibility_from_lidar_albedo(colour, sky_term, sun_irradiance, visibility, cos, seen,
                                 lidar_albedo, shadow=SHADOW, lit=LIT):
    """Correct the traced sun visibility where the colour clearly says otherwise.

    The RGB albedo is taken to follow the LiDAR albedo up to one spectral
    scale ``k`` (the median over traced-sunlit Gaussians). A Gaussian's sun
    visibility is then what its colour implies,
    ``v = (c / (k rho) - D) pi / (E cos)`` in luminance. Where the trace says
    sunlit and the colour implies less than ``shadow``, the shadow comes from
    geometry the fit lacks (or a sun a few degrees off) and ``v`` is lowered
    to it; where the trace says shadowed and the colour implies more than
    ``lit``, the occluder is geometry the fit has but the scene has not (a
    wall extended above a lower roof) and ``v`` is raised to it. In between,
    the trace stands.

    Returns ``(visibility, share of seen Gaussians lowered, share raised)``.
    """
    c, d, e = colour @ LUMINANCE, sky_term @ LUMINANCE, float(sun_irradiance @ LUMINANCE)
    rho = np.maximum(lidar_albedo, 0.05)
    usable = seen & (lidar_albedo > 0.05) & (cos > 0.2) & np.isfinite(c)
    k = None if e <= 1e-4 else lidar_albedo_scale(
        c, d + e * visibility * cos / np.pi, rho, usable & (visibility >= lit))
    if k is None:   # no sun to be shadowed from
        return visibility, 0.0, 0.0
    implied = (c / (k * rho) - d) * np.pi / (e * np.maximum(cos, 0.2))
    lower = usable & (visibility >= 0.5) & (implied < shadow)
    raise_ = usable & (visibility < 0.5) & (implied > lit)
    out = visibility.copy()
    change = lower | raise_
    out[change] = np.clip(implied[change], 0.0, 1.0)
    n = max(seen.sum(), 1)
    return out, float(lower.sum() / n), float(raise_.sum() / n)


def settle_sun_and_visibility(colour, ambient, sun_irradiance, source, traced, cos, normals,
                              seen, lidar_albedo, selection_level, keep=None):
    """Alternate :func:`visibility_from_lidar_albedo` (correcting the
    ``traced`` visibility under the current irradiance) and
    :func:`estimate_sun_irradiance` (from the corrected groups, reconciled
    with ``selection_level`` and ``keep``) until the irradiance changes by less than
    :data:`SETTLED` (a fixed point within 3-4 rounds on the street), at most
    :data:`MAX_ROUNDS` times.

    ``ambient``: each Gaussian's light without the sun, sky plus bounce.
    Returns ``(E, visibility, source, share lowered, share raised)``.
    """
    E, vis, lowered, raised = np.asarray(sun_irradiance, np.float64), traced, 0.0, 0.0
    for _ in range(MAX_ROUNDS):
        vis, lowered, raised = visibility_from_lidar_albedo(colour, ambient, E, traced, cos, seen,
                                                            lidar_albedo)
        estimate, _ = estimate_sun_irradiance(colour, ambient, vis, cos, normals, seen, lidar_albedo)
        if estimate is None:
            break
        before = float(E @ LUMINANCE)
        E, source = reconcile_sun_irradiance(estimate, selection_level, keep)
        if abs(float(E @ LUMINANCE) - before) <= SETTLED * max(before, 1e-6):
            break
    return E, vis, source, lowered, raised


#: The albedo's range at the start (:func:`albedo_from_shading`).
ALBEDO_FLOOR, ALBEDO_TOP = 0.02, 1.0


def clipped_albedo(albedo):
    """Per Gaussian, whether its albedo (N, 3) clipped at the top of the
    range in some channel, and whether at the floor (and not at the top)."""
    top = (albedo >= ALBEDO_TOP - 1e-3).any(axis=1)
    return top, (albedo <= ALBEDO_FLOOR + 1e-4).any(axis=1) & ~top


def unclip_visibility(target, ambient, sun_per_visibility, visibility, albedo, seen,
                      lidar_albedo=None):
    """Sun visibility that lets clipped albedo reproduce stage 1's colour.

    At stage 2's start the albedo is ``target / (ambient + S v)`` per
    channel (``target``: stage 1's colour less the specular light;
    ``ambient``: sky and bounce light; ``S``, ``sun_per_visibility``: the sun's
    term at full visibility; all per Gaussian and at the start's light level)
    clipped into [:data:`ALBEDO_FLOOR`, :data:`ALBEDO_TOP`]. A clipped
    Gaussian does not reproduce its colour, and on the KITTI excerpt the
    clipped half of the Gaussians (31 % at the top, 19 % at the floor) held
    all of the start's loss to stage 1 (``tests/bench/start_gap.py``:
    19.59 against 21.31 dB on the validation frames; the specular light's
    view dependence cost 0.01 dB). Stage 2 learns ``v`` per Gaussian and
    moves it there by gradient; this puts it there at the start.

    A Gaussian whose albedo clipped at the top is given more sun (its
    shadow is cast by geometry the scene lacks), one clipped at the floor
    less (a shadow the fitted geometry misses), never the other way: ``v``
    becomes what reproduces its colour (luminance) with the albedo the
    LiDAR albedo implies (:func:`lidar_albedo_scale`, clipped into the
    range), or, without LiDAR albedo, the bound it clipped at; within
    [0, 1]. Gaussians the cameras do not see (``seen``), or the sun does not
    reach (``S`` near 0), keep theirs.

    Returns ``(visibility, share of seen Gaussians raised, share lowered)``.
    """
    t, a_l = target @ LUMINANCE, ambient @ LUMINANCE
    s_l = sun_per_visibility @ LUMINANCE
    top, floor = clipped_albedo(albedo)
    top, floor = seen & top, seen & floor
    lit_able = s_l > 1e-4 * np.maximum(a_l, 1e-6)
    want = np.where(top, ALBEDO_TOP, ALBEDO_FLOOR)
    if lidar_albedo is not None:
        rho = np.maximum(lidar_albedo, 0.05)
        # The scale from the sunlit Gaussians whose albedo did not clip.
        usable = (seen & ~top & ~floor & (lidar_albedo > 0.05) & np.isfinite(t)
                  & (visibility >= LIT) & lit_able)
        k = lidar_albedo_scale(t, a_l + visibility * s_l, rho, usable)
        if k is not None and np.isfinite(k) and k > 0:
            want = np.clip(k * rho, ALBEDO_FLOOR, ALBEDO_TOP)
    implied = np.clip((t / np.maximum(want, 1e-6) - a_l) / np.maximum(s_l, 1e-12), 0.0, 1.0)
    out = visibility.astype(np.float64).copy()
    up = top & lit_able & (implied > out)
    down = floor & lit_able & (implied < out)
    out[up] = implied[up]
    out[down] = implied[down]
    n = max(int(seen.sum()), 1)
    return out, float(up.sum() / n), float(down.sum() / n)


#: Quantile of the seen Gaussians' required albedo (largest channel) that
#: :func:`light_scale` brings down to :data:`ALBEDO_CEILING`.
CLIP_QUANTILE = 0.95
ALBEDO_CEILING = 0.9
#: Most the light is raised (a darker scene is a failed stage 1, not dim light).
MAX_LIGHT_SCALE = 100.0


def light_scale(colour, shading, seen):
    """Factor by which sky and sun must be raised so that the albedo which
    reproduces ``colour`` under ``shading`` (``c / shading``) stays below
    :data:`ALBEDO_CEILING` for all but the brightest 5 % of the ``seen``
    Gaussians; 1 when it already does (light is never lowered: the
    lighting selection's level stands where it is plausible).

    The shading model has no interreflection, so under a bridge or between
    tall extended walls the traced sky term can be far darker than the
    light the images show; clipped albedo cannot reproduce stage 1 and
    stage 2 would start several dB below it."""
    ok = seen & np.all(np.isfinite(colour), axis=1) & np.all(np.isfinite(shading), axis=1)
    if not ok.any():
        return 1.0
    need = np.max(colour[ok] / np.maximum(shading[ok], 1e-3), axis=1)
    q = float(np.quantile(need, CLIP_QUANTILE))
    return float(np.clip(q / ALBEDO_CEILING, 1.0, MAX_LIGHT_SCALE))


def search_levels(levels, score_at):
    """The light level to start from: ``levels`` ascending, ``score_at(k)``
    sets level ``k`` and returns its validation score. Stops at the first
    level that scores below the one before it: the score is taken to rise
    while the raised light unclips the albedo and to fall once it mostly
    brightens the sky seen directly and the specular light, so no level
    past the first fall is scored. Returns ``(best level, {level: score} of the levels scored, the
    level last set)``.

    Scoring every level cost a start five validation renders; in the fits
    logged, the score fell from the first or second raise on (KITTI 8
    minutes: 18.93, 18.73, 18.43, 18.04, 17.57 dB; the street 28.17, 28.16,
    28.12, 28.10), and a start is made five to seven times."""
    scores, previous = {}, None
    for k in levels:
        score = score_at(k)
        scores[k] = score if np.isfinite(score) else -np.inf
        if previous is not None and scores[k] < previous:
            break
        previous = scores[k]
    return max(scores, key=scores.get), scores, k


def albedo_from_shading(colour, sky_term, sun_term):
    """``c / (D + E v cos / pi)`` clipped into the albedo range."""
    shading = np.maximum(sky_term + sun_term, 1e-3)
    return np.clip(colour / shading, ALBEDO_FLOOR, ALBEDO_TOP)


def split_by_node(values, table, counts):
    """Global (G, ...) rows back into per-node blocks, in ``table``'s order."""
    return [values[off:off + n] for off, n in zip(table.offsets, counts)]


def as_rows(color3f):
    """A Dr.Jit 3-vector array as a numpy (N, 3) array."""
    return np.array(color3f, np.float64).T   # Dr.Jit gives (3, N)


#: Cell (metres) and LiDAR-albedo bin (a factor, in log) of the groups whose
#: albedo :func:`albedo_spread` compares, and the least Gaussians per group.
SPREAD_CELL = 1.0
SPREAD_BIN = np.log(1.2)
SPREAD_MIN_GROUP = 5


def albedo_spread(albedo, lidar_albedo, centres, weight):
    """How far the start's albedo is from the paper's premise that a surface
    of one LiDAR albedo has one RGB albedo (L_lidar->rgb, Eq. 9): the
    weighted mean square of log albedo luminance about its group's weighted
    mean, over groups of Gaussians sharing a :data:`SPREAD_CELL` cell and a
    :data:`SPREAD_BIN` bin of LiDAR albedo (groups of at least
    :data:`SPREAD_MIN_GROUP` Gaussians with ``weight > 0``; ``weight``: how
    much the cameras see each one). None where no group qualifies.

    Every start reproduces stage 1's colours by construction (the albedo
    absorbs whatever the light does not explain), so the images score a
    light by what the albedo clips and what the traced shadows misplace,
    and a weak sun misplaces least. The albedo's spread instead grows with
    every shadow or facing the light leaves in it, whichever way it errs:
    too weak a sun leaves the real shadows in the albedo, a wrong direction
    puts its own there. Measured on the streets
    (``tests/bench/start_candidates.py``): it tells the facings' sun from
    a weak one under nearly every direction, but not directions within
    about 15 degrees of each other, and on one stage 1 it gave a
    direction 37 degrees off a smaller spread than one 13 degrees off."""
    weight = np.asarray(weight, np.float64)
    ok = (weight > 0) & np.all(np.isfinite(albedo), axis=1) & np.isfinite(lidar_albedo) \
        & (np.asarray(lidar_albedo) > 0)
    if not ok.any():
        return None
    luminance = np.asarray(albedo, np.float64)[ok] @ LUMINANCE
    cell = np.floor(np.asarray(centres, np.float64)[ok] / SPREAD_CELL).astype(np.int64)
    band = np.floor(np.log(np.asarray(lidar_albedo, np.float64)[ok]) / SPREAD_BIN).astype(np.int64)
    group = np.unique(np.column_stack([cell, band]), axis=0, return_inverse=True)[1].ravel()
    big = (np.bincount(group) >= SPREAD_MIN_GROUP)[group]
    if not big.any():
        return None
    # The lighting test's within-patch residual, on log albedo instead of
    # log colour (the groups left empty weigh nothing).
    within = PatchRegression(luminance[big], group[big], weight[ok][big])
    return within.residual(within.y)


#: How far (dB, on the validation frames) below the best start another
#: start may score and still be chosen for a smaller albedo spread.
START_PSNR_MARGIN = 1.0


def choose_start(scores, spreads):
    """Index of the start stage 2 keeps among candidates with validation
    PSNRs ``scores`` and albedo spreads ``spreads`` (:func:`albedo_spread`,
    None where not measured): among those within :data:`START_PSNR_MARGIN`
    of the best PSNR, the one with the least spread; the best PSNR where
    any of those has no spread. The margin keeps out starts the images
    reject (the facings' sun under the lighting's candidates 31 and 34
    degrees off started 6 and 8 dB below the best start on two streets,
    and 4 dB below on the KITTI excerpt) and lets through those near the
    truth's light (0.1-0.8 dB below the best on three streets;
    ``tests/bench/start_candidates.py``). Non-finite
    scores arrive as -inf and are never within the margin of a finite one."""
    scores = np.asarray(scores, np.float64)
    best = int(np.argmax(scores))
    near = [i for i in range(len(scores)) if scores[i] >= scores[best] - START_PSNR_MARGIN]
    if any(spreads[i] is None or not np.isfinite(spreads[i]) for i in near):
        return best
    return min(near, key=lambda i: spreads[i])
