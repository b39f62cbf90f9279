#!/usr/bin/env python
"""The GPU check of issue 43 (item 4): a test subset, ``error_vs_time`` and the kernel
report on ``cuda_ad_rgb`` (denoised curves through Mitsuba's OptiX denoiser), in one
command that ends within a time budget, with a short report.

    python tools/gpu_check.py                                   # cuda_ad_rgb, ~7 minutes at most
    python tools/gpu_check.py --variant llvm_ad_rgb --tests tests/test_jit_helpers.py \\
        --scenes cornell_box                                    # the same steps on the CPU (a dry run)
    python tools/gpu_check.py --make-wheels .whl                # (here) wheels for a machine without PyPI
    python3 tools/gpu_check.py --wheels .whl/part1 --install-only   # (there) in two transfers
    python3 tools/gpu_check.py --wheels .whl/part2                  # then the check

Steps, each a child process with its own time limit, cut to what is left of
``--budget`` (the later steps' shares kept back):

1. the environment: Python, Mitsuba, Dr.Jit, ``nvidia-smi -L``; whether the variant can
   be set and whether ``mi.OptixDenoiser`` exists. A variant that cannot be set stops
   the check here with the reason (exit status 2);
2. the tests of ``--tests`` (default :data:`TESTS`, without the ``slow`` ones) with
   ``PMIC_TEST_VARIANT`` set to the variant (see tests/conftest.py), one pytest run per
   file: passed / failed / skipped / errors and seconds of each, or "timed out";
3. ``benchmarks/error_vs_time.py --quick --variant V`` (128², ``--scenes``; ``--full``:
   512², the full ladders): each run's seconds and relMSE, and the speed-ups. On a
   ``cuda_*`` variant its "+OIDN" curves go through ``pmic_integrator.denoise``, which
   uses OptiX there;
4. ``benchmarks/kernel_report.py --variant V``: launches, distinct kernels, host reads,
   and how many kernels the first render compiled (on a GPU every distinct kernel is
   compiled on a fresh machine) and in how many milliseconds.

Writes into ``--out`` (default ``$OUT`` where set, else ``pmic-output/gpu_check``):
``gpu_check.md`` (the report, also printed), ``gpu_check.json``, ``gpu_check.log``
(every step's output), and the Markdown and JSON of steps 3 and 4. Exit status 0 when
every step ran and no test failed, 1 otherwise, 2 when the variant is unavailable.

A machine without PyPI access needs Mitsuba, Dr.Jit, OpenEXR, flip-evaluator and
colour-science as wheels for its Python: ``--make-wheels DIR`` downloads them (for
``--python-version``, default 3.12) and writes a Mitsuba wheel cut down to the variants
of ``--keep-variants`` without the plugins pmic's scenes never load (Mitsuba 3.9.1's
whole wheel for Python 3.12 is 59.6 MiB, cut down 32.0 MiB), in ``DIR/part1`` (the
others, 15.4 MiB) and ``DIR/part2`` (Mitsuba): with the checkout (~21 MiB) each fits
one transfer of the GPU machines here (64 MiB). ``--wheels DIR`` installs them with
``pip --no-index`` into ``--site`` (default ``/tmp/pmic-site``), copies this checkout's
package there as ``pip install .`` lays it out, and puts that folder first on the
children's ``PYTHONPATH``.
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: The default test subset: fast files first (Dr.Jit helpers, hash grids against brute
#: force, the furnace), then AOVs and the denoiser (OptiX on CUDA), then the images of
#: the bundled scenes against their references, and pmic against path in every JIT
#: variant the machine has (tests/test_variants.py: cuda_ad_spectral where the wheel
#: keeps it, ``--keep-variants``).
TESTS = ("tests/test_jit_helpers.py", "tests/test_hashgrid.py", "tests/test_furnace.py",
         "tests/test_variants.py", "tests/test_aovs_denoise.py", "tests/test_images.py")
#: Seconds each step may take at most (then cut to what the budget has left).
CAPS = {"environment": 60, "test_file": 150, "tests": 240, "error_vs_time": 150, "kernel_report": 90}
#: Wheels a machine without PyPI needs beside its own packages (numpy, scipy,
#: matplotlib, tqdm, pytest are on the project's GPU machines).
WHEELS = ("mitsuba==3.9.1", "drjit==1.5.0", "OpenEXR", "flip-evaluator", "colour-science")
#: Mitsuba plugins that neither pmic nor its bundled scenes and tests load.
UNUSED_PLUGINS = ("volpath", "volpathmis", "prbvolpath", "ellipsoids", "ellipsoidsmesh",
                  "bsplinecurve", "linearcurve", "sdfgrid", "timed_sunsky", "hair",
                  "measured_polarized", "pplastic", "polarizer", "retarder")


# ------------------------------------------------------------------------------------
# Running a step
# ------------------------------------------------------------------------------------
class Log:
    def __init__(self, path: Path):
        self.file = open(path, "w", encoding="utf-8")

    def write(self, text: str) -> None:
        self.file.write(text)
        self.file.flush()


def run(cmd: list[str], timeout: float, env: dict, log: Log, title: str) -> dict:
    """Run ``cmd`` (its output to ``log``) for at most ``timeout`` seconds; returns
    ``{"rc", "seconds", "timed_out", "tail"}``. On time-out its whole process group is
    ended (it is started in a session of its own)."""
    log.write(f"\n===== {title}: {' '.join(cmd)} (limit {timeout:.0f} s)\n")
    print(f"-- {title} (limit {timeout:.0f} s)", flush=True)
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, start_new_session=True)
    timed_out = False
    try:
        out, _ = proc.communicate(timeout=max(1.0, timeout))
    except subprocess.TimeoutExpired:
        timed_out = True
        os.killpg(proc.pid, signal.SIGKILL)
        out, _ = proc.communicate()
    seconds = time.perf_counter() - start
    log.write(out or "")
    log.write(f"\n===== {title}: rc {proc.returncode}, {seconds:.1f} s{' (timed out)' if timed_out else ''}\n")
    return {"rc": proc.returncode, "seconds": seconds, "timed_out": timed_out,
            "tail": (out or "").strip().splitlines()[-15:]}


def child_env(variant: str, site: Path | None) -> dict:
    env = dict(os.environ, PMIC_TEST_VARIANT=variant, PYTHONUNBUFFERED="1")
    paths = [str(site)] if site else []
    if not site:
        paths.append(str(ROOT / "src"))  # an uninstalled checkout: pmic_integrator from src
    if env.get("PYTHONPATH"):
        paths.append(env["PYTHONPATH"])
    env["PYTHONPATH"] = os.pathsep.join(paths)
    return env


PROBE = r"""
import json, sys
info = {"python": sys.version.split()[0]}
try:
    import pmic_integrator, mitsuba as mi, drjit as dr
    info.update(mitsuba=mi.__version__, drjit=dr.__version__)
    mi.set_variant(sys.argv[1])
    info["variant"] = mi.variant()
    info["optix_denoiser"] = hasattr(mi, "OptixDenoiser")
    import numpy as np
    scene = mi.load_dict(mi.cornell_box())
    image = mi.render(scene, spp=4)
    info["path_mean"] = float(np.mean(np.array(image)))
