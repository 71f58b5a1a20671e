"""A readable summary of a scene package: grid, place, surface model, sources, and
what the paper's protocol can do on it (altitudes, observation sizes, meta-tasks).

:func:`summarize` returns plain data (JSON-able); :func:`format_summary` turns
it into text for ``geonav tiles info``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from geonav.camera import Camera
from geonav.scene import Scene
from geonav.tasks import view_margin_m

#: The altitudes of the paper's curriculum (m above ground).
ALTITUDES_M = (300.0, 75.0, 45.0, 15.0)
#: Observation sizes (px) worth reporting.
OBS_SIZES_PX = (64, 84, 128, 256)


def count_meta_tasks(scene: Scene, *, size_m: float = 150.0, margin_alt_m: float = 300.0,
                     camera: Camera | None = None, need: float = 0.99) -> int:
    """How many disjoint ``size_m`` squares fit with the view margin of ``margin_alt_m``.

    Squares are laid on a grid from the lower-left of the area that keeps the
    margin (half the camera footprint at ``margin_alt_m``: 300 m at 300 m with a
    90 degree camera) inside the scene, and counted when the square plus its
    margin has valid imagery on at least ``need`` of its pixels.
    """
    camera = camera or Camera()
    margin = view_margin_m(margin_alt_m, camera)
    xmin, ymin, xmax, ymax = scene.bounds_m
    nx = math.floor((xmax - xmin - 2 * margin) / size_m + 1e-9)
    ny = math.floor((ymax - ymin - 2 * margin) / size_m + 1e-9)
    count = 0
    for i in range(max(0, nx)):
        for j in range(max(0, ny)):
            x0, y0 = xmin + margin + i * size_m, ymin + margin + j * size_m
            rs, cs = scene.window((x0 - margin, y0 - margin, x0 + size_m + margin,
                                   y0 + size_m + margin))
            window = scene.mask[rs, cs]
            if window.size and float(window.mean()) >= need:
                count += 1
    return count


def altitude_support(scene: Scene, *, camera: Camera | None = None,
                     altitudes_m: Sequence[float] = ALTITUDES_M,
                     obs_sizes_px: Sequence[int] = OBS_SIZES_PX) -> list[dict[str, Any]]:
    """Per altitude: footprint, whether it fits in the scene, and per observation size
    the view's ground resolution and whether the imagery is at least that fine."""
    camera = camera or Camera()
    side = min(scene.size_m)
    rows = []
    for alt in altitudes_m:
        footprint = camera.footprint_m(alt)
        sizes = {}
        for n in obs_sizes_px:
            res = footprint / n
            sizes[str(n)] = dict(view_res_m=round(res, 4), sharp=scene.gsd_m <= res * 1.001,
                                 blur_factor=round(max(1.0, scene.gsd_m / res), 2))
        rows.append(dict(alt_m=alt, footprint_m=round(footprint, 2),
                         fits=footprint <= side, obs=sizes))
    return rows


def summarize(scene: Scene, *, camera: Camera | None = None, task_size_m: float = 150.0,
              margin_alt_m: float = 300.0) -> dict[str, Any]:
    """Everything ``geonav tiles info`` shows, as plain data."""
    camera = camera or Camera()
    m = scene.manifest or {}
    xmin, ymin, xmax, ymax = scene.bounds_m
    dsm = None
    if scene.dsm is not None:
        valid = np.isfinite(scene.dsm)
        heights = scene.dsm[valid]
        dsm = dict(valid_fraction=round(float(valid.mean()), 4))
        if heights.size:
            p50, p99 = np.percentile(heights, [50, 99])
            dsm.update(min_m=round(float(heights.min()), 2), median_m=round(float(p50), 2),
                       p99_m=round(float(p99), 2), max_m=round(float(heights.max()), 2))
        dsm["ground_alt_m"] = m.get("ground_alt_m")
        dsm["height_reference"] = (m.get("dsm") or {}).get("height_reference",
                                                           "height above ground (m)")
    sources = []
    for src in m.get("sources", []):
        keep = ("kind", "file", "zoom", "scheme", "native_gsd_m", "est_native_gsd_m", "tiles",
                "tiles_corrupt", "tiles_missing", "attribution", "sha256")
        entry = {k: src[k] for k in keep if k in src}
        crs = src.get("crs")
        if crs:
            try:
                from geonav.geo import parse_crs

                entry["crs"] = parse_crs(crs).name
            except Exception:  # noqa: BLE001 - the name is cosmetic
                entry["crs"] = str(crs)[:60]
        sources.append(entry)
    return dict(
        name=scene.name,
        path=str(scene.path) if scene.path else None,
        width_px=scene.width, height_px=scene.height,
        width_m=round(scene.size_m[0], 2), height_m=round(scene.size_m[1], 2),
        gsd_m=scene.gsd_m,
        bounds_m=[round(v, 3) for v in (xmin, ymin, xmax, ymax)],
        bounds_wgs84=m.get("bounds_wgs84"),
        origin=dict(lon_deg=scene.origin.lon_deg, lat_deg=scene.origin.lat_deg,
                    alt_m=scene.origin.alt_m),
        valid_fraction=round(float(scene.mask.mean()), 4),
        dsm=dsm,
        sources=sources,
        attribution=m.get("attribution", ""),
        resampling=m.get("resampling"),
        camera=dict(size_px=camera.size_px, fov_deg=camera.fov_deg),
        altitudes=altitude_support(scene, camera=camera),
        meta_tasks=dict(size_m=task_size_m, margin_alt_m=margin_alt_m,
                        margin_m=view_margin_m(margin_alt_m, camera),
                        fit=count_meta_tasks(scene, size_m=task_size_m,
                                             margin_alt_m=margin_alt_m, camera=camera)),
    )


