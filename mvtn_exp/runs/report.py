"""The paper's tables next to this project's runs (``mvtn-report``).

``paper_tables.yaml`` (in the package) lists every table and figure of the paper this project can
reproduce: per row the command that reproduces it (and its experiment file, when not the table's), the conditions a finished run's
stored config must meet to count for the row (``where``, as ``mvtn-compare --where``), the
``metrics.json`` number it reports (``metric``, dotted for nested keys, e.g.
``rotation.180.mean_acc``) and the paper's numbers in percent: ``paper``, the headline (the best of
the paper's four runs), and ``paper_mean`` / ``paper_std``, the supplement's mean +- std of those
runs where it gives them; ``cite`` says where in the paper's LaTeX source they stand, ``source``
names a secondary source.

``report(runs)`` fills each row from the finished runs that match it and hold the metric: mean +-
sample std over them (in percent), their best, count and seeds; our mean against the paper's mean
as a two-sample (Welch) 95% interval and whether it lies within the paper's spread; our best and
mean against its best of four. A row without runs says what it needs (``needs``).
"""
from __future__ import annotations

import fnmatch
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from scipy import stats

from .paired_stats import mean_sd
from .sides import CompareError, _matches
from ..runtime.dotted import lookup
from .folders import Run, find_runs

ANY = "<set>"  # a ``where`` value: the key holds any value but null
PAPER_RUNS = 4  # the paper's headline cells are the best of four runs; the supplement gives their mean +- std
SPREAD = 2.0  # "within the paper's spread": ours' mean inside the paper's mean +- SPREAD std

TABLES_FILE = Path(__file__).resolve().parents[1] / "paper_tables.yaml"
ROW_KEYS = {"label", "command", "where", "metric", "paper", "paper_mean", "paper_std", "cite", "source", "experiment"}
TABLE_KEYS = {"id", "title", "experiment", "needs", "rows"}
# optional per table: the settings the paper states for it (dotted config keys -> values, as the
# experiment file composes them) and where it states them; a test holds the experiment file to them
SETUP_KEYS = {"setup", "setup_cite"}


class ReportError(ValueError):
    """A tables file that does not say what a row needs, or a folder that cannot be read or holds no run."""


# what ``read_folders`` counts as a run (``runs/folders.py``)
NO_RUNS = ("no runs in it (a run is a folder holding metrics.json, status.json or .hydra/, as mvtn-train and "
           "mvtn-eval write them; give the folder of such runs or one above them)")


def read_folders(folders) -> list[Run]:
    """Every run at or below ``folders`` (``find_runs``: in the order given, a run reached twice read
    once); a folder that holds no run is a ``ReportError`` naming it (one that is not there: a
    ``FolderError``), raised before anything is written."""
    runs, seen = [], set()
    for folder in folders:
        found = find_runs([folder])
        if not found:
            raise ReportError(f"{folder}: {NO_RUNS}")
        for run in found:
            if run.path.resolve() not in seen:
                seen.add(run.path.resolve())
                runs.append(run)
    return runs


@dataclass
class Row:
    label: str
    command: str
    where: dict
    metric: str
    paper: float | None = None  # the paper's headline number: the best of its four runs
    source: str | None = None
    experiment: str | None = None  # when not the table's
    paper_mean: float | None = None  # the supplement's mean +- std of those four runs, where it gives them
    paper_std: float | None = None
    cite: str | None = None  # where in the paper's LaTeX source (``L...``) the numbers stand


@dataclass
class Table:
    id: str
    title: str
    experiment: str
    needs: str
    rows: list[Row] = field(default_factory=list)
    setup: dict = field(default_factory=dict)
    setup_cite: str | None = None


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
        _keys(t, TABLE_KEYS | SETUP_KEYS, TABLE_KEYS, f"table {i + 1}", path)
        if not isinstance(t.get("setup", {}), dict):
            raise ReportError(f"{path}: table {t['id']!r}: setup: expected KEY: VALUE settings of the experiment file")
        rows = []
        for j, r in enumerate(t["rows"] or []):
            where = f"table {t['id']!r}, row {j + 1}"
            _keys(r, ROW_KEYS, {"label", "command", "where", "metric"}, where, path)
            for key in ("paper", "paper_mean", "paper_std"):
                v = r.get(key)
                if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))):
                    raise ReportError(f"{path}: {where}: {key}={v!r}: expected a number in percent or null")
            if (r.get("paper_mean") is None) != (r.get("paper_std") is None):
                raise ReportError(f"{path}: {where}: paper_mean and paper_std: expected both (the supplement's "
                                  "mean +- std) or neither")
            if not isinstance(r["where"], dict) or not r["where"]:
                raise ReportError(f"{path}: {where}: where: expected KEY: VALUE conditions on the stored config")
            num = {k: None if r.get(k) is None else float(r[k]) for k in ("paper", "paper_mean", "paper_std")}
            rows.append(Row(str(r["label"]), str(r["command"]), dict(r["where"]), str(r["metric"]), num["paper"],
                            r.get("source"), r.get("experiment"), num["paper_mean"], num["paper_std"], r.get("cite")))
        tables.append(Table(str(t["id"]), str(t["title"]), str(t["experiment"]), str(t["needs"]), rows,
                            dict(t.get("setup") or {}), t.get("setup_cite")))
    return tables


