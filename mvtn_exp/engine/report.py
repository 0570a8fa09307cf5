"""The paper's tables next to this project's runs (``mvtn-report``).

``paper_tables.yaml`` (in the package) lists every table and figure of the paper this project can
reproduce: per row the command that reproduces it (and its experiment file, when not the table's), the conditions a finished run's
stored config must meet to count for the row (``where``, as ``mvtn-compare --where``), the
``metrics.json`` number it reports (``metric``, dotted for nested keys, e.g.
``rotation.180.mean_acc``) and the paper's number in percent (``paper``; null where this
project's sources do not hold it, with ``source`` naming where a number comes from).

``report(runs)`` fills each row from the finished runs that match it and hold the metric: mean +-
sample std over them (in percent), their count and seeds, and the difference to the paper's number
in points. A row without runs says what it needs (``needs``).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from .compare import CompareError, Run, _matches, mean_sd

ANY = "<set>"  # a ``where`` value: the key holds any value but null

TABLES_FILE = Path(__file__).resolve().parents[1] / "paper_tables.yaml"
ROW_KEYS = {"label", "command", "where", "metric", "paper", "source", "experiment"}
TABLE_KEYS = {"id", "title", "experiment", "needs", "rows"}


class ReportError(ValueError):
    """A tables file that does not say what a row needs, or a folder that cannot be read."""


@dataclass
class Row:
    label: str
    command: str
    where: dict
    metric: str
    paper: float | None = None
    source: str | None = None
    experiment: str | None = None  # when not the table's


@dataclass
class Table:
    id: str
    title: str
    experiment: str
    needs: str
    rows: list[Row] = field(default_factory=list)


def _keys(node, allowed: set, required: set, where: str, path: Path) -> None:
    if not isinstance(node, dict):
        raise ReportError(f"{path}: {where}: expected a mapping, got {type(node).__name__}")
    bad = sorted(set(node) - allowed)
    if bad:
        raise ReportError(f"{path}: {where}: unknown key {bad[0]!r}; allowed: {', '.join(sorted(allowed))}")
    missing = sorted(required - set(node))
    if missing:
        raise ReportError(f"{path}: {where}: missing key {missing[0]!r}")


def load_tables(path: Path | str = TABLES_FILE) -> list[Table]:
    """The tables of ``path``; a malformed entry is one ``ReportError`` naming the file and entry."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ReportError(f"{path}: cannot read the tables ({exc})") from None
    if not isinstance(data, list):
        raise ReportError(f"{path}: expected a list of tables")
    tables = []
    for i, t in enumerate(data):
        _keys(t, TABLE_KEYS, TABLE_KEYS, f"table {i + 1}", path)
        rows = []
        for j, r in enumerate(t["rows"] or []):
            where = f"table {t['id']!r}, row {j + 1}"
            _keys(r, ROW_KEYS, {"label", "command", "where", "metric"}, where, path)
            paper = r.get("paper")
            if paper is not None and not isinstance(paper, (int, float)):
                raise ReportError(f"{path}: {where}: paper={paper!r}: expected a number in percent or null")
            if not isinstance(r["where"], dict) or not r["where"]:
                raise ReportError(f"{path}: {where}: where: expected KEY: VALUE conditions on the stored config")
            rows.append(Row(str(r["label"]), str(r["command"]), dict(r["where"]), str(r["metric"]),
                            None if paper is None else float(paper), r.get("source"), r.get("experiment")))
        tables.append(Table(str(t["id"]), str(t["title"]), str(t["experiment"]), str(t["needs"]), rows))
    return tables


def metric_value(metrics: dict, dotted: str) -> float | None:
    """``metrics["a"]["b"]`` for ``"a.b"`` (keys may contain dots themselves, e.g. ``"0.5"``), else None."""
    node, rest = metrics, dotted
    while rest:
        if not isinstance(node, dict):
            return None
        key = next((k for k in sorted(node, key=len, reverse=True)
                    if rest == k or rest.startswith(k + ".")), None)
        if key is None:
            return None
        node, rest = node[key], rest[len(key) + 1:]
    return float(node) if isinstance(node, (int, float)) and not isinstance(node, bool) else None


