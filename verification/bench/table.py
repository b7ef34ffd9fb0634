"""The benchmark's output: its table as text (``tissuebench bench``) and its section of
docs/benchmarks.md, one per machine, with the machine, the date and the commit it ran at."""

from __future__ import annotations

from realtime.models import linear_tm
from verification.bench import codegen


def format_table(out: dict) -> str:
    m = out["machine"]
    lines = [f"machine: {m['cpu']}, {m['cores']} cores, numba {m['numba']}"]
    if "roofline" in m:
        roof = m["roofline"]
        bw = ", ".join(f"{int(k) / 1e6:.3g} MB {v:.0f}" for k, v in roof["triad_gbs"].items())
        width = f" ({roof['vector_bits']}-bit vectors, as the kernels)" if "vector_bits" in roof else ""
        lines.append(f"one core: FMA peak {roof['fma_gflops']:.0f} GFLOP/s{width}; triad GB/s by data size: {bw}")
    for mesh in dict.fromkeys(r["mesh"] for r in out["results"]):
        rows = [r for r in out["results"] if r["mesh"] == mesh]
        head = f"\n{mesh}: {rows[0]['n_vertices']} vertices, {rows[0]['n_tets']} tetrahedra"
        ms = m.get("thread_scaling", {}).get(mesh)
        if ms:  # timed in the same rounds as the rows
            head += (
                f"; the machine's own gain from {ms['threads']} threads: FMA {ms['fma']:.2f}x, "
                f"triad on {ms['bytes'] / 1e6:.3g} MB {ms['triad']:.2f}x"
            )
        lines.append(head)
        lin = next(r["step_us"] for r in rows if r["name"] == linear_tm.NAME)
        bsr = next(r["step_us"] for r in rows if r["name"] == "scipy-bsr-matvec")
        rows = sorted(rows, key=lambda r: r.get("step_us") is None)
        for r in rows:
            if r.get("step_us") is None:
                lines.append(f"  {r['name']:<52} skipped: {r['skipped']}")
                continue
            note = f"  ({r['nonlinear_fraction']:.0%} of tetrahedra non-linear)" if "nonlinear_fraction" in r else ""
            if "share" in r:
                note += f"  {r['share']:.0%} of {r['part_of']}"
            if "speedup" in r:
                note += f"  {r['speedup']:.2f}x its {'float64' if r.get('precision') else 'one-thread'} row"
            if "roofline_us" in r:
                note += (
                    f"  roofline {r['roofline_us']:.1f} us ({r['roofline_limit']}): {r['roofline_fraction']:.0%} of it"
                )
            lines.append(
                f"  {r['name']:<52} {r['step_us']:>10.1f} us  ({r['step_us_min']:.1f} - {r['step_us_max']:.1f})"
                f"  x{r['step_us'] / lin:5.2f} linear-tm  x{r['step_us'] / bsr:5.2f} bsr{note}"
            )
    if "compiled_code" in out:
        lines.append("\n" + codegen.format_report(out["compiled_code"]))
    return "\n".join(lines)


def markdown_section(out: dict) -> str:
    """This run as a section of docs/benchmarks.md: a heading naming the machine, where and when it was
    measured, and one row per mesh and model (median microseconds per step, the spread, the ratio to
    linear-tm and to scipy's BSR product measured in the same rounds)."""
    m = out["machine"]
    lines = [
        f"## {m['cpu']}, {m['cores']} cores",
        "",
        f"Measured {m['date']} at commit {m['commit']} (numba {m.get('numba', '?')}) by `make bench`.",
        "",
        "| mesh | row | us per step | min - max | x linear-tm | x scipy BSR |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for mesh in dict.fromkeys(r["mesh"] for r in out["results"]):
        rows = [r for r in out["results"] if r["mesh"] == mesh]
        lin = next(r["step_us"] for r in rows if r["name"] == linear_tm.NAME)
        bsr = next(r["step_us"] for r in rows if r["name"] == "scipy-bsr-matvec")
        for r in rows:
            if r.get("step_us") is None:
                lines.append(f"| {mesh} | {r['name']} | skipped: {r['skipped']} | | | |")
                continue
            lines.append(
                f"| {mesh} | {r['name']} | {r['step_us']:.1f} | {r['step_us_min']:.1f} - {r['step_us_max']:.1f} "
                f"| {r['step_us'] / lin:.2f} | {r['step_us'] / bsr:.2f} |"
            )
    return "\n".join(lines) + "\n"


#: The head of docs/benchmarks.md, above one section per machine.
MARKDOWN_HEAD = (
    "# tissuebench: benchmarks\n\n"
    "Written by `make bench` (`tissuebench bench --markdown docs/benchmarks.md`): one section per machine, "
    "each replaced when that machine measures again. Speed is a property of a machine; compare rows "
    "within a section, measured in the same rounds.\n"
)


def write_markdown(path, out: dict) -> None:
    """Put this run's section into the markdown file at ``path``: the section of the same machine (its
    heading) is replaced, the other machines' are kept, in order. Written through a temporary file."""
    from pathlib import Path

    from meshes.io import atomic_write_text

    section = markdown_section(out)
    heading = section.split("\n", 1)[0]
    try:
        text = Path(path).read_text()
    except FileNotFoundError:
        text = MARKDOWN_HEAD
    head, *sections = text.split("\n## ")
    kept = ["## " + s.rstrip() + "\n" for s in sections if ("## " + s).split("\n", 1)[0] != heading]
    atomic_write_text(path, "\n".join([head.rstrip() + "\n", *kept, section]))