def metric_value(metrics: dict, dotted: str) -> float | None:
    """``metrics["a"]["b"]`` for ``"a.b"`` (keys may contain dots themselves, e.g. ``"0.5"``) as a
    float, else None (absent, or not a number)."""
    node = lookup(metrics, dotted)
    return float(node) if isinstance(node, (int, float)) and not isinstance(node, bool) else None


def _pattern(v) -> bool:
    return isinstance(v, str) and "*" in v


def row_matches(settings: dict, where: dict) -> bool:
    """``where`` as ``mvtn-compare --where`` reads it, ``"<set>"`` meaning any value but null and a
    value with ``*`` a shell pattern on the setting's text (``"*/best.pt"``: a finished run's
    checkpoint, e.g. the FSL rows' ``backbone.weights``)."""
    plain = {k: v for k, v in where.items() if v != ANY and not _pattern(v)}
    return (_matches(settings, plain) and all(settings.get(k) is not None for k, v in where.items() if v == ANY)
            and all(isinstance(settings.get(k), str) and fnmatch.fnmatchcase(settings[k], v)
                    for k, v in where.items() if _pattern(v)))


def counts_for(run: Run, metric: str) -> bool:
    """Whether ``run`` reports ``metric`` for a row: a training run its own numbers; an evaluation
    run (``mvtn-eval``: it names its ``ckpt``) only what training does not write (robustness,
    retrieval) and only on the test split."""
    if "ckpt" not in run.metrics:
        return True
    return not metric.startswith("test_") and run.metrics.get("split", "test") == "test"


def welch(mean_a: float, sd_a: float, n_a: int, mean_b: float, sd_b: float, n_b: int) -> dict | None:
    """``a - b`` of two independent samples given by mean, sample std and size: the difference and
    its 95% Welch interval (Welch-Satterthwaite degrees of freedom). None when a side has fewer
    than 2 runs (no spread to estimate); both spreads 0 give the point interval."""
    if n_a < 2 or n_b < 2:
        return None
    d = mean_a - mean_b
    va, vb = sd_a * sd_a / n_a, sd_b * sd_b / n_b
    se2 = va + vb
    if se2 <= 0.0:
        return {"diff": d, "low": d, "high": d, "df": math.inf}
    df = se2 * se2 / ((va * va / (n_a - 1) if va else 0.0) + (vb * vb / (n_b - 1) if vb else 0.0))
    half = float(stats.t.ppf(0.975, df)) * math.sqrt(se2)
    return {"diff": d, "low": d - half, "high": d + half, "df": df}


def _against_paper(row: Row, vals: list[float]) -> dict:
    """Ours (mean, sd, best) against the paper's best of four and its mean +- std."""
    mean, sd = mean_sd(vals) if vals else (None, None)
    best = max(vals) if vals else None
    out = {"mean": mean, "sd": sd, "best": best,
           "diff": None if mean is None or row.paper is None else mean - row.paper,
           "best_diff": None if best is None or row.paper is None else best - row.paper,
           "mean_diff": None, "interval": None, "within_spread": None}
    if mean is not None and row.paper_mean is not None:
        out["mean_diff"] = mean - row.paper_mean
        out["interval"] = welch(mean, sd, len(vals), row.paper_mean, row.paper_std, PAPER_RUNS)
        out["within_spread"] = abs(mean - row.paper_mean) <= SPREAD * row.paper_std
    return out


def report(tables: list[Table], runs: list[Run]) -> dict:
    """Every row with the finished runs that match it: ``{"tables": [{..., "rows": [{label, paper,
    paper_mean, paper_std, cite, n, seeds, mean, sd, best, diff, best_diff, mean_diff, interval,
    within_spread, runs}]}], "unmatched": [run paths no row took]}`` (values in percent). ``diff``:
    our mean - the paper's best of four; ``best_diff``: our best - it; ``mean_diff`` and
    ``interval`` (Welch, 95%): our mean - the supplement's mean of four; ``within_spread``: our mean
    within the paper's mean +- ``SPREAD`` std."""
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
            rows.append({"label": row.label, "command": row.command, "metric": row.metric, "paper": row.paper,
                         "paper_mean": row.paper_mean, "paper_std": row.paper_std, "cite": row.cite,
                         "source": row.source, "n": len(vals), "seeds": seeds, **_against_paper(row, vals),
                         "runs": paths})
        out.append({"id": t.id, "title": t.title, "experiment": t.experiment, "needs": t.needs, "rows": rows})
    unmatched = [str(r.path) for r in done if r.path not in used]
    return {"tables": out, "unmatched": unmatched,
            "not_finished": [f"{r.path} ({r.status})" for r in runs if r.status != "ok"]}