def row_matches(settings: dict, where: dict) -> bool:
    """``where`` as ``mvtn-compare --where`` reads it, ``"<set>"`` meaning any value but null."""
    plain = {k: v for k, v in where.items() if v != ANY}
    return _matches(settings, plain) and all(settings.get(k) is not None for k, v in where.items() if v == ANY)


def counts_for(run: Run, metric: str) -> bool:
    """Whether ``run`` reports ``metric`` for a row: a training run its own numbers; an evaluation
    run (``mvtn-eval``: it names its ``ckpt``) only what training does not write (robustness,
    retrieval) and only on the test split."""
    if "ckpt" not in run.metrics:
        return True
    return not metric.startswith("test_") and run.metrics.get("split", "test") == "test"


def report(tables: list[Table], runs: list[Run]) -> dict:
    """Every row with the finished runs that match it: ``{"tables": [{..., "rows": [{label, paper,
    n, seeds, mean, sd, diff, runs}]}], "unmatched": [run paths no row took]}`` (values in percent)."""
    done = [r for r in runs if r.status == "ok" and r.settings is not None]
    used: set[Path] = set()
    out = []
    for t in tables:
        rows = []
        for row in t.rows:
            vals, seeds, paths, ckpts = [], [], [], set()
            for run in done:
                v = metric_value(run.metrics, row.metric)
                if v is None or not counts_for(run, row.metric) or not row_matches(run.settings, row.where):
                    continue
                ckpt = run.metrics.get("ckpt")
                if ckpt is not None and ckpt in ckpts:  # one evaluation per checkpoint (the first found)
                    continue
                ckpts.add(ckpt)
                vals.append(100.0 * v)
                seeds.append(run.seed)
                paths.append(str(run.path))
                used.add(run.path)
            mean, sd = mean_sd(vals) if vals else (None, None)
            rows.append({"label": row.label, "command": row.command, "metric": row.metric, "paper": row.paper,
                         "source": row.source, "n": len(vals), "seeds": seeds, "mean": mean, "sd": sd,
                         "diff": None if mean is None or row.paper is None else mean - row.paper, "runs": paths})
        out.append({"id": t.id, "title": t.title, "experiment": t.experiment, "needs": t.needs, "rows": rows})
    unmatched = [str(r.path) for r in done if r.path not in used]
    return {"tables": out, "unmatched": unmatched,
            "not_finished": [f"{r.path} ({r.status})" for r in runs if r.status != "ok"]}


def _num(v, fmt="{:.1f}") -> str:
    return "" if v is None or (isinstance(v, float) and math.isnan(v)) else fmt.format(v)


def to_markdown(result: dict) -> str:
    """One Markdown table per paper table: the paper's number, ours (mean +- std over runs), the
    difference in points, and the command."""
    parts = ["Values in percent; ours: mean ± std over the finished runs that match the row "
             "(`n`: their number); difference: ours - paper, in points."]
    for t in result["tables"]:
        parts.append(f"\n### {t['title']}\n\n`+experiment={t['experiment']}`\n")
        lines = ["| row | paper | ours | n | ours - paper | command |", "|---|---|---|---|---|---|"]
        for r in t["rows"]:
            paper = _num(r["paper"]) or "not in this project's sources"
            if r["n"]:
                ours = _num(r["mean"]) + (f" ± {_num(r['sd'])}" if r["n"] > 1 else "")
            else:
                ours = f"not run (needs {t['needs']})"
            diff = _num(r["diff"], "{:+.1f}")
            lines.append(f"| {r['label']} | {paper} | {ours} | {r['n']} | {diff} | `{r['command']}` |")
        parts.append("\n".join(lines))
    if result["not_finished"]:
        parts.append("\nNot finished (left out): " + "; ".join(result["not_finished"]))
    return "\n".join(parts) + "\n"


def write(result: dict, out_dir) -> tuple[Path, Path]:
    """``report.md`` and ``report.json`` in ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    md, js = out / "report.md", out / "report.json"
    md.write_text(to_markdown(result))
    js.write_text(json.dumps(result, indent=1))
    return md, js


__all__ = ["ANY", "CompareError", "ReportError", "counts_for", "load_tables", "metric_value", "report", "row_matches",
           "to_markdown", "write"]
