"""``compare.md`` and ``compare.json``: a comparison's result (``compare.compare``) as Markdown, per
group the summary table, the per-seed table and what each side differs in, and both files written."""
from __future__ import annotations

import json
from pathlib import Path

from .sides import _by_option, _seeds, _show


def _cell(mean: float, sd: float) -> str:
    return f"{mean:.3f} ± {sd:.3f}"


def _ratio_cell(r) -> str:
    return "1 (reference)" if r is None else f"{r['ratio']:.2f} x [{r['ratio_low']:.2f}, {r['ratio_high']:.2f}]"


def _count_cell(c: dict) -> str:
    return f"{c['k']} of {c['n']} [{c['low']:.2f}, {c['high']:.2f}]"


def _letter(i: int) -> str:
    """The per-seed table's short name of side ``i`` (0-based): A, B, ..., Z, AA, AB, ..."""
    return ("" if i < 26 else _letter(i // 26 - 1)) + chr(ord("A") + i % 26)


def _seed_cell(side: dict, also: str | None, seed: int) -> str:
    """One seed's value of ``side``'s metric (``also``: None) or of an ``--also`` column; '-' if missing."""
    if seed not in side["seeds"]:
        return "-"
    return f"{(side['also_values'][also] if also else side['values'])[side['seeds'].index(seed)]:.4f}"


def to_markdown(result: dict) -> str:
    """``compare.md``: per group, the per-seed table and the summary table."""
    metric = result["metric"]
    lines = ["# Comparison", "", f"Metric: `{metric}`. Differences are in points (x 100) against the reference "
             f"(the first side), with the {result['interval']}.", ""]
    for grp in result["groups"]:
        sides = grp["sides"]
        if result["group"]:
            lines += [f"## {result['group']} = {_show(grp['group'])}", ""]
        lines += _summary_table(sides, metric) + _seed_table(sides, metric)
        for s in sides[1:]:
            keys = _by_option(s["differs_in"])
            note = f"'{s['label']}' differs from the reference in: {', '.join(keys[:8])}" + (" ..." if len(keys) > 8 else "")
            if s["dropped_seeds"]:
                note += f"; seeds left out (unfinished on one side): {_seeds(set(s['dropped_seeds']))}"
            lines += ["", note]
        lines.append("")
    return "\n".join(lines + _notes(result))


def _summary_table(sides: list[dict], metric: str) -> list[str]:
    """One row per side: its mean ± std, ``--also`` / ``--ratio`` / ``--count`` columns and the paired difference."""
    also, ratios = list(sides[0]["also"]), list(sides[0].get("ratios", {}))
    counts = list(sides[0].get("counts", {}))
    lines = ["| side | seeds | " + metric + " (mean ± std) | " + "".join(f"{k} | " for k in also)
             + "".join(f"{k} / reference [95%] | " for k in ratios)
             + "".join(f"seeds with {c} [Wilson 95%] | " for c in counts)
             + "vs reference (points) | 95% interval | ahead / tied / behind | commit |",
             "|---|---|---|" + "---|" * (len(also) + len(ratios) + len(counts)) + "---|---|---|---|"]
    for i, s in enumerate(sides):
        vs = ("reference" if i == 0 else f"{100 * s['diff']:+.1f} ± {100 * s['diff_sd']:.1f}")
        ci = "" if i == 0 else f"[{100 * s['low']:+.1f}, {100 * s['high']:+.1f}]"
        wins = "" if i == 0 else f"{s['ahead']} / {s['tied']} / {s['behind']}"
        lines.append(f"| {s['label']} | {len(s['seeds'])} | {_cell(s['mean'], s['sd'])} | "
                     + "".join(f"{_cell(*s['also'][k])} | " for k in also)
                     + "".join(f"{_ratio_cell(s['ratios'][k])} | " for k in ratios)
                     + "".join(f"{_count_cell(s['counts'][c])} | " for c in counts)
                     + f"{vs} | {ci} | {wins} | {', '.join(s['commits']) or '-'} |")
    return lines


def _seed_table(sides: list[dict], metric: str) -> list[str]:
    """Every seed's value per side (the metric, then the ``--also`` columns), sides named by letter."""
    seeds = sorted({s for side in sides for s in side["seeds"]}, key=lambda x: (str(type(x)), x))
    also = list(sides[0]["also"])
    columns = [(i, None) for i in range(len(sides))] + [(i, k) for k in also for i in range(len(sides))]
    lines = ["", f"Per seed ({metric}{', then ' + ', '.join(also) if also else ''}; "
             + "; ".join(f"{_letter(i)}: {s['label']}" for i, s in enumerate(sides)) + "):", "",
             "| seed | " + " | ".join(_letter(i) + (f" {k}" if k else "") for i, k in columns) + " |",
             "|---|" + "---|" * len(columns)]
    for seed in seeds:
        cells = [_seed_cell(sides[i], k, seed) for i, k in columns]
        lines.append(f"| {seed} | " + " | ".join(cells) + " |")
    return lines


def _notes(result: dict) -> list[str]:
    """The closing notes: keys filled with today's defaults, more than one machine, runs not finished."""
    lines = []
    filled = {k: n for k, n in result.get("filled", {}).items() if not k.startswith("-")}
    dropped = {k[1:]: n for k, n in result.get("filled", {}).items() if k.startswith("-")}
    if filled:
        lines += ["Keys some runs' records lack (made before the key existed), read as the current default: "
                  + ", ".join(f"{k} ({n} run{'s' if n > 1 else ''})" for k, n in filled.items()), ""]
    if dropped:
        lines += ["Keys some runs' records hold that their option no longer has (recorded before one schema per "
                  "option), left out: " + ", ".join(f"{k} ({n} run{'s' if n > 1 else ''})" for k, n in dropped.items()), ""]
    if len(result.get("machines", {})) > 1:
        lines += ["Runs made on more than one machine (float rounding differs between them, so a seed's run "
                  "repeats to the digit only on its own): " + ", ".join(f"{m} ({n} run{'s' if n > 1 else ''})"
                                                                       for m, n in result["machines"].items()), ""]
    if result["not_finished"]:
        lines += ["Runs not finished (left out):", ""]
        lines += [f"- {r['path']}: {r['status']}" + (f": {r['error']}" if r["error"] else "") for r in result["not_finished"]]
        lines.append("")
    return lines


def write(result: dict, out_dir) -> tuple[Path, Path]:
    """``compare.md`` and ``compare.json`` into ``out_dir`` (made if needed); their paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    md, js = out / "compare.md", out / "compare.json"
    md.write_text(to_markdown(result))
    js.write_text(json.dumps(result, indent=1, default=str))
    return md, js
