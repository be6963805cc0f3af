"""Render the benchmark figures of README.md and docs/*.md from the committed results files.

A page holds a benchmark figure only between two markers::

    <!-- figures: NAME -->
    ... generated text ...
    <!-- /figures -->

``NAME`` is a key of :data:`RENDERERS`; its function reads one results file under
``benchmarks/results`` and returns the block's text: a line of conditions (results file, date,
commit, threads on both sides, machine load, each "not recorded" when the file lacks it) and the
table or lines. Nothing between the markers is written by hand.

Usage::

    python benchmarks/render_docs_figures.py --check   # exit 1 and a diff when a page disagrees
    python benchmarks/render_docs_figures.py --write   # rewrite every block from its file

``tests/docs/test_docs_figures.py`` runs the check.
"""

from __future__ import annotations

import argparse
import difflib
import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"

BEGIN = re.compile(r"^<!-- figures: (?P<name>[\w.-]+) -->\s*$")
END = re.compile(r"^<!-- /figures -->\s*$")
NOT_RECORDED = "not recorded"


# -- helpers -----------------------------------------------------------------------------------

def _load(name: str, results: Path) -> dict:
    return json.loads((results / name).read_text(encoding="utf-8"))


def _uptime_load(text: str | None) -> str | None:
    """The 1-minute load average of an ``uptime`` line."""
    if not text:
        return None
    m = re.search(r"load average:\s*([\d.]+)", text)
    return m.group(1) if m else None


def _fmt_load(values) -> str | None:
    vals = [float(v) for v in values if v is not None]
    if not vals:
        return None
    lo, hi = min(vals), max(vals)
    return f"{lo:.1f}" if f"{lo:.1f}" == f"{hi:.1f}" else f"{lo:.1f}-{hi:.1f}"


def conditions(file: str, *, date: str | None, commit: str | None, threads: str | None,
               load: str | None, extra: str = "") -> str:
    """The conditions line every rendered block starts with."""
    parts = [f"Results file `benchmarks/results/{file}`",
             f"measured {date or NOT_RECORDED}",
             f"commit {commit or NOT_RECORDED}",
             f"threads {threads or NOT_RECORDED}",
             f"1-minute load {load or NOT_RECORDED} (2-core machine shared with other jobs)"]
    return "*" + "; ".join(parts) + (f"; {extra}" if extra else "") + ".*"


def _date_from_name(file: str) -> str | None:
    m = re.search(r"(\d{4}-\d{2}-\d{2})", file)
    return m.group(1) if m else None


def _thin(n: int) -> str:
    return f"{n:,}".replace(",", "\u202f")


# -- renderers ---------------------------------------------------------------------------------

REGISTRATION_FILE = "registration_quick_2026-11-25_issue16_after.json"
REGISTRATION_TARGETS = {"normals": 0.8, "fpfh": 0.8, "icp_point_to_point": 0.8, "icp_point_to_plane": 0.8,
                        "ransac": 0.5}


def render_registration_quick(results: Path) -> str:
    """The quick registration benchmark (minegeo against Open3D 0.20, light parameter set)."""
    d = _load(REGISTRATION_FILE, results)
    meta = d["meta"]
    th = meta.get("threads")
    head = conditions(REGISTRATION_FILE, date=_date_from_name(REGISTRATION_FILE), commit=None,
                      threads=f"{th} for minegeo (Numba) and {th} for Open3D" if th else None, load=None,
                      extra=f"open3d {meta['versions'].get('open3d', '?')}, "
                            f"`python benchmarks/bench_registration.py --quick`")
    sizes = d.get("_sizes", {})
    lines = [head, "",
             f"Map {_thin(sizes['map_points'])} points, scan "
             f"{_thin(sizes['scan_points'])} points after voxel downsampling; ratio = minegeo / Open3D "
             "(lower is better), median or minimum of the interleaved runs.", "",
             "| stage | minegeo s | Open3D s | ratio | target | meets | agreement with Open3D |",
             "|---|---:|---:|---:|---:|---|---|"]
    for stage in ("voxel", "octree", "normals", "fpfh", "ransac", "icp_point_to_point", "icp_point_to_plane"):
        r = d[stage]
        tgt = REGISTRATION_TARGETS.get(stage)
        ratio = f"{r['ratio']:.2f}"
        meets = "—" if tgt is None else ("yes" if float(ratio) <= tgt else "**no (miss)**")
        lines.append(f"| {stage} | {r['minegeo_s']:.4f} | {r['open3d_s']:.4f} | {ratio} | "
                     f"{'—' if tgt is None else f'≤ {tgt}'} | {meets} | {_registration_agreement(stage, r)} |")
    return "\n".join(lines)


def _registration_agreement(stage: str, r: dict) -> str:
    a = r["agreement"]
    if stage in ("voxel", "octree"):
        return "identical" if a == 1.0 else f"{a:.4f} identical"
    if stage == "normals":
        return f"{100 * a:.3f} % of normals within 1e-6 rad"
    if stage == "fpfh":
        return f"max relative L1 difference {a:.1e}"
    if stage == "ransac":
        n = a["runs"]
        return (f"success {a['minegeo_successes']}/{n} (minegeo, Open3D mode), {a['minegeo_mode_successes']}/{n} "
                f"(minegeo mode) vs {a['open3d_successes']}/{n} (Open3D), {r['seeds_per_section']} seeds × "
                f"{len(r['sections'])} sections, budget {_thin(r['budget'])} iterations")
    return (f"Δ {a['rot_rad']:.1e} rad / {a['trans_m']:.1e} m; {r['iterations']} iterations, "
            f"{r['status']}")


POSEGRAPH_FILE = "posegraph_2026-11-29.json"


