"""Every documented command on a fresh install: a clean clone, a new venv with the README's first
command (``pip install . && minegeo demo --out minegeo-demo``), an empty Numba cache, then every
```` ```bash ```` block of README.md and docs/*.md, timed, its exit status checked against the page,
its compile seconds taken apart, and every ``report.html`` it wrote opened in headless Chromium.

Usage (from the root of a checkout; the clone is made from its HEAD)::

    NUMBA_NUM_THREADS=1 python benchmarks/bench_docs_fresh.py --keep /work/fresh2   # ~20-30 min
    python benchmarks/bench_docs_fresh.py --keep /tmp/f --pages docs/mast.md --no-demo  # a quick try

How it runs, and what it reuses:

* ``git clone`` of this checkout's HEAD into ``DIR/minegeo`` (removed and made again each run);
  ``DIR/venv`` is reused when it exists and the ``minegeo`` it holds required exactly the core
  dependencies of the clone's ``pyproject.toml`` (else a new venv is made). The README's first
  command then runs verbatim, its two parts timed apart, with the clone's root as the current
  folder: ``pip install .`` (re-installs the package from the new clone) and the cold demo.
* ``NUMBA_CACHE_DIR`` is a new, empty folder for the whole run (Numba looks there before the
  package's ``__pycache__``), so each kernel is compiled by the first command that needs it: the
  demo first, then the docs blocks in page order.
* The pages' blocks are found and run as ``tests/docs/test_docs_commands.py`` does (its
  ``parse_page``, ``output_mismatch`` and hang limit are imported from the clone's copy, not
  copied): per page a fresh folder standing for the root of a clone with ``examples/`` of the
  clone and ``../shared/data``; ``MINEGEO_SHARED_DATA`` is the shared data folder; each block with
  ``bash -e -o pipefail``; after a block that does not exit as documented the page's later blocks
  are not run (they build on it). No ``PYTHONPATH``: the commands import the venv's package.
* Per block: wall seconds, CPU seconds of the children (user + system, ``os.times``), the compile
  seconds the verbs printed (``... s of this run was one-time Numba compilation``, localize's and
  the demo's own wording) and the ``timings_s.compile_s`` of every JSON file the block wrote or
  rewrote, whether the page's stated output (``<!-- docs-test: output -->``) was printed, and the
  ``report.html`` files it wrote. Those reports are opened at the end in headless Chromium
  (Playwright of this interpreter, Debian's ``/usr/bin/chromium``, as
  ``benchmarks/bench_fresh_install.py``): figures (``<img>``) and how many decoded.
* A block that fails because an optional extra is missing (minegeo's ``pip install
  'minegeo[X]'`` message, or ``No module named`` a package of an extra) is listed with what is
  missing. Nothing is installed silently: only when the page's own text tells the user to
  ``pip install 'minegeo[X]'`` is that command run (in the venv, after every page ran on the bare
  install), the page run again from its start in a new folder, and the extra's packages removed
  again afterwards so the kept venv stays what ``pip install .`` makes.

Writes ``benchmarks/results/docs_fresh_<date>[_<label>].json`` and ``.md`` (commit, date, load
before/after, threads, per block: page, line, commands, exit expected/got, wall s, CPU s, compile s,
reports with figures).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
SHARED = Path(os.environ.get("MINEGEO_SHARED_DATA", "/work/shared/data")).resolve()

#: the packages of each optional extra as Python imports them (for ``No module named 'X'``)
EXTRA_OF_MODULE = {"rosbags": "bag", "dask": "dask", "distributed": "dask", "laspy": "las", "lazrs": "las",
                   "pye57": "e57", "ezdxf": "dxf"}
INSTALL_EXTRA = re.compile(r"pip install '?minegeo\[(?P<extra>[\w,-]+)\]'?")
NO_MODULE = re.compile(r"No module named '(?P<mod>[\w.]+)'")
#: the compile seconds as the verbs print them (cli/_common.py, report/demo_report.py)
COMPILE_PRINTED = [re.compile(r"(\d+(?:\.\d+)?) s of this run was one-time Numba compilation"),
                   re.compile(r"(\d+(?:\.\d+)?) s of it one-time Numba compilation"),
                   re.compile(r"\((\d+(?:\.\d+)?) s compiling Numba kernels"),
                   re.compile(r"of which (\d+(?:\.\d+)?) s compiling numerical kernels")]


def _load(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def _uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def _git(clone: Path, *args: str) -> str:
    return subprocess.run(["git", *args], cwd=clone, capture_output=True, text=True).stdout.strip()


def _core_deps_of_clone(clone: Path) -> list[str]:
    try:
        import tomllib
    except ImportError:  # Python 3.10
        import tomli as tomllib
    return sorted(tomllib.loads((clone / "pyproject.toml").read_text())["project"]["dependencies"])


def _core_deps_in_venv(py: Path) -> list[str] | None:
    code = ("import importlib.metadata as m, json\n"
            "try:\n d = m.distribution('minegeo')\nexcept m.PackageNotFoundError:\n print('null')\n"
            "else:\n print(json.dumps(sorted(r for r in (d.requires or []) if 'extra ==' not in r)))")
    out = subprocess.run([str(py), "-c", code], capture_output=True, text=True).stdout.strip()
    return json.loads(out) if out else None


def _freeze(venv: Path, env: dict) -> list[str]:
    out = subprocess.run([str(venv / "bin" / "pip"), "freeze"], capture_output=True, text=True, env=env).stdout
    return sorted(ln for ln in out.splitlines() if ln and not ln.lower().startswith("minegeo"))


def _snapshot(folder: Path) -> dict[str, tuple[int, int]]:
    snap = {}
    for p in folder.rglob("*"):
        try:
            if p.is_file():
                st = p.stat()
                snap[str(p)] = (st.st_mtime_ns, st.st_size)
        except OSError:
            pass
    return snap


def _written(before: dict, after: dict) -> list[Path]:
    return sorted(Path(p) for p, v in after.items() if before.get(p) != v)


def _outermost(paths: list[str]) -> list[str]:
    """The JSON files not inside the folder of another ``result.json`` among them (a demo's steps write
    their own result.json in its folder; the demo's compile seconds already hold theirs)."""
    runs = [Path(p).parent for p in paths if Path(p).name == "result.json"]
    return [p for p in paths if not any(r != Path(p).parent and r in Path(p).parents for r in runs)]


def _compile_of_json(files: list[Path]) -> dict[str, float]:
    out = {}
    for f in files:
        if f.suffix != ".json":
            continue
        try:
            doc = json.loads(f.read_text())
            c = doc.get("timings_s", {}).get("compile_s") if isinstance(doc, dict) else None
        except (OSError, ValueError, AttributeError):
            continue
        if isinstance(c, (int, float)):
            out[str(f)] = float(c)
    return out


def _missing_extra(output: str) -> list[str]:
    extras = {m["extra"] for m in INSTALL_EXTRA.finditer(output)}
    for m in NO_MODULE.finditer(output):
        top = m["mod"].split(".")[0]
        if top in EXTRA_OF_MODULE:
            extras.add(EXTRA_OF_MODULE[top])
    return sorted(extras)


def _run_block(cmd: str, cwd: Path, env: dict, timeout: float) -> dict:
    before = _snapshot(cwd)
    r0, t0 = os.times(), time.perf_counter()
    try:
        p = subprocess.run(["bash", "-e", "-o", "pipefail", "-c", cmd], cwd=cwd, env=env,
                           stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                           text=True, timeout=timeout)
        code, out = p.returncode, p.stdout
    except subprocess.TimeoutExpired as exc:
        code = "timeout"
        out = exc.stdout.decode() if isinstance(exc.stdout, bytes) else (exc.stdout or "")
    wall, r1 = time.perf_counter() - t0, os.times()
    written = _written(before, _snapshot(cwd))
    printed = [float(m.group(1)) for line in out.splitlines() for rx in COMPILE_PRINTED
               for m in [rx.search(line)] if m]
    by_json = _compile_of_json(written)
    return {"exit": code, "wall_s": round(wall, 2),
            "cpu_s": round((r1.children_user - r0.children_user) + (r1.children_system - r0.children_system), 2),
            "compile_printed_s": round(sum(printed), 2) if printed else None,
            "compile_result_json_s": round(sum(by_json[k] for k in _outermost(list(by_json))), 2) if by_json
            else None,
            "compile_by_json": {str(Path(k).relative_to(cwd)): v for k, v in by_json.items()},
            "reports": [str(p.relative_to(cwd)) for p in written if p.name == "report.html"],
            "output": out}


def _reports_in_browser(files: list[Path], chromium: Path) -> list[dict]:
    """Each report opened from its file URL (as bench_fresh_install.py): figures and how many decoded."""
    from playwright.sync_api import sync_playwright

    out = []
    with sync_playwright() as pw:
        br = pw.chromium.launch(executable_path=str(chromium), args=["--no-sandbox", "--disable-gpu"])
        page = br.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        for rep in files:
            errors.clear()
            page.goto(rep.resolve().as_uri())
            info = page.evaluate("""() => ({
                imgs: Array.from(document.images).map(i => i.complete && i.naturalWidth > 0),
                status: (document.getElementById('status') || {}).textContent || null})""")
            out.append({"figures": len(info["imgs"]), "figures_decoded": sum(info["imgs"]),
                        "status": " ".join((info["status"] or "").split())[:140], "page_errors": list(errors)})
        br.close()
    return out


def _sandbox(base: Path, clone: Path, env0: dict) -> tuple[Path, dict]:
    """A fresh folder standing for the root of a clone, next to ``shared/data`` (as the docs test)."""
    user = base / "clone"
    user.mkdir(parents=True)
    (user / "examples").symlink_to(clone / "examples", target_is_directory=True)
    (base / "shared").mkdir()
    (base / "shared" / "data").symlink_to(SHARED, target_is_directory=True)
    env = dict(env0)
    env["MINEGEO_SHARED_DATA"] = str(SHARED)
    return user, env


def _run_page(page: Path, clone: Path, base: Path, env0: dict, docs_test, attempt: str) -> list[dict]:
    rel = str(page.relative_to(clone))
    blocks = docs_test.parse_page(page.read_text(encoding="utf-8"))
    if not blocks:
        return []
    user, env = _sandbox(base, clone, env0)
    rows, stop = [], None
    for b in blocks:
        row = {"page": rel, "line": b.line, "attempt": attempt, "commands": b.text, "exit_expected": b.exit_status,
               "folder": str(user)}
        if stop is not None:
            row.update({"exit": None, "not_run": f"the block of line {stop} did not exit as documented"})
            rows.append(row)
            continue
        print(f"[{time.strftime('%H:%M:%S')}] {rel}:{b.line} ({attempt})", file=sys.stderr, flush=True)
        r = _run_block(b.text, user, env, docs_test.HANG_TIMEOUT_S)
        out = r.pop("output")
        row.update(r)
        row["as_documented"] = r["exit"] == b.exit_status
        if b.expected_output:
            miss = docs_test.output_mismatch(b.expected_output, out)
            row["stated_output"] = "printed" if miss is None else f"missing: {miss}"
        lines = out.strip().splitlines()
        row["output_tail"] = lines[-12:]
        if not row["as_documented"]:
            row["missing_extras"] = _missing_extra(out)
            errs = [ln for ln in lines if "error" in ln.lower() or "No module named" in ln]
            row["error_line"] = (errs or lines or [""])[-1]
            stop = b.line
        print(f"    exit {r['exit']} (page: {b.exit_status})  wall {r['wall_s']} s  cpu {r['cpu_s']} s  compile "
              f"{r['compile_printed_s']} / {r['compile_result_json_s']} s  reports {len(r['reports'])}",
              file=sys.stderr, flush=True)
        rows.append(row)
    return rows


def _fmt(v, nd=1) -> str:
    return "-" if v is None else (f"{v:.{nd}f}" if isinstance(v, float) else str(v))


def markdown(doc: dict) -> str:
    m = doc["meta"]
    lines = [f"# Docs commands on a fresh install, {m['date']}, commit {m['commit']}", "",
             f"{m['cpus']} CPUs; NUMBA_NUM_THREADS {m['NUMBA_NUM_THREADS']}; Python {m['python']}; "
             f"venv {'reused' if m['venv_reused'] else 'new'} ({m['venv']}); empty NUMBA_CACHE_DIR for the whole run.",
             f"Load before: `{m['uptime_before']}`; after: `{m['uptime_after']}`.", "",
             "Per block: exit expected/got, wall s, CPU s (children), compile s as printed by the verbs / "
             "as their result.json `timings_s.compile_s` state it, stated output, reports (figures decoded of "
             "figures).", "",
             "| page:line | attempt | commands | exit page/got | wall s | CPU s | compile s printed / json | "
             "stated output | reports (figures) |", "|---|---|---|---|---:|---:|---|---|---|"]
    reps = {r["path"]: r for r in doc["reports"]}
    for r in doc["readme"] + doc["blocks"]:
        cmd = " ; ".join(ln.strip() for ln in r["commands"].splitlines() if ln.strip() and not ln.strip() == "\\")
        cmd = cmd.replace("|", "\\|")
        cmd = cmd if len(cmd) <= 110 else cmd[:107] + "..."
        if r.get("exit") is None:
            lines.append(f"| {r['page']}:{r['line']} | {r['attempt']} | `{cmd}` | {r['exit_expected']}/not run | "
                         f"- | - | - | - | {r.get('not_run', '')} |")
            continue
        rp = [reps.get(str(Path(r["folder"]) / x)) for x in r.get("reports", [])]
        rtxt = ", ".join(f"{x}: {p['figures_decoded']}/{p['figures']}" if p else f"{x}: not opened"
                         for x, p in zip(r.get("reports", []), rp, strict=True)) or "-"
        got = f"{r['exit_expected']}/{r['exit']}" + ("" if r.get("as_documented", True) else " **NOT as documented**")
        lines.append(f"| {r['page']}:{r['line']} | {r['attempt']} | `{cmd}` | {got} | {_fmt(r['wall_s'])} | "
                     f"{_fmt(r['cpu_s'])} | {_fmt(r['compile_printed_s'])} / {_fmt(r['compile_result_json_s'])} | "
                     f"{r.get('stated_output', '-')} | {rtxt} |")
    fails = [r for r in doc["readme"] + doc["blocks"] if r.get("exit") is not None and not r.get("as_documented", True)]
    lines += ["", "## Blocks that did not exit as documented", ""]
    lines += [f"* {r['page']}:{r['line']} ({r['attempt']}): exit {r['exit']}, the page says {r['exit_expected']}; "
              f"missing extras: {', '.join(r.get('missing_extras') or []) or 'none'}; last error line: "
              f"`{r.get('error_line', '')}`" for r in fails] or ["* none"]
    lines += ["", "## Extras", ""]
    lines += [f"* {e['page']}: `{e['command']}` (the page's own instruction) exit {e['exit']}, {e['wall_s']:.1f} s; "
              f"added {', '.join(e['added']) or 'nothing'}; removed afterwards: {e['removed']}" for e in doc["extras"]] \
        or ["* none installed"]
    tot = [r for r in doc["readme"] + doc["blocks"] if r.get("exit") is not None]
    nrep = len(doc["reports"])
    okrep = sum(1 for r in doc["reports"] if r["figures"] > 0 and r["figures_decoded"] == r["figures"])
    lines += ["", f"Totals: {len(tot)} steps run, {sum(1 for r in tot if r.get('as_documented', True))} as documented; "
              f"wall {sum(r['wall_s'] for r in tot):.0f} s, CPU {sum(r['cpu_s'] for r in tot):.0f} s, compile "
              f"(printed) {sum(r['compile_printed_s'] or 0 for r in tot):.0f} s; reports {nrep}, "
              f"{okrep} with all figures decoded (at least one)."]
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keep", type=Path, default=None, help="work in this folder (its venv/ is reused) and keep it")
    ap.add_argument("--pages", nargs="+", default=None, help="only these pages (paths in the clone, e.g. docs/mast.md)")
    ap.add_argument("--no-demo", action="store_true", help="skip the demo part of the README's first command")
    ap.add_argument("--label", default="", help="suffix of the results files")
    ap.add_argument("--out-dir", type=Path, default=RESULTS)
    ap.add_argument("--markdown", type=Path, default=None, metavar="JSON",
                    help="write the .md of this results file again (and its json compile sums) and exit")
    a = ap.parse_args()
    if a.markdown:
        doc = json.loads(a.markdown.read_text())
        for r in doc["readme"] + doc["blocks"]:
            by = r.get("compile_by_json") or {}
            if by:
                r["compile_result_json_s"] = round(sum(by[k] for k in _outermost(list(by))), 2)
        a.markdown.write_text(json.dumps(doc, indent=1) + "\n")
        a.markdown.with_suffix(".md").write_text(markdown(doc) + "\n")
        print(markdown(doc))
        return 0

    work = (a.keep or Path(tempfile.mkdtemp(prefix="minegeo-docs-fresh-"))).resolve()
    work.mkdir(parents=True, exist_ok=True)
    bfi = _load("bench_fresh_install", ROOT / "benchmarks" / "bench_fresh_install.py")
    meta: dict = {"date": time.strftime("%Y-%m-%d %H:%M"), "cpus": os.cpu_count(), "python": sys.version.split()[0],
                  "NUMBA_NUM_THREADS": os.environ.get("NUMBA_NUM_THREADS", "(unset: all cores)"),
                  "uptime_before": _uptime(), "shared_data": str(SHARED)}
    clone = work / "minegeo"
    if clone.exists():
        shutil.rmtree(clone)
    subprocess.run(["git", "clone", "-q", str(ROOT), str(clone)], check=True)
    meta["commit"] = _git(clone, "rev-parse", "--short", "HEAD")
    meta["commit_subject"] = _git(clone, "log", "-1", "--format=%s")[:200]
    sys.path.insert(0, str(clone / "tests"))  # the docs test imports tests/helpers.py
    docs_test = _load("docs_commands_of_clone", clone / "tests" / "docs" / "test_docs_commands.py")

    venv = work / "venv"
    deps = _core_deps_of_clone(clone)
    reuse = (venv / "bin" / "python").exists() and _core_deps_in_venv(venv / "bin" / "python") == deps
    if not reuse:
        if venv.exists():
            shutil.rmtree(venv)
        subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    meta.update({"venv": str(venv), "venv_reused": reuse, "core_dependencies": deps})
    cache = work / "numba_cache"
    if cache.exists():
        shutil.rmtree(cache)
    cache.mkdir()
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "VIRTUAL_ENV", "PYTHONHOME") and not k.startswith("MINEGEO_")}
    env.update({"PATH": f"{venv / 'bin'}:{env['PATH']}", "VIRTUAL_ENV": str(venv), "NUMBA_CACHE_DIR": str(cache),
                "PIP_DISABLE_PIP_VERSION_CHECK": "1"})
    meta["NUMBA_CACHE_DIR"] = str(cache)

    # the README's first command, verbatim, from the root of the clone, its parts timed apart
    readme = clone / "README.md"
    first = next(b for b in re.findall(r"```console\n(.*?)```", readme.read_text(), flags=re.S))
    first_cmd = first.strip().splitlines()[0]
    meta["readme_first_command"] = first_cmd
    parts = [p.strip() for p in first_cmd.split("&&")]
    rows_readme = []
    for part in parts:
        if a.no_demo and part.startswith("minegeo demo"):
            continue
        print(f"[{time.strftime('%H:%M:%S')}] README: {part}", file=sys.stderr, flush=True)
        r = _run_block(part, clone, env, 3600)
        out = r.pop("output")
        r.update({"page": "README.md", "line": readme.read_text().splitlines().index(first_cmd) + 1,
                  "attempt": "bare", "commands": part, "exit_expected": 0, "folder": str(clone),
                  "as_documented": r["exit"] == 0, "output_tail": out.strip().splitlines()[-12:]})
        rows_readme.append(r)
        print(f"    exit {r['exit']}  wall {r['wall_s']} s  cpu {r['cpu_s']} s  compile {r['compile_printed_s']} / "
              f"{r['compile_result_json_s']} s", file=sys.stderr, flush=True)
        if r["exit"] != 0:
            break
    site = subprocess.run([str(venv / "bin" / "python"), "-c", "import minegeo, pathlib; "
                           "print(pathlib.Path(minegeo.__file__).parent)"], capture_output=True, text=True,
                          env=env, cwd=work).stdout.strip()
    meta["installed_package"] = site
    meta["pip_freeze"] = _freeze(venv, env)

    pages = [clone / p for p in a.pages] if a.pages else [readme] + sorted((clone / "docs").glob("*.md"))
    runs = work / "pages"
    if runs.exists():
        shutil.rmtree(runs)
    blocks: list[dict] = []
    if all(r["exit"] == 0 for r in rows_readme):
        for page in pages:
            blocks += _run_page(page, clone, runs / page.stem / "bare", env, docs_test, "bare")

    # the pages that tell the user to install the extra they missed: follow the page, run it again
    extras = []
    for page in pages:
        need = sorted({e for r in blocks if r["page"] == str(page.relative_to(clone))
                       for e in r.get("missing_extras", [])})
        text = page.read_text(encoding="utf-8")
        told = {m["extra"]: m.group(0) for m in INSTALL_EXTRA.finditer(text)}
        todo = [e for e in need if e in told]
        if not todo:
            continue
        freeze0 = _freeze(venv, env)
        for e in todo:
            cmd = told[e] if told[e].count("'") % 2 == 0 else told[e] + "'"
            print(f"[{time.strftime('%H:%M:%S')}] {page.name} tells the user: {cmd}", file=sys.stderr, flush=True)
            r = _run_block(cmd, work, env, 1800)
            extras.append({"page": str(page.relative_to(clone)), "extra": e, "command": cmd, "exit": r["exit"],
                           "wall_s": r["wall_s"], "output_tail": r["output"].strip().splitlines()[-5:]})
        added = sorted(set(_freeze(venv, env)) - set(freeze0))
        blocks += _run_page(page, clone, runs / page.stem / ("with_" + "_".join(todo)), env, docs_test,
                            "after " + " ".join(told[e] for e in todo))
        names = [ln.split("==")[0] for ln in added]
        if names:
            subprocess.run([str(venv / "bin" / "pip"), "uninstall", "-q", "-y", *names], env=env, check=False)
        restored = _freeze(venv, env) == freeze0
        for x in extras:
            if x["page"] == str(page.relative_to(clone)):
                x.update({"added": added, "removed": "yes, venv as before" if restored else "NO: venv differs"})

    meta["uptime_after"] = _uptime()
    reports = []
    files = [Path(r["folder"]) / x for r in rows_readme + blocks for x in r.get("reports", [])]
    files = list(dict.fromkeys(f for f in files if f.is_file()))
    if files:
        for f, info in zip(files, _reports_in_browser(files, bfi.CHROMIUM), strict=True):
            reports.append({"path": str(f), **info})
    doc = {"meta": meta, "readme": rows_readme, "blocks": blocks, "extras": extras, "reports": reports}
    a.out_dir.mkdir(parents=True, exist_ok=True)
    stem = a.out_dir / (f"docs_fresh_{time.strftime('%Y-%m-%d')}" + (f"_{a.label}" if a.label else ""))
    stem.with_suffix(".json").write_text(json.dumps(doc, indent=1) + "\n")
    stem.with_suffix(".md").write_text(markdown(doc) + "\n")
    print(markdown(doc))
    if not a.keep:
        shutil.rmtree(work, ignore_errors=True)
    ok = all(r.get("as_documented", True) for r in rows_readme + blocks if r.get("exit") is not None)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
