"""Copy the tables of benchmarks/results/ into README.md, between its marker comments
(``<!-- NAME:start -->`` … ``<!-- NAME:end -->``), so that the README shows exactly what
the last benchmark runs measured.

    python benchmarks/readme_tables.py
"""
from __future__ import annotations

import json
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"


def table_lines(md_file: Path, first_header: str, rows: int | None = None) -> str:
    lines = md_file.read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(first_header))
    out = []
    for line in lines[start:]:
        if not line.startswith("|"):
            break
        out.append(line)
    return "\n".join(out[: rows + 2] if rows else out)


def speedup_table() -> str:
    """Time to each relMSE: every pmic curve against its like (raw against path,
    denoised against path + OIDN), from the last error_vs_time run at 512²."""
    data = json.loads((RESULTS / "error_vs_time_512.json").read_text())
    pairs = (("speedup", "pmic (final gather)", "path"),
             ("speedup_denoised", "pmic + OIDN", "path + OIDN"),
             # The reference's own noise (5.3e-4 in the room at 512²) added to every
             # relMSE: the same pair on relMSE minus that noise.
             ("speedup_denoised_noise_corrected", "pmic + OIDN, relMSE − reference noise",
              "path + OIDN, same"),
             ("speedup_first_hit", "pmic first-hit", "path"),
             ("speedup_first_hit_denoised", "pmic first-hit + OIDN", "path + OIDN"))
    out = ["| scene | relMSE | method | its time | against | their time | faster by |",
           "|---|---|---|---|---|---|---|"]
    for name, scene in data["scenes"].items():
        for key, ours, theirs in pairs:
            for target, v in scene.get(key, {}).items():
                path = (f"{v['path_s']:.1f} s" + (" (extrapolated)" if v.get("path_extrapolated") else "")
                        if v["path_s"] else "not reached")
                pmic = f"{v['pmic_s']:.2f} s" if v["pmic_s"] else "not reached"
                ratio = f"**{v['speedup']:.1f}×**" if v["speedup"] else "—"
                out.append(f"| {name} | {target} | {ours} | {pmic} | {theirs} | {path} | {ratio} |")
    return "\n".join(out)


def main():
    readme = (ROOT / "README.md").read_text()
    blocks = {
        "speedups": speedup_table(),
        "scene_errors": table_lines(RESULTS / "scene_errors_128.md", "| scene |"),
        "table1": table_lines(RESULTS / "table1_512.md", "| method | 10k"),
        "precompute": table_lines(RESULTS / "precompute.md", "| global photons"),
    }
    for name, table in blocks.items():
        pattern = re.compile(rf"(<!-- {name}:start -->\n).*?(\n<!-- {name}:end -->)", re.S)
        if not pattern.search(readme):
            raise SystemExit(f"README.md has no <!-- {name}:start/end --> markers")
        readme = pattern.sub(lambda m: m.group(1) + table + m.group(2), readme)
    (ROOT / "README.md").write_text(readme)
    print("README.md tables updated from", RESULTS)


if __name__ == "__main__":
    main()