def render_posegraph(results: Path) -> str:
    """``minegeo posegraph`` on one Numba thread against GTSAM's single-threaded LM."""
    d = _load(POSEGRAPH_FILE, results)
    meta = d["meta"]
    head = conditions(POSEGRAPH_FILE, date=meta.get("date"), commit=meta.get("commit"),
                      threads="1 for minegeo (Numba) and 1 for GTSAM (single-threaded wheel)",
                      load=_fmt_load([_uptime_load(meta.get("uptime_before")),
                                      _uptime_load(meta.get("uptime_after"))]),
                      extra=f"GTSAM {meta.get('gtsam', '?')}; `python benchmarks/bench_posegraph.py --cli`")
    lines = [head, "",
             "F = the written graph's cost evaluated by GTSAM on the file's own factors; F* = GTSAM's LM run "
             "to convergence; process = CPU of the whole `minegeo posegraph` process, optimiser = wall time "
             "of the optimisation inside it; GTSAM = CPU of its `optimize()`.", "",
             "| graph | minegeo exit, status, iterations | (F − F*)/F* | minegeo process / optimiser s "
             "| GTSAM default: iterations, F, s | GTSAM converged: iterations, s |",
             "|---|---|---:|---|---|---|"]
    for name, r in d["results"].items():
        m = r["minegeo"]["1"]
        gd, gc = r["gtsam_default"], r["gtsam_converged"]
        above = (gd["cost"] - gc["cost"]) / gc["cost"]
        gd_note = f" ({above:.1e} above F*)" if above > 1e-6 else ""
        lines.append(f"| {name.removesuffix('.g2o')} | {m['exit']}, {m['status']}, {m['iterations']} "
                     f"| {m['relative_to_gtsam_converged']:.1e} | {m['process_s']:.1f} / {m['optimise_s']:.1f} "
                     f"| {gd['iterations']}, {gd['cost']:.10g}{gd_note}, {gd['process_s']:.1f} "
                     f"| {gc['iterations']}, {gc['process_s']:.1f} |")
    return "\n".join(lines)


BATCH_FILE = "batch_2026-11-25.json"


def render_batch(results: Path) -> str:
    """``minegeo localize-batch`` throughput and accuracy against the synthetic truth."""
    d = _load(BATCH_FILE, results)
    head = conditions(BATCH_FILE, date=d.get("date"), commit=d.get("commit"),
                      threads=f"{d.get('cpus', '?')} cores shared by the workers (each `cores // workers` "
                              "Numba threads)",
                      load=_fmt_load([_uptime_load(d.get("uptime_before")), _uptime_load(d.get("uptime_after"))]
                                     + [_uptime_load(r.get("uptime_after")) for r in d["runs"]]),
                      extra=f"{d['n_scans']} scans of `minegeo synth --preset small --seed {d['synth_seed']}` "
                            f"moved by random rigid motions, `--seed {d['seed']}`")
    lines = [head, "",
             "| workers | command wall s | scans/min (command) | scans/min (batch) | ok / ambiguous / failed "
             "| ok within its 95 % radius | ok within 0.10 m | worst ok error m | ok at a wrong place |",
             "|---:|---:|---:|---:|---|---:|---:|---:|---:|"]
    for r in d["runs"]:
        c, s = r["counts"], r["score"]
        lines.append(f"| {r['workers']} | {r['wall_s']:.1f} | {r['scans_per_minute_wall']:.1f} "
                     f"| {r['scans_per_minute_batch']:.1f} | {c['ok']} / {c['ambiguous']} / {c['failed']} "
                     f"| {s['ok_within_95_radius']}/{s['ok']} | {s['ok_within_0.10_m']}/{s['ok']} "
                     f"| {s['worst_ok_error_m']:.3f} | {s['wrong_place_ok']} |")
    o = d["one_by_one"]
    lines += ["", f"One by one with `minegeo localize`: {o['identical']} of {o['n']} `result.json` identical to "
              f"the batch's (timings aside); {o['in_process_scans_per_minute']:.1f} scans/min in one Python "
              f"process, {o['subprocess_scans_per_minute']:.1f} scans/min as a shell loop "
              f"({o['subprocess_s_per_scan']:.2f} s per scan); poses equal across worker counts: "
              f"{'yes' if d.get('poses_equal_across_worker_counts') else 'no'}."]
    return "\n".join(lines)


PREPARE_FILE = "prepare_scaling_2026-11-25.json"
GEOREF_FILE = "georef_scaling_2026-11-25.json"
GEOREF_LAS_FILE = "georef_scaling_2026-11-28_las.json"
_POW = {10 ** 6: "10⁶", 10 ** 7: "10⁷", 10 ** 8: "10⁸", 10 ** 9: "10⁹"}


def render_prepare_scaling(results: Path) -> str:
    """``minegeo prepare-map`` wall time and peak memory from 10⁶ to 10⁸ points."""
    d = _load(PREPARE_FILE, results)
    rows = d["rows"]
    head = conditions(PREPARE_FILE, date=d["meta"].get("date"), commit=d["meta"].get("commit"),
                      threads=d["meta"].get("threads"),
                      load=_fmt_load([r["load_before"][0] for r in rows]),
                      extra=f"profile {d['meta'].get('profile')}, {d['meta'].get('extent')}")
    lines = [head, "",
             "| input points | file GB | wall s | peak RSS GB | read + downsample s | normals + FPFH s "
             "| ICP target s | search structures s | map / ICP points | chunks |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {_POW.get(r['n_points'], r['n_points'])} | {r['file_bytes'] / 1e9:.3f} "
                     f"| {r['wall_s']:.1f} | {r['peak_rss_gb']:.2f} | {r['read_downsample_s']:.1f} "
                     f"| {r['features_s']:.1f} | {r['icp_target_s']:.1f} | {r['search_structures_s']:.1f} "
                     f"| {_thin(r['n_down'])} / {_thin(r['n_icp_points'])} | {r['n_chunks']} |")
    f = d["fit"]
    lines += ["", f"Fit over the sizes: wall time ∝ n^{f['a_wall']:.2f}, read + downsample ∝ "
              f"n^{f['a_read_downsample']:.2f}."]
    return "\n".join(lines)