def _num(v, fmt="{:.1f}") -> str:
    return "" if v is None or (isinstance(v, float) and math.isnan(v)) else fmt.format(v)


def _printed(v: float) -> str:
    """A paper number as printed (to the digits it has, at least one decimal: 92.0, 85.42)."""
    text = f"{v:g}"
    return text if "." in text or "e" in text else f"{v:.1f}"


def _paper_cells(r: dict) -> tuple[str, str]:
    if r["paper"] is not None:
        best = _printed(r["paper"])
    elif r["cite"] and r["cite"].startswith("not in"):
        best = "not in the paper"
    else:
        best = "-" if r["paper_mean"] is not None else "not given"  # (some tables give only the mean +- std)
    spread = f"{_printed(r['paper_mean'])} ± {_printed(r['paper_std'])}" if r["paper_mean"] is not None else "-"
    return best, spread


def _ours_cells(r: dict, needs: str) -> tuple[str, str, str, str]:
    """(ours mean +- std, ours best, ours - paper's mean [95% Welch], within the spread)."""
    if not r["n"]:
        return f"not run (needs {needs})", "", "", ""
    ours = _num(r["mean"]) + (f" ± {_num(r['sd'])}" if r["n"] > 1 else "")
    best = f"{_num(r['best'])} (of {r['n']})"
    if r["mean_diff"] is None:
        return ours, best, _num(r["diff"], "{:+.1f}") + (" (vs best of 4)" if r["diff"] is not None else ""), ""
    iv = r["interval"]
    diff = _num(r["mean_diff"], "{:+.1f}") + (f" [{iv['low']:+.1f}, {iv['high']:+.1f}]" if iv else " (one run: no interval)")
    return ours, best, diff, "yes" if r["within_spread"] else "no"


def to_markdown(result: dict) -> str:
    """One Markdown table per paper table: the paper's best of four and mean +- std, ours (mean +-
    std over runs, and the best), our mean - the paper's mean with a 95% Welch interval (against
    the best of four where the paper gives no mean), whether ours lies within the paper's spread,
    and the command."""
    parts = [f"Values in percent. Paper: the headline (best of {PAPER_RUNS} runs) and the supplement's mean ± std of "
             f"those runs; ours: mean ± std over the finished runs that match the row (`n`) and their best; "
             f"ours - paper: our mean - the paper's mean, with the two-sample (Welch) 95% interval, or - its best of "
             f"{PAPER_RUNS} where it gives no mean; within spread: our mean inside the paper's mean ± {SPREAD:g} std."]
    for t in result["tables"]:
        parts.append(f"\n### {t['title']}\n\n`+experiment={t['experiment']}`\n")
        lines = ["| row | paper (best of 4) | paper mean ± std | ours | n | ours best | ours - paper | within spread | command |",
                 "|---|---|---|---|---|---|---|---|---|"]
        for r in t["rows"]:
            best, spread = _paper_cells(r)
            ours, ours_best, diff, within = _ours_cells(r, t["needs"])
            lines.append(f"| {r['label']} | {best} | {spread} | {ours} | {r['n']} | {ours_best} | {diff} | {within} | "
                         f"`{r['command']}` |")
        parts.append("\n".join(lines))
    if result["not_finished"]:
        parts.append("\nNot finished (left out): " + "; ".join(result["not_finished"]))
    return "\n".join(parts) + "\n"


def paper_markdown(tables: list[Table]) -> str:
    """The paper's numbers alone, one Markdown table per paper table: each row's best of four, the
    supplement's mean +- std and where the LaTeX source gives them (``docs/paper.md`` holds this
    text; ``mvtn-report --paper`` prints it)."""
    parts = []
    for t in tables:
        parts.append(f"### {t.title}\n\n`+experiment={t.experiment}`; needs {t.needs}\n")
        if t.setup:
            stated = ", ".join(f"`{k}={v}`" for k, v in t.setup.items())
            parts.append(f"The paper's setup, which the file runs: {stated} ({t.setup_cite}).\n")
        lines = ["| row | paper (best of 4) | paper mean ± std | where in the paper | command |", "|---|---|---|---|---|"]
        for row in t.rows:
            r = {"paper": row.paper, "paper_mean": row.paper_mean, "paper_std": row.paper_std, "cite": row.cite}
            best, spread = _paper_cells(r)
            cite = (row.cite or "") + (f"; {row.source}" if row.source else "")
            lines.append(f"| {row.label} | {best} | {spread} | {cite} | `{row.command}` |")
        parts.append("\n".join(lines) + "\n")
    return "\n".join(parts)


def write(result: dict, out_dir) -> tuple[Path, Path]:
    """``report.md`` and ``report.json`` in ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    md, js = out / "report.md", out / "report.json"
    md.write_text(to_markdown(result))
    js.write_text(json.dumps(result, indent=1))
    return md, js


__all__ = ["ANY", "NO_RUNS", "PAPER_RUNS", "SPREAD", "CompareError", "ReportError", "counts_for", "load_tables", "metric_value",
           "read_folders", "report", "row_matches", "paper_markdown", "to_markdown", "welch", "write"]