except Exception as error:
    info["error"] = f"{type(error).__name__}: {error}"
print("PROBE " + json.dumps(info))
"""


def environment(variant: str, env: dict, log: Log, timeout: float) -> dict:
    info: dict = {}
    if shutil.which("nvidia-smi"):
        gpus = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, timeout=30)
        info["gpus"] = gpus.stdout.strip().splitlines()
    else:
        info["gpus"] = []
    step = run([sys.executable, "-c", PROBE, variant], timeout, env, log, "environment")
    for line in step["tail"]:
        if line.startswith("PROBE "):
            info.update(json.loads(line[6:]))
    if "variant" not in info and "error" not in info:
        info["error"] = "the probe printed nothing: " + " / ".join(step["tail"][-3:])
    info["seconds"] = step["seconds"]
    return info


# ------------------------------------------------------------------------------------
# The steps
# ------------------------------------------------------------------------------------
def junit_counts(path: Path) -> dict:
    root = ET.parse(path).getroot()
    suite = root if root.tag == "testsuite" else root.find("testsuite")
    counts = {k: int(suite.get(k, 0)) for k in ("tests", "failures", "errors", "skipped")}
    counts["passed"] = counts["tests"] - counts["failures"] - counts["errors"] - counts["skipped"]
    counts["failed_names"] = [f"{case.get('classname')}::{case.get('name')}" for case in suite.iter("testcase")
                              if case.find("failure") is not None or case.find("error") is not None]
    return counts


def tests_step(files, env, log, deadline, reserve) -> list[dict]:
    rows = []
    tests_end = min(deadline - reserve, time.perf_counter() + CAPS["tests"])
    with tempfile.TemporaryDirectory() as tmp:
        for file in files:
            left = tests_end - time.perf_counter()
            if left < 5:
                rows.append({"file": file, "status": "not run (budget)"})
                continue
            xml = Path(tmp) / (Path(file).stem + ".xml")
            step = run([sys.executable, "-m", "pytest", file, "-q", "-m", "not slow", "-p", "no:cacheprovider",
                        f"--junitxml={xml}"], min(CAPS["test_file"], left), env, log, f"tests {file}")
            row = {"file": file, "seconds": round(step["seconds"], 1)}
            if step["timed_out"]:
                row["status"] = "timed out"
            elif xml.exists():
                row.update(junit_counts(xml))
                row["status"] = "ok" if row["failures"] + row["errors"] == 0 else "FAILED"
            else:
                row["status"] = f"pytest exited {step['rc']} without a report"
            rows.append(row)
    return rows


def benchmark_step(name, args, env, log, timeout, out: Path) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        step = run([sys.executable, f"benchmarks/{name}.py", *args, "--out", tmp], timeout, env, log, name)
        result = {"rc": step["rc"], "seconds": round(step["seconds"], 1), "timed_out": step["timed_out"]}
        for path in sorted(Path(tmp).glob("*.json")):
            data = json.loads(path.read_text())
            result.setdefault("data", data)
            for kept in (path, path.with_suffix(".md")):
                if kept.exists():
                    shutil.copy(kept, out / kept.name)
        if step["rc"] != 0 and not step["timed_out"]:
            result["tail"] = step["tail"][-6:]
    return result


# ------------------------------------------------------------------------------------
# The report
# ------------------------------------------------------------------------------------
def report(variant, info, tests, evt, kr, budget, elapsed) -> list[str]:
    lines = [f"# GPU check: {variant}", "",
             f"`python tools/gpu_check.py {' '.join(sys.argv[1:])}`: {elapsed:.0f} s of a {budget:.0f} s budget.", "",
             f"- GPUs: {', '.join(info.get('gpus') or ['none found by nvidia-smi'])}",
             f"- Python {info.get('python')}, Mitsuba {info.get('mitsuba')}, Dr.Jit {info.get('drjit')}; "
             f"variant {info.get('variant', 'NOT SET')}; OptiX denoiser: {info.get('optix_denoiser')}; "
             f"first render (path, Cornell box, 4 spp): {info.get('seconds', 0):.1f} s with start-up, "
             f"mean {info.get('path_mean', float('nan')):.4f}"]
    if "error" in info:
        lines.append(f"- **variant unavailable**: {info['error']} (a {variant} variant needs its device "
                     f"and driver; `--variant llvm_ad_rgb` runs the same steps on the CPU)")
        return lines
    lines += ["", "## Tests (`PMIC_TEST_VARIANT=" + variant + "`, not slow)", "",
              "| file | status | passed | failed | errors | skipped | s |", "|---|---|---|---|---|---|---|"]
    for r in tests:
        lines.append(f"| {r['file']} | {r['status']} | {r.get('passed', '')} | {r.get('failures', '')} | "
                     f"{r.get('errors', '')} | {r.get('skipped', '')} | {r.get('seconds', '')} |")
    failed = [n for r in tests for n in r.get("failed_names", [])]
    if failed:
        lines += ["", "Failed: " + ", ".join(f"`{n}`" for n in failed[:20])]
    if evt:
        lines += error_vs_time_lines(variant, evt)
    if kr:
        lines += kernel_report_lines(kr)
    return lines


def error_vs_time_lines(variant, evt) -> list[str]:
    lines = ["", f"## error_vs_time ({evt.get('seconds', 0)} s"
             f"{', TIMED OUT' if evt.get('timed_out') else ''}, rc {evt.get('rc')})", ""]
    data = evt.get("data")
    if data:
        lines += [f"{data.get('resolution')}², mode {data.get('mode')}; \"+OIDN\" curves are denoised by "
                  f"`pmic_integrator.denoise` ({'OptiX' if variant.startswith('cuda') else 'OIDN'} here).", "",
                  "| scene | run | settings | s | compile s | relMSE | luminance |", "|---|---|---|---|---|---|---|"]
        for scene, sdata in data.get("scenes", {}).items():
            for r in sdata.get("runs", []):
                settings = ", ".join(f"{k}={v}" for k, v in r.get("integrator", {}).items()
                                     if k not in ("type", "max_depth", "aovs"))
                lines.append(f"| {scene} | {r['label']} | {settings or '-'}, spp={r['spp']} | "
                             f"{r['seconds']:.3f} | {r.get('compile_s', 0):.1f} | {r['rel_mse']:.2e} | "
                             f"{r.get('luminance_ratio', float('nan')):.4f} |")
            for key in ("speedup", "speedup_denoised"):
                if key in sdata:
                    ups = "; ".join(f"{t}: {v['speedup']:.2f}x" if v.get("speedup") else f"{t}: -"
                                    for t, v in sdata[key].items())
                    lines.append(f"| {scene} | {key} (relMSE target: pmic over path) | {ups} | | | | |")
    elif evt.get("tail"):
        lines += ["```", *evt["tail"], "```"]
    return lines


def kernel_report_lines(kr) -> list[str]:
    lines = ["", f"## Kernel report ({kr.get('seconds', 0)} s{', TIMED OUT' if kr.get('timed_out') else ''}, "
             f"rc {kr.get('rc')})", ""]
    data = kr.get("data")
    if data:
        lines += ["| integrator | launches | JIT | distinct | memcpy | memset | host reads | first run: "
                  "compiled / from disk | compile ms |", "|---|---|---|---|---|---|---|---|---|"]
        for name, idata in data.get("integrators", {}).items():
            w, c = idata["warm"]["total"], idata["cold"]["total"]
            lines.append(f"| {name} | {w['launches']} | {w['jit']} | {w['distinct']} | {w['memcpy']} | "
                         f"{w['memset']} | {w['host_reads']} | {c['new_compiled']} / {c['new_from_disk']} | "
                         f"{c['compile_ms']:.0f} |")
        lines += ["", "Per stage: kernel_report.md."]
    elif kr.get("tail"):
        lines += ["```", *kr["tail"], "```"]
    return lines


# ------------------------------------------------------------------------------------
# Wheels for a machine without PyPI
# ------------------------------------------------------------------------------------
def make_wheels(folder: Path, python_version: str, keep: list[str]) -> int:
    folder.mkdir(parents=True, exist_ok=True)
    platforms = [f"--platform={p}" for p in ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64",
                                            "manylinux_2_17_x86_64", "manylinux2014_x86_64")]
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:",
                        f"--python-version={python_version}", "--implementation=cp", *platforms,
                        "-d", tmp, *WHEELS], check=True)
        for part in ("part1", "part2"):
            shutil.rmtree(folder / part, ignore_errors=True)
            (folder / part).mkdir()
        for wheel in sorted(Path(tmp).glob("*.whl")):
            if wheel.name.startswith("mitsuba-"):
                slim_mitsuba(wheel, folder / "part2" / wheel.name, keep)
            else:
                shutil.copy(wheel, folder / "part1" / wheel.name)
    for part in ("part1", "part2"):
        total = 0
        for wheel in sorted((folder / part).glob("*.whl")):
            total += wheel.stat().st_size
            print(f"{part}: {wheel.stat().st_size / 2**20:6.1f} MiB  {wheel.name}")
        print(f"{part}: {total / 2**20:6.1f} MiB in all")
    print(f"\nOn the machine without PyPI, one call after the other (a transfer may hold ~40 MiB "
          f"beside the checkout):\n  python3 tools/gpu_check.py --wheels {folder}/part1 --install-only\n"
          f"  python3 tools/gpu_check.py --wheels {folder}/part2")
    return 0


def slim_mitsuba(source: Path, target: Path, keep: list[str]) -> None:
    """A copy of Mitsuba's wheel with the variant modules of ``keep`` only and without
    :data:`UNUSED_PLUGINS` (and without the spectral upsampling table when no spectral
    variant is kept); its RECORD lists what is left."""
    spectral = any("spectral" in v for v in keep)

    def dropped(name: str) -> bool:
        base = name.split("/")[-1]
        if name.startswith("mitsuba/") and name.count("/") == 1 and ".cpython-" in base:
            variant = base.split(".cpython-")[0]
            if variant.split("_")[0] in ("scalar", "llvm", "cuda", "metal") and variant not in keep:
                return True
        if name.startswith("mitsuba/plugins/") and base.rsplit(".", 1)[0] in UNUSED_PLUGINS:
            return True
        return name == "mitsuba/data/srgb.coeff" and not spectral

    with zipfile.ZipFile(source) as src, zipfile.ZipFile(target, "w", zipfile.ZIP_DEFLATED) as dst:
        names = [i.filename for i in src.infolist() if not dropped(i.filename)]
        for name in names:
            data = src.read(name)
            if name.endswith(".dist-info/RECORD"):
                data = "".join(line + "\n" for line in data.decode().splitlines()
                               if not line or not dropped(line.split(",")[0])).encode()
            dst.writestr(src.getinfo(name), data)


def install_wheels(folder: Path, site: Path) -> Path:
    """Install the wheels of ``folder`` and this checkout's package into ``site`` (added
    to what an earlier call installed there: wheels too large for one transfer can come
    in two)."""
    wheels = sorted(glob.glob(str(folder / "*.whl")))
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-index", "--no-deps", "--no-compile",
                    "--upgrade", "--target", str(site), *wheels], check=True)
    # The package laid out as ``pip install .`` lays it out (pyproject's package-dir),
    # without a build backend: src/pmic_integrator, plugins/ and scenes/ as its data.
    package = site / "pmic_integrator"
    shutil.rmtree(package, ignore_errors=True)
    skip = shutil.ignore_patterns("__pycache__", "*.pyc")
    shutil.copytree(ROOT / "src" / "pmic_integrator", package, ignore=skip)
    shutil.copytree(ROOT / "plugins", package / "plugins", ignore=skip)
    shutil.copytree(ROOT / "scenes", package / "data", ignore=skip)
    return site


# ------------------------------------------------------------------------------------
def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variant", default="cuda_ad_rgb")
    parser.add_argument("--tests", nargs="*", default=list(TESTS), help="test files (none: skip the tests)")
    parser.add_argument("--scenes", nargs="+", default=["cornell_box", "indirect_room"])
    parser.add_argument("--full", action="store_true",
                        help="error_vs_time at 512² with the full ladders (give a larger --budget)")
    parser.add_argument("--skip", nargs="*", default=[], choices=["error_vs_time", "kernel_report"])
    parser.add_argument("--budget", type=float, default=420.0, help="seconds for all the steps")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--wheels", type=Path, default=None,
                        help="install the wheels of this folder and the checkout into --site first")
    parser.add_argument("--site", type=Path, default=None,
                        help="the folder of installed packages put first on the children's PYTHONPATH "
                             "(with --wheels default /tmp/pmic-site)")
    parser.add_argument("--install-only", action="store_true", help="stop after installing --wheels")
    parser.add_argument("--make-wheels", type=Path, default=None, help="download and slim the wheels, then stop")
    parser.add_argument("--python-version", default="3.12", help="for --make-wheels")
    parser.add_argument("--keep-variants", nargs="+", default=["scalar_rgb", "cuda_ad_rgb"],
                        help="for --make-wheels")
    args = parser.parse_args(argv)
    if args.make_wheels:
        return make_wheels(args.make_wheels, args.python_version, args.keep_variants)
    start = time.perf_counter()
    deadline = start + args.budget
    if args.full:  # 512², the full ladders: most of the budget
        CAPS["error_vs_time"] = max(CAPS["error_vs_time"], args.budget - CAPS["tests"] - CAPS["kernel_report"])
    site = args.site or (Path("/tmp/pmic-site") if args.wheels else None)
    if args.wheels:
        install_wheels(args.wheels, site)
        if args.install_only:
            print(f"installed {args.wheels}/*.whl and pmic_integrator into {site}")
            return 0
    out = args.out or Path(os.environ.get("OUT") or ROOT / "pmic-output" / "gpu_check")
    out.mkdir(parents=True, exist_ok=True)
    log = Log(out / "gpu_check.log")
    env = child_env(args.variant, site)
    reserve = sum(CAPS[s] for s in ("error_vs_time", "kernel_report") if s not in args.skip)

    info = environment(args.variant, env, log, min(CAPS["environment"], args.budget))
    tests, evt, kr = [], {}, {}
    if "error" not in info:
        tests = tests_step(args.tests, env, log, deadline, reserve)
        if "error_vs_time" not in args.skip:
            left = min(CAPS["error_vs_time"], deadline - time.perf_counter()
                       - (0 if "kernel_report" in args.skip else CAPS["kernel_report"]))
            mode = ["--resolution", "512"] if args.full else ["--quick"]
            evt = benchmark_step("error_vs_time", [*mode, "--variant", args.variant, "--scenes", *args.scenes],
                                 env, log, max(10.0, left), out)
        if "kernel_report" not in args.skip:
            left = min(CAPS["kernel_report"], deadline - time.perf_counter())
            kr = benchmark_step("kernel_report", ["--variant", args.variant], env, log, max(10.0, left), out)
    elapsed = time.perf_counter() - start
    lines = report(args.variant, info, tests, evt, kr, args.budget, elapsed)
    (out / "gpu_check.md").write_text("\n".join(lines) + "\n")
    (out / "gpu_check.json").write_text(json.dumps(
        {"variant": args.variant, "environment": info, "tests": tests,
         "error_vs_time": {k: v for k, v in evt.items() if k != "data"},
         "kernel_report": {k: v for k, v in kr.items() if k != "data"}, "seconds": elapsed}, indent=1))
    print("\n".join(lines))
    print(f"\nwrote {out}/gpu_check.md, .json, .log")
    if "error" in info:
        print(f"\nGPU check stopped: {info['error']}", file=sys.stderr)
        return 2
    ok = all(r.get("status") == "ok" for r in tests) and all(
        s.get("rc") == 0 for s in (evt, kr) if s)
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