def _render_georef(file: str, results: Path) -> str:
    d = _load(file, results)
    rows = d["rows"]
    head = conditions(file, date=_date_from_name(file), commit=d.get("commit"), threads=d.get("threads"),
                      load=_fmt_load([r["load_before"][0] for r in rows]),
                      extra="streamed (`--georef --no-prepare`)")
    lines = [head, "", "| input points | wall s | peak RSS GB | written GB | fit status |",
             "|---:|---:|---:|---:|---|"]
    for r in rows:
        lines.append(f"| {_POW.get(r['n_points'], r['n_points'])} | {r['wall_s']:.1f} | {r['peak_rss_gb']:.2f} "
                     f"| {r['out_bytes'] / 1e9:.3f} | {r['status']} |")
    return "\n".join(lines)


def render_georef_scaling(results: Path) -> str:
    """``georef`` streamed, PLY in / PLY out."""
    return _render_georef(GEOREF_FILE, results)


def render_georef_scaling_las(results: Path) -> str:
    """``georef`` streamed, LAS in / LAS out with every field."""
    return _render_georef(GEOREF_LAS_FILE, results)


SLAM_FILE = "slam_2026-11-30b.json"


def render_slam_ablation(results: Path) -> str:
    """The SLAM ablation on the synthetic VLP-16 sequences against KISS-ICP."""
    d = _load(SLAM_FILE, results)
    meta = d["meta"]
    th = meta.get("threads")
    head = conditions(SLAM_FILE, date=meta.get("date"), commit=meta.get("git"),
                      threads=f"{th} for minegeo (Numba) and {th} for KISS-ICP" if th else None, load=None,
                      extra="`python benchmarks/bench_slam.py`")
    lines = [head, "",
             "| sequence | method | ATE RMSE | ATE RMSE, aligned | RPE 10 m | RPE 100 m | end-point drift "
             "| loops / plane nodes |",
             "|---|---|---|---|---|---|---|---|"]
    names = {"odometry": "odometry", "+loops": "+ loops", "+planes": "+ planes",
             "+loops+planes": "+ both (default)"}
    for seq, r in d["results"].items():
        first = True
        for v, m in r["methods"].items():
            label = names.get(v, v)
            seq_cell = f"{seq} {m['path_m']:.0f} m" if first else ""
            first = False
            loops = m.get("loops_accepted")
            planes = m.get("plane_nodes")
            lp = "" if v.startswith("KISS") or v == "odometry" else \
                f"{loops if 'loops' in v else '–'} / {planes if 'planes' in v else '–'}"
            lines.append(f"| {seq_cell} | {label} | {m['ate_m']:.3f} m ({m['ate_pct']:.3f} %) "
                         f"| {m['ate_aligned_m']:.3f} m ({m['ate_aligned_pct']:.3f} %) | {m['rpe10_pct']:.2f} % "
                         f"| {m['rpe100_pct']:.2f} % | {m['end_m']:.2f} m ({m['end_pct']:.2f} %) | {lp} |")
    return "\n".join(lines)


MULRAN_FILE = "mulran_2026-12-01.json"
#: the 20 s tables' sequences (the network streams; the paper world's have their own tables)
NETWORK_SEQUENCES = '"vehicle, loop 3.2 m" "vehicle, junctions 3.5 m" "drone, NIOSH 2.9 m" "handheld, loop 3.2 m"'


def render_mulran(results: Path) -> str:
    """minegeo's odometry and ``minegeo slam`` against the MulRan Riverside02 reference poses."""
    d = _load(MULRAN_FILE, results)
    commit = d.get("git", {}).get("commit")
    dirty = d.get("git", {}).get("dirty_files")
    threads = d.get("numba_threads")
    head = conditions(MULRAN_FILE, date=_date_from_name(MULRAN_FILE),
                      commit=(commit[:7] + ("+dirty" if dirty else "")) if commit else None,
                      threads=None if threads is None else f"{threads} (Numba)",
                      load=_fmt_load([(d.get("load_average_1_5_15") or [None])[0]]),
                      extra=f"{d['frames']} keyframes; trust bounds {d['trust_bounds']['translation_m']} m and "
                            f"{d['trust_bounds']['rotation_deg']}° per pair")
    lines = [head, "",
             "| variant (pairs) | translation median / p90 / p95 / max (m) | rotation median / p95 / max (°) "
             "| within bounds | path ratio | s per frame |",
             "|---|---|---|---:|---:|---:|"]

    def row(label, dist, within, pairs, ratio, s):
        t, r = dist["translation_m"], dist["rotation_deg"]
        return (f"| {label} ({pairs}) | {t['median']:.3f} / {t['p90']:.3f} / {t['p95']:.3f} / {t['max']:.2f} "
                f"| {r['median']:.2f} / {r['p95']:.2f} / {r['max']:.2f} | {within} | {ratio:.3f} | {s} |")

    for v in d["variants"]:
        p = v["params"]
        label = f"odometry, voxel {p['voxel_size_m']} m, gate {p['max_correspondence_distance_m']} m"
        lines.append(row(label, v["distribution"], v["within_trust"], v["pairs"], v["path_ratio"],
                         f"{v['time_per_frame_s']:.2f}"))
    c = d["cli"]
    lines.append(row(f"`{c['command'].replace('minegeo -q', 'minegeo')}`", c["distribution"], c["within_trust"],
                     d["variants"][0]["pairs"], c["path_ratio"],
                     f"{c['wall_s'] / c['summary']['frames']:.2f} (whole command)"))
    return "\n".join(lines)


#: the same benchmark script on the same machine, one run after the other: the code before issue 29's
#: first commit (5d8b3cd^ = f04d4e1, ``--code``) and the code of the current table (MULRAN_FILE)
MULRAN_BEFORE_FILES = ("mulran_2026-12-01_f04d4e1.json", MULRAN_FILE)


