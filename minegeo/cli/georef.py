"""``minegeo georef``: georeference a map with ground control points (7- or 6-parameter LSQ fit).

Writes ``MAP_GEO`` (the map in the CRS, stored relative to a recorded origin) with its sidecar
``MAP_GEO.georef.json``, and ``DIR/result.json`` + ``DIR/report.html``. Exit status 0 when the
fit is ok or has warnings (printed), 1 when it failed (unit mismatch, mirrored coordinates: no
map is written), 2 for input errors.
"""

from __future__ import annotations

import sys
from pathlib import Path

from minegeo._params import arg_type
from minegeo.cli._argtypes import positive_float

HELP = "georeference a map into a projected CRS from ground control points (Helmert 7/6-parameter LSQ)"


#: the parameter class whose field rules the options use (imported when an option is parsed)
_GEO = "minegeo.georef.result:GeorefParams"


def add_arguments(parser) -> None:
    parser.add_argument("--map", required=True, help="map point cloud (PLY, PCD, LAS/LAZ, XYZ...) in its local frame")
    parser.add_argument("--gcps", required=True, help="GCP CSV: id,x,y,z,E,N,H,sigma_E_m,sigma_N_m,sigma_H_m")
    parser.add_argument("--crs", default=None, help="CRS of E,N,H, e.g. EPSG:5186 (default: '# crs:' line of the GCP file)")
    parser.add_argument("--out", required=True, help="georeferenced map to write (MAP_GEO), e.g. map_geo.ply")
    parser.add_argument("--report", required=True, help="output directory for result.json and report.html")
    parser.add_argument("--model", choices=("similarity", "rigid"), default="similarity",
                        help="similarity: 7 parameters with scale (default); rigid: 6 parameters, scale 1")
    parser.add_argument("--convention", choices=("position_vector", "coordinate_frame"), default="position_vector",
                        help="rotation sign convention reported: EPSG 9606 position vector (default) or 9607")
    parser.add_argument("--sigma-local-m", type=arg_type(_GEO, "sigma_local_m"), default=0.0,
                        help="std. dev. of the GCP map coordinates (target picking), m (default 0)")
    parser.add_argument("--default-sigma-m", type=positive_float, default=0.01,
                        help="std. dev. of E,N,H when the GCP file has no sigma columns (default 0.01 m)")
    parser.add_argument("--blunder-alpha", type=arg_type(_GEO, "blunder_alpha"), default=0.001,
                        help="significance level of the per-coordinate w-test (default 0.001 -> 3.29)")
    parser.add_argument("--variance", choices=("aposteriori", "apriori"), default="aposteriori",
                        help="sigma0 scaling the parameter covariance (default aposteriori)")
    parser.add_argument("--max-scale-deviation", type=arg_type(_GEO, "max_scale_deviation"), default=0.01,
                        help="unit rule: fail when the GCP distance ratio differs from 1 by more (default 0.01)")
    parser.add_argument("--max-sigma0", type=arg_type(_GEO, "max_sigma0", le=1e12), default=10.0,
                        help="fail when sigma0 exceeds this (residuals >> stated GCP sigmas; default 10)")
    parser.add_argument("--force", action="store_true",
                        help="write MAP_GEO even when the fit failed (never for production use)")


def streamable_map(map_path: Path, out_path: Path):
    """The map opened for chunked reading (:mod:`minegeo.io.chunked`) when ``georef`` can stream it:
    a PLY/PCD map whose records are x, y, z only (nothing else to carry over), read in chunks, and
    a ``.ply`` output; or a LAS/LAZ map and a ``.las``/``.laz`` output (every field of every record
    is copied, only the coordinates change: :func:`~minegeo.georef.stream_georeferenced_las`).
    Otherwise None: the map is read whole (attributes, normals and colour are transformed and
    written as before)."""
    from minegeo.errors import MinegeoError
    from minegeo.io.chunked import open_point_chunks

    src, dst = map_path.suffix.lower(), out_path.suffix.lower()
    las = src in (".las", ".laz") and dst in (".las", ".laz")
    if not las and (dst != ".ply" or src not in (".ply", ".pcd")):
        return None
    try:
        chunks = open_point_chunks(map_path)
    except (MinegeoError, OSError):
        return None  # the whole-file reader reports the problem in its own words
    if las:  # every field of each record is carried over by stream_georeferenced_las
        return chunks if chunks.chunked and chunks.format in ("las", "laz") else None
    return chunks if chunks.chunked and chunks.metadata.get("xyz_only") else None


def map_origin_auto(chunks) -> int:
    """Pass 1 over a streamed map: set ``chunks.origin`` to ``read_point_cloud(..., origin="auto")``'s
    origin (0 within +-10 km, else the rounded bounding-box centre) and return the point count."""
    import numpy as np

    from minegeo.errors import TooFewPointsError
    from minegeo.io.chunked import scan_bounds

    try:
        n, lo, hi = scan_bounds(chunks)
    except TooFewPointsError:
        return 0
    if max(abs(lo).max(), abs(hi).max()) > 1e4:
        chunks.origin = np.round(0.5 * (lo + hi))
    return n


