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
from public_scenes import ORDER

MODES = ("wavefront", "tail loop")


def photon_stage(scene, mode: str, history: bool = False) -> dict:
    """Stats of one pmic render at 1 spp with the tail loop off or on (and with
    ``history`` the kernels' execution seconds and launches of its photon stage)."""
    from pmic_integrator import photons, pipeline

    saved = photons.TAIL_LOOP_PATHS
    photons.TAIL_LOOP_PATHS = 0 if mode == "wavefront" else saved
    trace_maps, kernels = pipeline.trace_maps, {}

    def recorded(*args, **kwargs):
        dr.kernel_history()  # (clears it)
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        try:
            maps = trace_maps(*args, **kwargs)
            dr.sync_thread()
        finally:
            launched = dr.kernel_history()
            dr.set_flag(dr.JitFlag.KernelHistory, False)
        kernels.update(launches=len(launched),
                       execution_s=sum(k.get("execution_time", 0.0) for k in launched) / 1000)
        return maps

    if history:
        pipeline.trace_maps = recorded
    try:
        integrator = mi.load_dict({"type": "pmic"})
        integrator.progress = False
        dr.eval(mi.render(scene, integrator=integrator, spp=1))
        dr.sync_thread()
    finally:
        photons.TAIL_LOOP_PATHS = saved
        pipeline.trace_maps = trace_maps
    stats = integrator.stats
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