def render_mulran_before(results: Path) -> str:
    """MulRan: the odometry before issue 29 and now, measured by the same script on the same machine."""
    runs = [_load(f, results) for f in MULRAN_BEFORE_FILES]
    heads = []
    for f, d in zip(MULRAN_BEFORE_FILES, runs, strict=True):
        commit, dirty = d["git"]["commit"], d["git"]["dirty_files"]
        heads.append(conditions(f, date=_date_from_name(f), commit=commit[:7] + ("+dirty" if dirty else ""),
                                threads=f"{d['numba_threads']} (Numba)",
                                load=_fmt_load([d["load_average_1_5_15"][0]]),
                                extra=f"`{d['command']}`"))
    lines = [*heads, "", "| variant | commit | translation median / p95 (m) | rotation median / p95 (°) "
             "| within bounds | path ratio | s per frame |", "|---|---|---|---|---:|---:|---:|"]
    for i in range(len(runs[0]["variants"])):
        for d in runs:
            v = d["variants"][i]
            p, t, r = v["params"], v["distribution"]["translation_m"], v["distribution"]["rotation_deg"]
            lines.append(f"| odometry, voxel {p['voxel_size_m']} m, gate {p['max_correspondence_distance_m']} m "
                         f"| {d['git']['commit'][:7]} | {t['median']:.3f} / {t['p95']:.3f} "
                         f"| {r['median']:.2f} / {r['p95']:.2f} | {v['within_trust']} of {v['pairs']} "
                         f"| {v['path_ratio']:.3f} | {v['time_per_frame_s']:.3f} |")
    for d in (d for d in runs if d["cli"] is not None):
        c = d["cli"]
        t, r = c["distribution"]["translation_m"], c["distribution"]["rotation_deg"]
        lines.append(f"| `minegeo slam`, voxel 1.0 m, gate 6.0 m | {d['git']['commit'][:7]} "
                     f"| {t['median']:.3f} / {t['p95']:.3f} | {r['median']:.2f} / {r['p95']:.2f} "
                     f"| {c['within_trust']} of {d['variants'][0]['pairs']} | {c['path_ratio']:.3f} "
                     f"| {c['wall_s'] / c['summary']['frames']:.3f} (whole command) |")
    return "\n".join(lines)


DEMO_FILE = "demo_2026-12-01.json"


def render_demo(results: Path) -> str:
    """One ``minegeo demo`` run: each step's result against the synthetic truth, and its time."""
    d = _load(DEMO_FILE, results)
    meta = d["meta"]
    head = conditions(DEMO_FILE, date=meta.get("date"), commit=meta.get("commit"), threads=meta.get("threads"),
                      load=_fmt_load([_uptime_load(meta.get("uptime_before")),
                                      _uptime_load(meta.get("uptime_after"))]),
                      extra=f"`{meta['command']}`, seed {d['seed']}, Numba cache {meta['numba_cache']}")
    lines = [head, "", "| step | status | result against the truth | time s |", "|---|---|---|---:|"]
    for r in d["steps"]:
        lines.append(f"| {r['step']} | {r['status']} | {r['result'].replace('|', '/')} | {r['time_s']:.1f} |")
    lines += ["", f"Whole command: {meta['wall_s_time_v']:.1f} s wall, {meta['cpu_s_time_v']:.1f} s CPU (user + "
              f"system, `/usr/bin/time -v`), exit {meta['exit']}; {meta['note']}."]
    return "\n".join(lines)


FRESH_INSTALL_FILES = ("fresh_install_2026-12-01_idle.json", "fresh_install_2026-12-01_one-core-busy.json")


def render_fresh_install(results: Path) -> str:
    """The README's first command on a fresh clone and a new venv (``benchmarks/bench_fresh_install.py``):
    ``minegeo demo`` cold (empty Numba cache) on an idle machine and with one core kept busy, then warm."""
    lines = ["| condition | results file | commit | load before / after | demo cold: wall s (of which compiling) "
             "| demo warm: wall s | reports with figures |", "|---|---|---|---|---|---|---|"]
    for name in FRESH_INSTALL_FILES:
        if not (results / name).is_file():
            continue
        d = _load(name, results)
        m, st = d["meta"], d["steps"]
        cold, warm = st["demo cold"], st["demo warm"]
        busy = m["busy_cores"]
        cond = "idle" if not busy else f"{busy} of {m['cpus']} cores kept busy"
        load = f"{_uptime_load(m.get('uptime_before'))} / {_uptime_load(m.get('uptime_after'))}"
        figs = sum(1 for r in d["reports"] if r["figures"] >= 1 and r["figures_decoded"] == r["figures"])
        lines.append(f"| {cond} | `benchmarks/results/{name}` | {m['commit']} | {load} | {cold['wall_s']:.0f} "
                     f"({cold['compile_s']:.0f}) | {warm['wall_s']:.0f} | {figs} of {len(d['reports'])} |")
    m0 = _load(FRESH_INSTALL_FILES[0], results)["meta"]
    head = conditions(FRESH_INSTALL_FILES[0], date=m0.get("date"), commit=m0.get("commit"),
                      threads=f"Numba threads {m0.get('NUMBA_NUM_THREADS')}",
                      load=_fmt_load([_uptime_load(m0.get("uptime_before")), _uptime_load(m0.get("uptime_after"))]),
                      extra="each other row from its own file (below); `python benchmarks/bench_fresh_install.py`: a "
                            "clean clone, a new venv, `pip install .`, then `minegeo demo` on an empty Numba cache; "
                            "compile seconds of the main process (the demo also compiles in a second process)")
    return head + "\n\n" + "\n".join(lines)


