#!/usr/bin/env python
"""The photon stage with its tail loop and without, on the public scenes, in one run.

    python benchmarks/photon_stage.py                          # every public scene, 3 rounds
    python benchmarks/photon_stage.py --scenes white_room torus --repeat 5

A batch of light paths is traced as a wavefront: each bounce one kernel, then the paths
that go on are compacted. Each bounce is recorded and code-generated anew, the same for
2 paths as for 60 000, and a room's photon paths run to 64 bounces. Once a batch has
``photons.TAIL_LOOP_PATHS`` paths or fewer left, the rest of its bounces run in one
symbolic loop (``photons._trace_tail``), which stores the same photons in the same
order (``tests/test_pipeline.py::test_the_photon_tail_loop_stores_what_the_wavefront_stores``).
Per scene and mode (``wavefront``: ``TAIL_LOOP_PATHS = 0``; ``tail loop``: the default),
pmic's default photon stage at 1 spp, in rounds that alternate the modes after a
warm-up of each: the median seconds, the kernels' own execution seconds and the
launches (Dr.Jit's kernel history, one extra run), and the photon counts (equal in
both modes). Writes ``benchmarks/results/photon_stage.{json,md}``.
"""
from __future__ import annotations

import argparse
import statistics

import pmic_integrator  # noqa: F401  (LLVM set-up before Mitsuba)
import drjit as dr
import mitsuba as mi

import common
import kernel_report
from public_scenes import ORDER

MODES = ("wavefront", "tail loop")
#: kernel_report's name of the photon stage (pipeline.trace_maps).
PHOTON_STAGE = next(label for _, function, label in kernel_report.STAGES if function == "trace_maps")


def photon_stage(scene, mode: str, history: bool = False) -> dict:
    """Stats of one pmic render at 1 spp with the tail loop off or on (and with
    ``history`` the kernels' execution seconds and launches of its photon stage, as
    ``kernel_report.py`` counts them)."""
    from pmic_integrator import photons

    saved = photons.TAIL_LOOP_PATHS
    photons.TAIL_LOOP_PATHS = 0 if mode == "wavefront" else saved
    kernels = {}
    try:
        if history:
            recorder = kernel_report.render_recorded(scene, {"type": "pmic"}, 1)
            stage = recorder.stages()[PHOTON_STAGE]
            stats = recorder.integrator_stats
            kernels = {"launches": stage.n["launches"], "execution_s": stage.execution_ms / 1000}
        else:
            integrator = mi.load_dict({"type": "pmic"})
            integrator.progress = False
            dr.eval(mi.render(scene, integrator=integrator, spp=1))
            dr.sync_thread()
            stats = integrator.stats
    finally:
        photons.TAIL_LOOP_PATHS = saved
    return {"seconds": stats["time_photons"], "global": stats.get("photons_global", 0),
            "caustic": stats.get("photons_caustic", 0), **kernels}


def measure(name: str, repeat: int) -> dict:
    scene = common.load_public(name)
    runs = {mode: [] for mode in MODES}
    for mode in MODES:
        photon_stage(scene, mode)  # warm-up: compiles the kernels
    for round_ in range(repeat):
        for mode in (MODES if round_ % 2 == 0 else MODES[::-1]):
            runs[mode].append(photon_stage(scene, mode))
    row = {"scene": name}
    for mode in MODES:
        kernels = photon_stage(scene, mode, history=True)
        row[mode] = {"seconds": statistics.median(r["seconds"] for r in runs[mode]),
                     "runs": [r["seconds"] for r in runs[mode]],
                     "execution_s": kernels["execution_s"], "launches": kernels["launches"],
                     "photons": (runs[mode][0]["global"], runs[mode][0]["caustic"])}
    row["same_photon_counts"] = row[MODES[0]]["photons"] == row[MODES[1]]["photons"]
    print(name, {m: (round(row[m]["seconds"], 2), row[m]["launches"]) for m in MODES}, flush=True)
    return row


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", nargs="*", default=list(ORDER))
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args(argv)
    mi.set_variant(common.VARIANT)
    rows = [measure(name, args.repeat) for name in args.scenes]
    command = common.command(__file__, argv)
    lines = ["# The photon stage: wavefront against tail loop", "",
             f"`{command}` ({common.machine_summary()}); pmic's defaults, 1 spp; median of "
             f"{args.repeat} runs per mode in alternating rounds; kernel seconds and launches from "
             "Dr.Jit's kernel history (one more run).", "",
             "| scene | photons (global, caustic) | wavefront s | kernels s | launches | "
             "tail loop s | kernels s | launches | faster by |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        w, t = r["wavefront"], r["tail loop"]
        lines.append(f"| {r['scene']} | {t['photons'][0]}, {t['photons'][1]}"
                     f"{'' if r['same_photon_counts'] else ' (counts differ!)'} | {w['seconds']:.2f} | "
                     f"{w['execution_s']:.2f} | {w['launches']} | {t['seconds']:.2f} | {t['execution_s']:.2f} | "
                     f"{t['launches']} | {w['seconds'] / max(t['seconds'], 1e-9):.1f}× |")
    common.write_results(common.RESULTS, "photon_stage", {"command": command, "rows": rows}, lines)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
