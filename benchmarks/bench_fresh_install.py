"""The README's first command on a fresh install: a clean clone, a new venv, ``pip install .``, then
``minegeo demo`` cold (empty Numba cache), again warm, and every ``report.html`` of the demo opened
in headless Chromium (figures decoded).

Usage (from the root of a checkout; the clone is made from its HEAD)::

    python benchmarks/bench_fresh_install.py --label idle
    python benchmarks/bench_fresh_install.py --label one-core-busy --busy-cores 1

``--busy-cores N`` keeps N processes spinning on the CPU during the cold demo (the "one core busy
elsewhere" condition on a 2-core machine). The venv has no access to the system's site-packages,
so it holds exactly what ``pip install .`` installs (PyPI must be reachable for the install; the
demo itself downloads nothing). Results: ``benchmarks/results/fresh_install_<date>_<label>.json``
and ``.md`` with the commit, the load before and after, the CPU count and ``NUMBA_NUM_THREADS``.

The browser check uses this interpreter's Playwright and Debian's ``/usr/bin/chromium`` (as the
report tests do); it records per report the number of figures and whether each decoded.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
CHROMIUM = Path(os.environ.get("MINEGEO_CHROMIUM", "/usr/bin/chromium"))


def _uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def _spin(stop_at: float) -> None:  # pragma: no cover - a busy core
    x = 0
    while time.time() < stop_at:
        x += 1


def _run(cmd: list[str], cwd: Path, env: dict) -> dict:
    t0 = time.perf_counter()
    r0 = os.times()
    p = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    r1 = os.times()
    return {"cmd": " ".join(cmd), "exit": p.returncode, "wall_s": time.perf_counter() - t0,
            "cpu_s": (r1.children_user - r0.children_user) + (r1.children_system - r0.children_system),
            "stdout_tail": p.stdout[-3000:], "stderr_tail": p.stderr[-3000:]}


def _reports_in_browser(folder: Path) -> list[dict]:
    from playwright.sync_api import sync_playwright

    out = []
    with sync_playwright() as pw:
        br = pw.chromium.launch(executable_path=str(CHROMIUM), args=["--no-sandbox", "--disable-gpu"])
        page = br.new_page()
        for rep in sorted(folder.rglob("report.html")):
            page.goto(rep.resolve().as_uri())
            info = page.evaluate("""() => ({
                imgs: Array.from(document.images).map(i => i.complete && i.naturalWidth > 0),
                status: (document.getElementById('status') || {}).textContent || null})""")
            out.append({"report": str(rep.relative_to(folder)), "figures": len(info["imgs"]),
                        "figures_decoded": sum(info["imgs"]), "status": (info["status"] or "").strip()[:120]})
        br.close()
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--label", required=True)
    ap.add_argument("--busy-cores", type=int, default=0)
    ap.add_argument("--keep", type=Path, default=None, help="build in this folder and keep it")
    a = ap.parse_args()

    work = a.keep or Path(tempfile.mkdtemp(prefix="minegeo-fresh-"))
    work.mkdir(parents=True, exist_ok=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    rec: dict = {"meta": {"date": time.strftime("%Y-%m-%d %H:%M"), "commit": commit, "label": a.label,
                          "cpus": os.cpu_count(), "busy_cores": a.busy_cores,
                          "NUMBA_NUM_THREADS": os.environ.get("NUMBA_NUM_THREADS", "(unset: all cores)"),
                          "uptime_before": _uptime()}, "steps": {}}
    clone = work / "minegeo"
    if clone.exists():
        shutil.rmtree(clone)
    subprocess.run(["git", "clone", "-q", str(ROOT), str(clone)], check=True)
    venv = work / "venv"
    if not (venv / "bin" / "python").exists():
        subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("NUMBA_CACHE_DIR", "PYTHONPATH"))}
    env["PATH"] = f"{venv / 'bin'}:{env['PATH']}"
    env["PIP_DISABLE_PIP_VERSION_CHECK"] = "1"
    user = clone.parent / "user"  # where the user stands: outside the clone
    if user.exists():
        shutil.rmtree(user)
    user.mkdir()
    rec["steps"]["pip install ."] = _run([str(venv / "bin" / "pip"), "install", "-q", "."], clone, env)
    if rec["steps"]["pip install ."]["exit"] != 0:
        print(rec["steps"]["pip install ."]["stderr_tail"])
        return 1
    # the installed (non-editable) package has its own, empty Numba cache next to its modules
    site = subprocess.run([str(venv / "bin" / "python"), "-c", "import minegeo, pathlib; "
                           "print(pathlib.Path(minegeo.__file__).parent)"], capture_output=True, text=True,
                          env=env, cwd=user).stdout.strip()
    for c in Path(site).rglob("__pycache__"):
        for f in c.glob("*.nb[ic]"):
            f.unlink()
    procs = []
    if a.busy_cores:
        stop = time.time() + 3600
        procs = [mp.Process(target=_spin, args=(stop,), daemon=True) for _ in range(a.busy_cores)]
        for p in procs:
            p.start()
    demo = [str(venv / "bin" / "minegeo"), "demo", "--out", "minegeo-demo"]
    rec["steps"]["demo cold"] = _run(demo, user, env)
    rec["meta"]["uptime_after_cold"] = _uptime()
    for p in procs:
        p.terminate()
    res = json.loads((user / "minegeo-demo" / "result.json").read_text())
    rec["steps"]["demo cold"]["compile_s"] = res["timings_s"].get("compile_s")
    rec["steps"]["demo cold"]["background_compilation"] = res.get("background_compilation")
    rec["steps"]["demo warm"] = _run(demo + ["--force"], user, env)
    res = json.loads((user / "minegeo-demo" / "result.json").read_text())
    rec["steps"]["demo warm"]["compile_s"] = res["timings_s"].get("compile_s")
    rec["meta"]["uptime_after"] = _uptime()
    rec["reports"] = _reports_in_browser(user / "minegeo-demo")
    RESULTS.mkdir(parents=True, exist_ok=True)
    stem = RESULTS / f"fresh_install_{time.strftime('%Y-%m-%d')}_{a.label}"
    stem.with_suffix(".json").write_text(json.dumps(rec, indent=1) + "\n")
    lines = [f"# Fresh install ({a.label}), {rec['meta']['date']}, commit {commit}", "",
             f"{rec['meta']['cpus']} CPUs, {a.busy_cores} kept busy by a spinning process during the cold demo; "
             f"NUMBA_NUM_THREADS {rec['meta']['NUMBA_NUM_THREADS']}.",
             f"Load before: `{rec['meta']['uptime_before']}`; after: `{rec['meta']['uptime_after']}`.", "",
             "| step | exit | wall s | of which compiling s | CPU s |", "|---|---|---|---|---|"]
    for k, s in rec["steps"].items():
        comp = s.get("compile_s")
        lines.append(f"| {k} | {s['exit']} | {s['wall_s']:.1f} | {'' if comp is None else f'{comp:.1f}'} | "
                     f"{s['cpu_s']:.1f} |")
    lines += ["", "| report | figures | decoded | status |", "|---|---|---|---|"]
    lines += [f"| {r['report']} | {r['figures']} | {r['figures_decoded']} | {r['status']} |" for r in rec["reports"]]
    stem.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0 if all(s["exit"] == 0 for s in rec["steps"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