def _md_tables(text: str, cells: bool = False) -> list[list]:
    """The Markdown tables of ``text``, each as its lines; with ``cells`` each line as its cells
    (stripped texts between the ``|``)."""
    out, cur = [], []
    for line in [*text.splitlines(), ""]:
        if line.startswith("|"):
            cur.append([c.strip() for c in line.strip().strip("|").split("|")] if cells else line)
        elif cur:
            out.append(cur)
            cur = []
    return out


def _json_conditions(stem: str, results: Path, extra: str = "") -> str:
    """The conditions line of a results file (its ``meta`` record, or its top level)."""
    d = _load(stem + ".json", results)
    meta = {**d, **d["meta"]} if isinstance(d.get("meta"), dict) else d
    date = meta.get("date") or meta.get("created_utc") or _date_from_name(stem)
    git = meta.get("git")
    commit = meta.get("commit") or (git.get("commit", "")[:7] if isinstance(git, dict) else git)
    th = meta.get("threads")
    if th is None and meta.get("numba_threads") is not None:
        th = f"{meta['numba_threads']} (Numba)"
    if isinstance(th, dict):
        mg = (th.get("minegeo") or {}).get("numba_get_num_threads", th.get("requested"))
        o3 = (th.get("open3d") or {}).get("open3d_get_max_threads")
        th = f"{mg} for minegeo (Numba)" + (f" and {o3} for Open3D" if o3 else "")
    loads = []
    for key in ("load_1min_start", "load_1min_end"):
        if isinstance(meta.get(key), int | float):
            loads.append(meta[key])
    for key in ("loadavg_start", "loadavg_end", "load_before", "load_after", "load_average_1_5_15", "load"):
        v = meta.get(key)
        if isinstance(v, list) and v:
            loads.append(v[0])
    for key in ("uptime_before", "uptime_after"):
        loads.append(_uptime_load(meta.get(key)))
    if isinstance(meta.get("load_avg"), list) and meta["load_avg"]:
        loads.append(meta["load_avg"][0])
    if isinstance(meta.get("machine"), str):  # bench_intersections: "... load average: a, b, c ..." per process
        loads += [float(m) for m in re.findall(r"load average: ([0-9.]+)", meta["machine"])]
    return conditions(stem + ".json", date=date, commit=commit or None, threads=str(th) if th else None,
                      load=_fmt_load(loads), extra=extra)


def md_copy(stem: str, tables: list[int] | None = None, extra: str = ""):
    """A renderer that copies a committed results ``.md`` (all of it but its title, headings made
    bold; or only the tables numbered ``tables``) under the conditions of its ``.json``."""

    def render(results: Path) -> str:
        text = (results / (stem + ".md")).read_text(encoding="utf-8")
        if tables is not None:
            found = _md_tables(text)
            body = "\n\n".join("\n".join(found[i]) for i in tables)
        else:
            lines = []
            for line in text.splitlines():
                if line.startswith("# "):
                    continue
                m = re.match(r"^#{2,6} (.*)$", line)
                lines.append(f"**{m.group(1)}**" if m else line)
            body = "\n".join(lines).strip("\n")
        return _json_conditions(stem, results, extra) + "\n\n" + body

    render.__doc__ = f"``benchmarks/results/{stem}.md`` ({'tables ' + str(tables) if tables else 'whole'})."
    return render


def stream_ate_rows(parts: list[tuple[str, str, str, tuple[str, ...]]], extra: str = ""):
    """A renderer of one table of ``bench_stream_ate.py`` rows gathered from several results files:
    ``parts`` = ``(row label, results stem, sequence, modes)``; ATE unaligned and aligned (m and % of the
    path), the conditions of every file used."""

    def render(results: Path) -> str:
        stems, lines = [], ["| stream | mode | path | ATE RMSE, unaligned | ATE RMSE, aligned | max error (unaligned) |",
                            "|---|---|---|---|---|---|"]
        for label, stem, seq, modes in parts:
            rows = {r["mode"]: r for r in _load(stem + ".json", results)["rows"] if r["sequence"] == seq}
            stems += [stem] if stem not in stems else []
            for m in modes:
                r = rows[m]
                lines.append(f"| {label} | {m} | {r['path_m']:.1f} m | {r['ate_unaligned_m']:.3f} m "
                             f"({r['ate_unaligned_pct']:.3f} %) | {r['ate_aligned_m']:.3f} m ({r['ate_aligned_pct']:.3f} %) "
                             f"| {r['ate_max_m']:.3f} m |")
        head = "\n".join(_json_conditions(st, results) for st in stems)
        return head + ("\n\n" + extra if extra else "") + "\n\n" + "\n".join(lines)

    render.__doc__ = "Rows of " + ", ".join(sorted({f"``{p[1]}``" for p in parts})) + "."
    return render


def md_columns(stem: str, columns: tuple[str, ...], table: int = 0):
    """A renderer of the named ``columns`` of table ``table`` of a committed results ``.md`` (a
    percentage written ``7.1%`` there is ``7.1 %`` here), under the conditions of its ``.json``."""

    def render(results: Path) -> str:
        rows = _md_tables((results / (stem + ".md")).read_text(encoding="utf-8"), cells=True)[table]
        idx = [rows[0].index(c) for c in columns]
        out = ["| " + " | ".join(columns) + " |", "|" + "|".join(["---"] * len(columns)) + "|"]
        for c in rows[2:]:
            out.append("| " + " | ".join(re.sub(r"(\d)%$", r"\1 %", c[j]) for j in idx) + " |")
        return _json_conditions(stem, results) + "\n\n" + "\n".join(out)

    render.__doc__ = f"``benchmarks/results/{stem}.md`` table {table}, columns {', '.join(columns)}."
    return render


def _bench_module(name: str):
    """A benchmark script of this folder as a module (its table renderer)."""
    import importlib

    here = str(Path(__file__).resolve().parent)
    if here not in sys.path:
        sys.path.insert(0, here)
    return importlib.import_module(name)