def format_summary(s: dict[str, Any]) -> str:
    """The summary as aligned text lines."""
    lines = [
        f"scene {s['name']}" + (f"  ({s['path']})" if s.get("path") else ""),
        f"  size        {s['width_px']} x {s['height_px']} px = {s['width_m']:.1f} x "
        f"{s['height_m']:.1f} m at {s['gsd_m']:g} m/px",
        f"  origin      lon {s['origin']['lon_deg']:.7f}, lat {s['origin']['lat_deg']:.7f}, "
        f"ground {s['origin']['alt_m']:.2f} m AMSL",
        "  bounds      x {0:.2f}..{2:.2f} m, y {1:.2f}..{3:.2f} m (local tmerc)".format(
            *s["bounds_m"]),
    ]
    if s.get("bounds_wgs84"):
        w, so, e, n = s["bounds_wgs84"]
        lines.append(f"              lon {w:.7f}..{e:.7f}, lat {so:.7f}..{n:.7f} (WGS 84)")
    lines.append(f"  imagery     {s['valid_fraction']:.1%} valid"
                 + (f", resampled with {s['resampling']}" if s.get("resampling") else ""))
    d = s.get("dsm")
    if d is None:
        lines.append("  DSM         none (no obstacles)")
    elif "min_m" in d:
        lines.append(f"  DSM         {d['min_m']:.1f}..{d['max_m']:.1f} m above ground "
                     f"(median {d['median_m']:.1f}, 99% {d['p99_m']:.1f}), "
                     f"{d['valid_fraction']:.1%} known"
                     + (f", ground {d['ground_alt_m']:.2f} m" if d.get("ground_alt_m")
                        is not None else ""))
    else:
        lines.append("  DSM         present but without valid heights")
    lines.append(f"  attribution {s['attribution'] or '(none given)'}")
    for i, src in enumerate(s["sources"]):
        bits = [src.get("kind", "raster"), src.get("file", "?")]
        if "crs" in src:
            bits.append(src["crs"])
        if "zoom" in src:
            bits.append(f"zoom {src['zoom']} ({src.get('scheme', 'xyz')}, "
                        f"{src.get('tiles', '?')} tiles, {src.get('tiles_missing', 0)} missing, "
                        f"{src.get('tiles_corrupt', 0)} corrupt)")
        gsd = src.get("native_gsd_m", src.get("est_native_gsd_m"))
        if gsd is not None:
            bits.append(f"native {gsd:g} m/px")
        lines.append(("  sources     " if i == 0 else "              ") + ", ".join(map(str, bits)))
        if src.get("attribution") and src["attribution"] != s["attribution"]:
            lines.append(f"              attribution: {src['attribution']}")
    cam = s["camera"]
    sizes = list(s["altitudes"][0]["obs"]) if s["altitudes"] else []
    lines.append(f"  views       camera {cam['fov_deg']:g} deg; per observation size: ok = "
                 "imagery at least as fine as the view, xN = N times too coarse")
    lines.append("    alt m  footprint m  fits  " + "  ".join(f"{n + ' px':>8}" for n in sizes))
    for row in s["altitudes"]:
        cells = []
        for n in sizes:
            o = row["obs"][n]
            cells.append(f"{'ok' if o['sharp'] else 'x' + format(o['blur_factor'], 'g'):>8}")
        lines.append(f"    {row['alt_m']:5g}  {row['footprint_m']:11g}  "
                     f"{'yes' if row['fits'] else 'NO':>4}  " + "  ".join(cells))
    mt = s["meta_tasks"]
    lines.append(f"  meta-tasks  {mt['fit']} disjoint {mt['size_m']:g} m tasks fit with the "
                 f"{mt['margin_m']:g} m margin a {mt['margin_alt_m']:g} m view needs")
    return "\n".join(lines)