def run(args) -> int:
    from minegeo._output import OutputTransaction, run_timings
    from minegeo._provenance import StageTimer, input_record, provenance, write_json_atomic
    from minegeo.errors import InputError, TooFewPointsError
    from minegeo.georef import (
        GeorefParams,
        apply_georef,
        georeference,
        sidecar_path,
        stream_georeferenced_las,
        stream_georeferenced_map,
        write_georeferenced_map,
    )
    from minegeo.io import read_gcps, read_point_cloud
    from minegeo.report.georef_report import write_georef_report

    timer = StageTimer()
    params = GeorefParams(
        model=args.model,
        convention=args.convention,
        blunder_alpha=args.blunder_alpha,
        sigma_local_m=args.sigma_local_m,
        variance=args.variance,
        max_scale_deviation=args.max_scale_deviation,
        max_sigma0=args.max_sigma0,
    )
    import math

    for opt, v in (("--default-sigma-m", args.default_sigma_m), ("--sigma-local-m", args.sigma_local_m)):
        if not math.isfinite(v) or v < 0 or (opt == "--default-sigma-m" and v == 0):
            raise InputError(f"{opt} must be a finite standard deviation in metres"
                             f"{' > 0' if opt == '--default-sigma-m' else ' >= 0'}, got {v}")
    map_path = Path(args.map)
    out_path = Path(args.out)
    report_dir = Path(args.report)
    inputs_in = {"map (--map)": map_path, "GCP file (--gcps)": Path(args.gcps)}
    outs = {"--out": out_path, "the sidecar of --out": sidecar_path(out_path)}
    # every input is read and checked and every output path checked before anything is written;
    # the map, its sidecar and the report folder are staged and moved into place together
    from tqdm import tqdm

    from minegeo._output import progress_enabled

    bar = tqdm(total=5, desc="georef", unit="step", file=sys.stderr, disable=not progress_enabled(args))

    def step(name: str) -> None:
        bar.set_postfix_str(name)
        bar.update(1)

    with bar, OutputTransaction("georef", inputs=inputs_in, files=outs, folders={"--report": report_dir}) as tx:
        bar.set_postfix_str("read")
        with timer("read"):
            gcps = read_gcps(args.gcps, default_sigma_m=args.default_sigma_m)
            chunks = streamable_map(map_path, out_path)
            if chunks is None:
                cloud = read_point_cloud(map_path, origin="auto")
                n_map = len(cloud)
            else:  # pass 1 of 2: the count and the local origin ("auto"), one chunk in memory
                n_map = map_origin_auto(chunks)
        if n_map == 0:
            raise TooFewPointsError(f"the map {map_path} holds no points: there is nothing to georeference")
        step("fit")
        with timer("fit"):
            result = georeference(gcps, args.crs, params)
        inputs = {"map": input_record(map_path), "gcps": input_record(args.gcps)}
        outputs = {}
        cloud_geo = None
        if result.ok or args.force:
            extra = {"inputs": inputs, "report": str(report_dir / "report.html")}
            step("transform")
            if chunks is None:
                with timer("transform"):
                    cloud_geo = apply_georef(cloud, result, allow_failed=args.force)
                step("write map")
                with timer("write_map"):
                    write_georeferenced_map(tx.file("--out"), cloud_geo, result, extra=extra)
            else:  # pass 2 of 2: transformed and written chunk by chunk
                step("write map")
                writer = stream_georeferenced_las if chunks.format in ("las", "laz") else stream_georeferenced_map
                with timer("transform_and_write_map"):
                    _, _, cloud_geo = writer(tx.file("--out"), chunks, result, n_map, allow_failed=args.force,
                                             extra=extra)
            outputs = {"map_geo": str(out_path), "sidecar": str(sidecar_path(out_path))}
        outputs["result_json"] = str(report_dir / "result.json")
        outputs["report_html"] = str(report_dir / "report.html")
        step("report")
        prov = provenance(seed=None, origin=result.origin, inputs=list(inputs.values()))
        stage = tx.folder("--report")
        summary = {
            "command": "georef",
            "status": result.status,
            "reason": result.reason,
            "parameters": params.as_dict(),
            "crs": result.crs,
            "origin": result.origin,
            "T_crs_map": result.T_crs_map,
            "outputs": outputs,
            "timings_s": {**timer.as_dict(), **run_timings(args)},
            "provenance": prov,
            "result": result.as_dict(),
        }
        write_json_atomic(stage / "result.json", summary)
        write_georef_report(stage / "report.html", result, inputs=inputs, cloud_geo=cloud_geo, outputs=outputs,
                            provenance=prov, timings=summary["timings_s"])
        bar.n = bar.total - 1  # steps skipped for a failed fit count as done
        step("done")

    t = result.translation_m
    rms = result.rms_m
    if getattr(args, "quiet", False):  # -q: only warnings and errors (the result is in the files)
        return 0 if result.ok else 1
    print(f"status: {result.status.upper()}" + (f" — {result.reason}" if result.reason else ""))
    print(f"model {result.model}: T = ({t[0]:.4f}, {t[1]:.4f}, {t[2]:.4f}) m, scale {result.scale:.9f} "
          f"({result.ds_ppm:+.2f} ppm), yaw {result.euler_zyx_dms[2]}")
    print(f"sigma0 {result.sigma0:.3f} (dof {result.dof}), chi-square {result.chi2['verdict']}, "
          f"RMS horizontal {rms['horizontal'] * 1000:.1f} mm, height {rms['height'] * 1000:.1f} mm"
          + (f", suspected blunder: {result.suspected_blunder_id}" if result.suspected_blunder_id else ""))
    print("written: " + ", ".join(outputs.values()))
    return 0 if result.ok else 1