def markdown_table(bench: str, stem: str):
    """``<bench>.py --markdown`` (a benchmark's own table) of a results file under its conditions."""

    def render(results: Path) -> str:
        body = _bench_module(bench).markdown(results / (stem + ".json")).splitlines()
        body = [ln for ln in body if not ln.startswith("<!-- generated by")]
        return (_json_conditions(stem, results, f"`python benchmarks/{bench}.py --markdown "
                                                f"benchmarks/results/{stem}.json`") + "\n\n" + "\n".join(body).strip("\n"))

    render.__doc__ = f"``{bench}.py --markdown benchmarks/results/{stem}.json``."
    return render


def control_table(stem: str):
    """``bench_control.py --markdown`` of a control results file under its conditions."""
    return markdown_table("bench_control", stem)


def records_table(stem: str):
    """``bench_control_records.py --markdown`` of a results file under its conditions."""
    return markdown_table("bench_control_records", stem)


def first_use_table(*stems: str):
    """``bench_first_use.py --markdown`` of first-use results files side by side, under the first one's
    conditions (each file's commit, date and threads are in the table's first line)."""

    def render(results: Path) -> str:
        docs = [_load(st + ".json", results) for st in stems]
        d0 = docs[0]
        head = conditions(stems[0] + ".json", date=d0.get("date"), commit=d0.get("commit"),
                          threads=f"NUMBA_NUM_THREADS={d0.get('numba_num_threads')}",
                          load="per verb in the table's load columns",
                          extra="`python benchmarks/bench_first_use.py --markdown "
                                + " ".join(f"benchmarks/results/{st}.json" for st in stems) + "`")
        return head + "\n\n" + _bench_module("bench_first_use").markdown(docs)

    render.__doc__ = f"``bench_first_use.py --markdown`` of {', '.join(stems)}."
    return render


#: the columns of bench_intersections.py's tables that docs/intersections.md shows: the whole Table I
#: form, and the short form of the 2026-11-29 NIOSH runs (with failed frames and status)
INTERSECTION_FULL = ("Method", "MAE (m)", "RMSE (m)", "max (m)", "REP-1 (%)", "REP-2 (%)", "REP-3 (%)", "REP-4 (%)",
                     "REP-5 (%)", "precision", "recall", "time (s)")
INTERSECTION_SHORT = ("Method", "MAE (m)", "RMSE (m)", "max (m)", "REP-5 (%)", "precision", "recall", "failed frames",
                      "status")


#: bench_stream_ate's --modes of the re-measured tables (the oracle's rows in the same run)
MODES4 = 'raw deskewed "deskewed + IMU" "deskewed by the truth"'

#: the oracle table's streams: (row label, sequence, results stem of the deskewed row, of the oracle's)
ORACLE_STREAMS = (
    *((f"{label}, 20 s", seq, "stream_ate_2026-12-01b_local_map", "stream_ate_2026-12-01b_local_map")
      for label, seq in (("vehicle, loop", "vehicle, loop 3.2 m"), ("vehicle, junctions", "vehicle, junctions 3.5 m"),
                         ("drone, NIOSH", "drone, NIOSH 2.9 m"), ("handheld, loop", "handheld, loop 3.2 m"))),
    *((f"drone, NIOSH, 60 s, seed {k}", "drone, NIOSH 2.9 m", "stream_ate_2026-12-01b_drone60" + ("" if k == 1 else f"_seed{k}"),
       "stream_ate_2026-12-01b_drone60" + ("" if k == 1 else f"_seed{k}")) for k in (1, 2, 3)),
    *((f"vehicle, paper {n}", f"vehicle, paper {n}", f"stream_ate_2026-12-01b_paper_{n}",
       f"stream_ate_2026-12-01b_paper_{n}") for n in ("ring", "straight", "ramp")),
)

RENDERERS = {
    "registration_quick": render_registration_quick,
    "posegraph": render_posegraph,
    "batch": render_batch,
    "prepare_scaling": render_prepare_scaling,
    "georef_scaling": render_georef_scaling,
    "georef_scaling_las": render_georef_scaling_las,
    "slam_ablation": render_slam_ablation,
    "mulran": render_mulran,
    "mulran_before": render_mulran_before,
    "demo": render_demo,
    "demo_slam_seeds": md_copy("demo_slam_seeds_2026-12-01", [0], extra=(
        "`git worktree add /tmp/minegeo-6db6ec7 6db6ec7; python benchmarks/bench_demo_slam_seeds.py --seeds $(seq 1 30) "
        "--work /tmp/demo_seeds --trees 6db6ec7=/tmp/minegeo-6db6ec7 HEAD=. --json … --md …`")),
    "covariance_frames_demo_seeds": md_copy("covariance_frames_2026-12-01_demo_seeds", [0, 1], extra=(
        "`python benchmarks/bench_covariance_frames.py --demo-seeds $(seq 1 30) --odometry frame --values 9 1 "
        "--json … --md …`")),
    "fresh_install": render_fresh_install,
    "localization_study": md_copy("study_2026-11-25", extra="`python benchmarks/bench_study.py --seed 31 --n 20`"),
    "like_for_like_same": md_copy("like_for_like_2026-11-25", [0]),
    "like_for_like_best": md_copy("like_for_like_2026-11-25", [1]),
    "like_for_like_cold": md_copy("like_for_like_2026-11-25", [3]),
    "default_profile": md_copy("default_profile_2026-11-25"),
    "localization_paper": md_copy("localization_paper_passes2_levelled_2026-11-23b"),
    "gravity": md_copy("gravity_2026-11-25"),
    "gicp": md_copy("gicp_2026-11-29_idle50",
                    extra="`python benchmarks/bench_gicp.py --threads 1 2 --repeats 7` (50 ms idle before each call)"),
    "gicp_back_to_back": md_copy("gicp_2026-11-29_idle0", [1],
                                 extra="the same with `--idle-ms 0` (calls back to back), 2 threads"),
    "uncertainty_study": md_copy("uncertainty_study_2026-11-25", [0],
                                 extra="`python benchmarks/bench_uncertainty_study.py run --seeds 21,22 --n 6`"),
    "kernels_search": md_copy("kernels", [0], extra="`python benchmarks/bench_kernels.py`, median of 3, ms"),
    "realtime_local_map": md_copy("realtime_2026-12-01_local_map", [0, 1],
                                  extra="2 threads on both sides; per frame the minimum of 2 alternating runs; "
                                        "`NUMBA_NUM_THREADS=2 python benchmarks/bench_realtime.py --threads 2 "
                                        "--duration-s 20 --repeats 2 --odometry submap`"),
    "realtime_idle": md_copy("realtime_2026-12-01_idle", [0, 1],
                             extra="2 threads on both sides (minegeo: Numba omp layer, OMP_WAIT_POLICY PASSIVE; "
                                   "KISS-ICP max_num_threads 2); per frame the minimum of 2 alternating runs; "
                                   "`NUMBA_NUM_THREADS=2 python benchmarks/bench_realtime.py --threads 2 --repeats 2 "
                                   "--odometry frame`"),
    "realtime_loaded": md_copy("realtime_2026-12-01_loaded", [0, 1],
                               extra="2 threads on both sides, as above, with 12 busy shell loops on the 2 cores "
                                     "(started a minute before); `NUMBA_NUM_THREADS=2 python benchmarks/bench_realtime.py "
                                     "--threads 2 --duration-s 20 --repeats 2 --odometry submap`"),
    "realtime_t1": md_copy("realtime_2026-12-01_loaded_t1", [0, 1],
                           extra="1 thread on both sides, the same 12 busy loops; `NUMBA_NUM_THREADS=1 python "
                                 "benchmarks/bench_realtime.py --threads 1 --duration-s 20 --repeats 2 --odometry submap`"),
    "slam_deskew": md_copy("deskew_2026-11-30b", [0], extra="`python benchmarks/bench_deskew.py --duration-s 20`"),
    "start_velocity": md_copy("start_velocity_2026-12-01", [0],
                              extra="`NUMBA_NUM_THREADS=1 python benchmarks/bench_start_velocity.py --seeds 1-10`; "
                                    "median (min-max) over the seeds, m/s"),
    "slam_imu": md_copy("slam_imu_2026-12-01", [0], extra="`python benchmarks/bench_slam_imu.py --duration-s 20`"),
    "control_driftauto": control_table("control_2026-11-29_driftauto_lr"),
    "control_driftauto_weakbias": control_table("control_2026-11-29_driftauto_lr_weakbias"),
    "control_driftauto_lownoise": control_table("control_2026-11-29_driftauto_lownoise"),
    "control_similarity": control_table("control_2026-11-30_similarity"),
    "control_slam_model_noise": control_table("control_2026-11-30_slam_model_noise_only"),
    "control_slam_model_bias": control_table("control_2026-11-30_slam_model_bias"),
    "control_records_vehicle": records_table("control_records_2026-12-01_vehicle"),
    "control_records_handheld": records_table("control_records_2026-12-01_handheld"),
    "control_records_vehicle_refit": records_table("control_records_2026-12-01_vehicle_refit"),
    "control_records_handheld_refit": records_table("control_records_2026-12-01_handheld_refit"),
    "first_use_before_after": first_use_table("first_use_2026-11-29_before", "first_use_2026-11-29_after_head"),
    "first_use_after2": first_use_table("first_use_2026-11-29_after2_base", "first_use_2026-11-29_after2"),
    **{f"intersections_{k}": md_columns(f"intersections_{stem}", cols)
       for k, stem, cols in (("synthetic", "2026-11-28", INTERSECTION_FULL),
                             ("niosh_imu", "2026-11-29_niosh_imu", INTERSECTION_SHORT),
                             ("niosh_noimu", "2026-11-29_niosh_noimu", INTERSECTION_SHORT),
                             ("niosh_08_imu", "2026-11-29_niosh_0.8km_imu", INTERSECTION_SHORT),
                             ("niosh_08_noimu", "2026-11-29_niosh_0.8km_noimu", INTERSECTION_SHORT),
                             ("niosh_before", "2026-11-28_niosh", INTERSECTION_FULL),
                             ("corridor", "2026-11-28_corridor", INTERSECTION_FULL))},
    "stream_ate_local_map": md_copy("stream_ate_2026-12-01b_local_map", [0],
                                    extra="`python benchmarks/bench_stream_ate.py --duration-s 20 --sequences "
                                          f"{NETWORK_SEQUENCES} --modes {MODES4} "
                                          "--kiss-from benchmarks/results/stream_ate_2026-11-29.json`"),
    "stream_ate_drone60": md_copy("stream_ate_2026-12-01b_drone60", [0],
                                  extra="`python benchmarks/bench_stream_ate.py --duration-s 60 --sequences "
                                        f"\"drone, NIOSH 2.9 m\" --modes {MODES4} "
                                        "--kiss-from benchmarks/results/stream_ate_2026-11-29_drone60.json`"),
    **{f"stream_ate_drone60_seed{k}": md_copy(f"stream_ate_2026-12-01b_drone60_seed{k}", [0],
                                              extra=f"`python benchmarks/bench_stream_ate.py --duration-s 60 --seed {k} "
                                                    f"--sequences \"drone, NIOSH 2.9 m\" --modes {MODES4} --kiss-from "
                                                    f"benchmarks/results/stream_ate_2026-11-30b_drone60_seed{k}.json`")
       for k in (2, 3)},
    **{f"stream_ate_paper_{n}": md_copy(f"stream_ate_2026-12-01b_paper_{n}", [0],
                                        extra=f"`python benchmarks/bench_stream_ate.py --duration-s {d} --sequences "
                                              f"\"vehicle, paper {n}\" --modes {MODES4} --kiss-from "
                                              f"benchmarks/results/stream_ate_2026-11-30b_paper_{n}.json`")
       for n, d in (("ring", "41.8"), ("straight", "172"), ("ramp", "88.7"))},
    "stream_ate_oracle": stream_ate_rows(
        [(label, stem, seq, (mode,))
         for label, seq, ours, truth in ORACLE_STREAMS
         for stem, mode in ((ours, "deskewed"), (truth, "deskewed by the truth"))],
        extra="the deskewed and oracle rows of the files of the tables above (the same run, the same frames)"),
    "stream_ate_drone20_seeds": stream_ate_rows(
        [(f"drone, NIOSH, 20 s, seed {k}", f"stream_ate_2026-12-01b_drone20_seed{k}", "drone, NIOSH 2.9 m",
          ("raw", "deskewed", "deskewed + IMU", "deskewed by the truth",
           "KISS-ICP (its deskewing), voxel 1.0 m as shipped", "KISS-ICP (its deskewing), voxel 0.25 m for 3 m drifts"))
         for k in (2, 3, 4, 5)],
        extra="`python benchmarks/bench_stream_ate.py --duration-s 20 --seed K --sequences \"drone, NIOSH 2.9 m\" "
              f"--modes {MODES4} --kiss-from benchmarks/results/stream_ate_2026-12-01_drone20_seedK.json` "
              "for K = 2, 3, 4, 5 (KISS-ICP run on the same frames in that file's run)"),
    "inertial_edge_noise": md_copy("inertial_edge_noise_2026-12-01", [0],
                                   extra="`NUMBA_NUM_THREADS=1 python benchmarks/bench_inertial_edge_noise.py --work W`"),
    **{f"imu_seeds_{k}": md_copy(f"imu_seeds_2026-12-01_{k}", [0],
                                  extra=f"`NUMBA_NUM_THREADS=1 python benchmarks/bench_imu_seeds.py --sequence \"{seq}\" "
                                        "--seeds 1-10 --work W`")
       for k, seq in (("vehicle", "vehicle, loop 3.2 m"), ("handheld", "handheld, loop 3.2 m"),
                      ("drone", "drone, NIOSH 2.9 m"))},
    "stream_ate": md_copy("stream_ate_2026-12-01b", [0],
                          extra=f"`python benchmarks/bench_stream_ate.py --duration-s 20 --sequences {NETWORK_SEQUENCES} "
                                "--odometry frame --kiss-from benchmarks/results/stream_ate_2026-11-29.json`"),
    "mast_coverage": md_copy("mast/mast_benchmark", [2]),
    "mast_partial": md_copy("mast/mast_benchmark", [3]),
    "mast_beacon_survey": md_copy("mast/mast_benchmark", [4]),
    "mast_table2_summary": md_copy("mast/mast_benchmark", [1]),
    "mast_table2_rows": md_copy("mast/mast_benchmark", [0]),
}


# -- pages ---------------------------------------------------------------------------------------

def pages(root: Path = ROOT) -> list[Path]:
    """README.md and every page of docs/."""
    return [root / "README.md"] + sorted((root / "docs").glob("*.md"))


def blocks(text: str) -> list[tuple[str, int, int]]:
    """``(name, first, last)`` line indices (0-based, the marker lines) of every figures block."""
    out, open_ = [], None
    for i, line in enumerate(text.splitlines()):
        b, e = BEGIN.match(line), END.match(line)
        if b:
            if open_ is not None:
                raise ValueError(f"line {i + 1}: figures block opened inside another (line {open_[1] + 1})")
            open_ = (b["name"], i)
        elif e:
            if open_ is None:
                raise ValueError(f"line {i + 1}: <!-- /figures --> without an opening marker")
            out.append((open_[0], open_[1], i))
            open_ = None
        elif "<!-- figures" in line or "<!-- /figures" in line:
            raise ValueError(f"line {i + 1}: malformed figures marker: {line.strip()}")
    if open_ is not None:
        raise ValueError(f"line {open_[1] + 1}: figures block '{open_[0]}' never closed")
    return out


def render_page(text: str, results: Path = RESULTS) -> str:
    """``text`` with every figures block rendered from its results file."""
    lines = text.splitlines()
    for name, first, last in reversed(blocks(text)):
        if name not in RENDERERS:
            raise ValueError(f"line {first + 1}: no renderer for figures '{name}' (known: {sorted(RENDERERS)})")
        lines[first + 1:last] = [""] + RENDERERS[name](results).splitlines() + [""]
    return "\n".join(lines) + ("\n" if text.endswith("\n") else "")


def check(root: Path = ROOT, results: Path = RESULTS) -> list[str]:
    """A unified diff per page whose figures blocks disagree with their results files."""
    diffs = []
    for page in pages(root):
        text = page.read_text(encoding="utf-8")
        try:
            want = render_page(text, results)
        except ValueError as exc:
            diffs.append(f"{page.relative_to(root)}: {exc}")
            continue
        if want != text:
            rel = str(page.relative_to(root))
            diffs.append("".join(difflib.unified_diff(text.splitlines(True), want.splitlines(True),
                                                      f"{rel} (page)", f"{rel} (from results)")))
    return diffs


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    mode = ap.add_mutually_exclusive_group(required=True)
    mode.add_argument("--check", action="store_true", help="exit 1 when a page disagrees with its results")
    mode.add_argument("--write", action="store_true", help="rewrite every figures block from its results")
    args = ap.parse_args(argv)
    if args.check:
        diffs = check()
        for d in diffs:
            print(d)
        print(f"{len(diffs)} page(s) disagree with their results files" if diffs else "all figures agree")
        return 1 if diffs else 0
    for page in pages():
        text = page.read_text(encoding="utf-8")
        new = render_page(text)
        if new != text:
            page.write_text(new, encoding="utf-8")
            print(f"rewrote {page.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
