"""Mutation check: how many deliberately broken copies of the model zoo the test suite catches.

    python scripts/mutation_check.py                       # every mutant, the tests of this tree
    python scripts/mutation_check.py --tests-rev 54364e0   # the same mutants, the tests of a commit
    python scripts/mutation_check.py --only viewgcn --list
    python scripts/mutation_check.py --auto 2 --rerun outputs/mutation/mutants.json   # survivors again

Two kinds of mutant, each applied to a copy of this tree (the checkout is never touched):
- named mutants (``NAMED``): plausible wrong implementations of a method, written by hand (the
  issue's first: a ViewGCN selector keeping the least confident view, nearest-point sampling, a
  DGCNN graph built once from xyz, a ViT cropping its position embedding, ...);
- operator mutants: every comparison, arithmetic operator, ``argmax``/``amax``/``max``-style call
  and boolean constant of ``mvtn_exp/models``, ``selectors`` and ``tasks`` is a candidate; ``--auto
  N`` draws N of them per module (seeded), each swapped for its opposite.

A mutant is *killed* when the tests of its module (``TEST_FILES``) fail or error within
``--timeout`` seconds; *survived* when they pass. Tests that fail on the unmutated tree (possible
with ``--tests-rev``) are left out first, and listed. Prints a table per
module (Markdown) and writes ``OUT/mutants.json``. Runs one mutant at a time, each pytest on one
torch thread; expect minutes per module.
"""
from __future__ import annotations

import argparse
import ast
import json
import os
import random
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("models", "selectors", "tasks")


@dataclass
class Mutant:
    name: str
    path: str   # relative to the repository root
    old: str
    new: str
    line: int = 0  # operator mutants: the 1-based line whose ``old`` becomes ``new``

    def apply(self, text: str) -> str:
        if not self.line:
            return text.replace(self.old, self.new, 1)
        lines = text.splitlines(keepends=True)
        lines[self.line - 1] = lines[self.line - 1].replace(self.old, self.new, 1)
        return "".join(lines)


NAMED = [
    Mutant("viewgcn: selector keeps the least confident candidate", "mvtn_exp/models/viewgcn.py",
           "best = scores.detach().softmax(-1).amax(-1).argmax(-1)", "best = scores.detach().softmax(-1).amax(-1).argmin(-1)"),
    Mutant("viewgcn: nearest-point sampling (argmin)", "mvtn_exp/models/viewgcn.py",
           "idx[:, i] = nearest.argmax(1)", "idx[:, i] = nearest.argmin(1)"),
    Mutant("viewgcn: no non-local message passing", "mvtn_exp/models/viewgcn.py",
           "f, v, s = self.selectors[level](self.nonlocal_mp[level](f), v, keep[level])",
           "f, v, s = self.selectors[level](f, v, keep[level])"),
    Mutant("viewgcn: local graph ignores view positions", "mvtn_exp/models/viewgcn.py",
           "w = self.edge(torch.cat((vi, vj, vi - vj, _safe_norm(vi - vj)), -1))",
           "w = self.edge(torch.cat((vi, vi, vi - vi, _safe_norm(vi - vi)), -1))"),
    Mutant("viewgcn: always the first candidate", "mvtn_exp/models/viewgcn.py",
           "pick = best[..., None, None]", "pick = torch.zeros_like(best)[..., None, None]"),
    Mutant("viewgcn: FPS never starts at random", "mvtn_exp/models/viewgcn.py",
           'random_start = self.training and self.fps_start == "random"', "random_start = False"),
    Mutant("viewgcn: M // 2, M // 4 for every M", "mvtn_exp/models/viewgcn.py",
           "OFFICIAL_LEVEL_VIEWS.get(m, (m // 2, m // 4))", "(m // 2, m // 4)"),
    Mutant("dgcnn: graph built once from xyz", "mvtn_exp/models/dgcnn.py",
           "idx = knn(x.detach(), k)",
           'old = edge_features.__dict__.get("idx")  # the xyz graph of this forward, reused by later layers\n'
           '    reuse = x.shape[1] > 3 and old is not None and tuple(old.shape[:2]) == (x.shape[0], x.shape[2])\n'
           '    idx = old if reuse else knn(x.detach(), k)\n'
           '    edge_features.idx = idx'),
    Mutant("dgcnn: neighbours from the first three channels", "mvtn_exp/models/dgcnn.py",
           "idx = knn(x.detach(), k)", "idx = knn(x.detach()[:, :3], k)"),
    Mutant("dgcnn: edge feature without the centre", "mvtn_exp/models/dgcnn.py",
           "torch.cat([nb - centre, centre], dim=3)", "torch.cat([nb, centre], dim=3)"),
    Mutant("vit: position embedding cropped", "mvtn_exp/models/vit.py",
           'grid = F.interpolate(grid, size=(gh, gw), mode="bicubic", align_corners=False)',
           "grid = grid[:, :, :gh, :gw]"),
    Mutant("vit: class token without position", "mvtn_exp/models/vit.py",
           "return torch.cat([self.pos_embed[:, :1], grid.flatten(2).transpose(1, 2)], dim=1)",
           "return torch.cat([torch.zeros_like(self.pos_embed[:, :1]), grid.flatten(2).transpose(1, 2)], dim=1)"),
    Mutant("mvcnn: mean pooling where max is asked", "mvtn_exp/models/multiview.py",
           'return feats.amax(dim=1) if self.pool == "max" else feats.mean(dim=1)', "return feats.mean(dim=1)"),
    Mutant("backbones: ImageNet scaling not applied", "mvtn_exp/models/multiview.py",
           "images = (images - self.input_mean.to(images.dtype)) / self.input_std.to(images.dtype)", "pass"),
    Mutant("retrieval: NDCG grades synset-only pairs 2", "mvtn_exp/tasks/retrieval.py",
           "exact = np.array([d == query_sub for d in db_subs], dtype=bool)",
           "exact = np.array([d is not None and d == query_sub for d in db_subs], dtype=bool)"),
    Mutant("retrieval: mAP over the retrieved relevant only", "mvtn_exp/tasks/retrieval.py",
           'per["mAP"][j] = float(np.sum((np.cumsum(rel) / ranks)[rel]) / n_rel) if n_rel else 0.0',
           'per["mAP"][j] = float(np.sum((np.cumsum(rel) / ranks)[rel]) / max(1, rel.sum())) if n_rel else 0.0'),
    Mutant("retrieval: plain DCG discount from rank 1", "mvtn_exp/tasks/retrieval.py",
           "return float(gains[0] + np.sum(gains[1:] / np.log2(np.arange(2, gains.size + 1))))",
           "return float(np.sum(gains / np.log2(np.arange(2, gains.size + 2))))"),
    Mutant("fixed: circular azimuths from 0", "mvtn_exp/selectors/fixed.py",
           "device=points.device, dtype=self._dtype(points), azim_start=self.azim_start)",
           "device=points.device, dtype=self._dtype(points))"),
    Mutant("fixed: random views frozen at evaluation", "mvtn_exp/selectors/fixed.py",
           'elif self.eval_draw == "fresh":', "elif False:"),
    Mutant("mvtn: circular u0 offsets bounded by 360 / M", "mvtn_exp/selectors/mvtn.py",
           'azim_bound = 180.0 if variant.startswith("direct") else 180.0 / M',
           'azim_bound = 180.0 if variant.startswith("direct") else 360.0 / M'),
]

# operator mutants: (regular expression of the source token, its replacement)
SWAPS = {ast.Lt: "<=", ast.LtE: "<", ast.Gt: ">=", ast.GtE: ">", ast.Eq: "!=", ast.NotEq: "==",
         ast.Add: "-", ast.Sub: "+", ast.Mult: "/", ast.Div: "*"}
TOKENS = {ast.Lt: "<", ast.LtE: "<=", ast.Gt: ">", ast.GtE: ">=", ast.Eq: "==", ast.NotEq: "!=",
          ast.Add: "+", ast.Sub: "-", ast.Mult: "*", ast.Div: "/"}
CALLS = {"argmax": "argmin", "argmin": "argmax", "amax": "amin", "amin": "amax", "topk": "topk",
         "softmax": "log_softmax", "clamp_min": "clamp_max", "minimum": "maximum", "maximum": "minimum"}


def operator_mutants(path: Path) -> list[Mutant]:
    """Every one-token swap of ``path`` (a module under mvtn_exp/), as a ``Mutant`` of one line."""
    text = path.read_text()
    lines = text.splitlines(keepends=True)
    rel = str(path.relative_to(ROOT))
    out: list[Mutant] = []
    seen: set[tuple[int, str, str]] = set()

    def add(lineno: int, old: str, new: str, what: str) -> None:
        line = lines[lineno - 1]
        if line.count(old) != 1 or line.lstrip().startswith(("#", '"', "'")) or (lineno, old, new) in seen:
            return
        seen.add((lineno, old, new))
        out.append(Mutant(f"{path.stem}:{lineno}: {what}", rel, old, new, lineno))

    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.Compare) and len(node.ops) == 1 and type(node.ops[0]) in SWAPS:
            op = type(node.ops[0])
            add(node.lineno, f" {TOKENS[op]} ", f" {SWAPS[op]} ", f"{TOKENS[op]} -> {SWAPS[op]}")
        elif isinstance(node, ast.BinOp) and type(node.op) in SWAPS and node.lineno == node.end_lineno:
            op = type(node.op)
            add(node.lineno, f" {TOKENS[op]} ", f" {SWAPS[op]} ", f"{TOKENS[op]} -> {SWAPS[op]}")
        elif isinstance(node, ast.Attribute) and node.attr in CALLS and CALLS[node.attr] != node.attr:
            add(node.lineno, f".{node.attr}(", f".{CALLS[node.attr]}(", f"{node.attr} -> {CALLS[node.attr]}")
        elif isinstance(node, ast.Constant) and isinstance(node.value, bool):
            add(node.lineno, f"={node.value}", f"={not node.value}", f"{node.value} -> {not node.value}")
    return out


# the test files that test each module (by stem); other modules: the test files importing them
TEST_FILES = {
    "viewgcn": ("test_method_parts", "test_model_zoo", "test_multiview"),
    "dgcnn": ("test_method_parts", "test_point_encoders", "test_model_zoo"),
    "vit": ("test_method_parts", "test_backbones", "test_model_zoo"),
    "multiview": ("test_multiview", "test_method_parts", "test_model_zoo"),
    "backbones": ("test_backbones", "test_method_parts", "test_multiview"),
    "view_transformer": ("test_model_zoo", "test_multiview", "test_method_parts"),
    "point_encoders": ("test_point_encoders", "test_model_zoo", "test_method_parts"),
    "pooled_layer": ("test_point_encoders",),
    "sync_bn": ("test_sync_bn",),
    "precision": ("test_precision_ema",),
    "retrieval": ("test_retrieval", "test_eval_modes"),
    "robustness": ("test_robustness",),
    "classification": ("test_train_e2e", "test_view_gradient"),
    "fixed": ("test_selectors", "test_method_parts", "test_cameras_layouts"),
    "mvtn": ("test_selectors", "test_selector_options", "test_g_capacity"),
    "config": ("test_selector_options", "test_selectors", "test_config"),
    "canonical": ("test_canonical",),
    "hypotheses": ("test_hypotheses",),
    "invariant_cache": ("test_invariant_cache",),
    "polarity": ("test_polarity",),
    "search": ("test_search",),
    "probes": ("test_view_gradient", "test_selectors"),
    "poi": ("test_selectors", "test_selector_options", "test_hypotheses"),
    "optimized": ("test_model_zoo",),
    "training": ("test_selector_options", "test_view_gradient", "test_precise_bn"),
}


def tests_for(path: str, tests_dir: Path) -> list[str]:
    """Test files (relative to the tree) for the module at ``path``: ``TEST_FILES`` by its stem,
    else those importing it; only the files that exist in ``tests_dir``."""
    stem = Path(path).stem
    if stem in TEST_FILES:
        names = [f"{n}.py" for n in TEST_FILES[stem]]
    else:
        dotted = path[:-3].replace("/", ".")
        names = [p.name for p in tests_dir.glob("test_*.py") if dotted in p.read_text()]
    return sorted(f"tests/{n}" for n in names if (tests_dir / n).is_file())


def make_tree(tests_rev: str | None) -> Path:
    """A copy of this tree (package, configs, tests) in a temporary folder; the tests of ``tests_rev``
    when given (its test files, conftest included)."""
    tmp = Path(tempfile.mkdtemp(prefix="mutants-"))
    for name in ("mvtn_exp", "tests", "configs", "hydra_plugins", "pyproject.toml", "README.md", "docs", "scripts"):
        src = ROOT / name
        if src.is_dir():
            shutil.copytree(src, tmp / name, ignore=shutil.ignore_patterns("__pycache__"))
        elif src.exists():
            shutil.copy2(src, tmp / name)
    if tests_rev:
        shutil.rmtree(tmp / "tests")
        (tmp / "tests").mkdir()
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", tests_rev, "tests"], check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(tmp)], input=archive, check=True)
    return tmp


def _pytest(tree: Path, args: list[str], timeout: float):
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1", PYTHONDONTWRITEBYTECODE="1")
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:xdist", *args]
    return subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True, timeout=timeout)


def failing_unmutated(tree: Path, files: list[str], timeout: float) -> list[str]:
    """Test ids that fail on the unmutated tree (tests of another commit may): left out of every
    mutant's run, so a mutant is killed only by a test that passes without it."""
    proc = _pytest(tree, ["-rf", *files], timeout)
    return re.findall(r"^FAILED (\S+)", proc.stdout, flags=re.M)


def run_tests(tree: Path, files: list[str], timeout: float, deselect=()) -> str:
    """``killed`` / ``survived`` / ``timeout`` for the test ``files`` in ``tree``."""
    try:
        proc = _pytest(tree, ["-x", *files, *[f"--deselect={t}" for t in deselect]], timeout)
    except subprocess.TimeoutExpired:
        return "timeout"
    return "survived" if proc.returncode == 0 else "killed"


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tests-rev", help="run the test files of this git commit (the 'before' of a change)")
    ap.add_argument("--auto", type=int, default=0, help="operator mutants drawn per module (seeded)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", default="", help="mutants whose name contains this text")
    ap.add_argument("--no-named", action="store_true", help="operator mutants only")
    ap.add_argument("--timeout", type=float, default=600.0, help="seconds per mutant (a timeout counts as killed)")
    ap.add_argument("--list", action="store_true", help="list the mutants and their test files, run nothing")
    ap.add_argument("--out", default="outputs/mutation", help="folder for mutants.json")
    ap.add_argument("--rerun", metavar="JSON", help="a mutants.json: run its survivors again, keep its other outcomes")
    ap.add_argument("--compare", nargs=2, metavar=("BEFORE", "AFTER"), help="two mutants.json: per module, side by side")
    return ap


def main(argv=None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    if args.compare:
        print(side_by_side(*(json.loads(Path(p).read_text()) for p in args.compare)))
        return 0

    mutants = [] if args.no_named else list(NAMED)
    rng = random.Random(args.seed)
    for pkg in PACKAGES:
        for path in sorted((ROOT / "mvtn_exp" / pkg).glob("*.py")):
            cands = operator_mutants(path)
            mutants += rng.sample(cands, min(args.auto, len(cands)))
    mutants = [m for m in mutants if args.only in m.name]
    kept = []
    if args.rerun:
        previous = json.loads(Path(args.rerun).read_text())["results"]
        again = {r["name"] for r in previous if r["outcome"] == "survived"} & {m.name for m in mutants}
        kept = [r for r in previous if r["name"] not in again]
        mutants = [m for m in mutants if m.name in again]
    for m in mutants:
        if not m.line and (ROOT / m.path).read_text().count(m.old) != 1:
            print(f"mutation_check: mutant {m.name!r}: its text is not found once in {m.path}", file=sys.stderr)
            return 2
    tree = make_tree(args.tests_rev)
    results, broken = [], {}
    try:
        for i, m in enumerate(mutants, 1):
            files = tests_for(m.path, tree / "tests")
            if args.list:
                print(f"{m.name}  [{', '.join(files) or 'no tests'}]")
                continue
            key = tuple(files)
            if files and key not in broken:
                broken[key] = failing_unmutated(tree, files, args.timeout)
                if broken[key]:
                    print(f"left out (they fail without a mutant): {', '.join(broken[key])}", flush=True)
            target = tree / m.path
            original = target.read_text()
            target.write_text(m.apply(original))
            t0 = time.time()
            outcome = run_tests(tree, files, args.timeout, broken.get(key, ())) if files else "survived"
            target.write_text(original)
            results.append({**asdict(m), "module": m.path, "outcome": outcome, "tests": files, "seconds": round(time.time() - t0, 1)})
            print(f"[{i}/{len(mutants)}] {outcome:8s} {m.name} ({time.time() - t0:.0f} s)", flush=True)
    finally:
        shutil.rmtree(tree, ignore_errors=True)
    if args.list:
        return 0
    out = ROOT / args.out
    out.mkdir(parents=True, exist_ok=True)
    results = kept + results
    (out / "mutants.json").write_text(json.dumps({"tests_rev": args.tests_rev, "results": results,
                                                  "left_out": {" ".join(k): v for k, v in broken.items() if v}}, indent=1))
    print(table(results, args.tests_rev))
    return 0


def table(results: list[dict], tests_rev: str | None) -> str:
    """Markdown: mutants, killed and the score per module, then the survivors."""
    rows = ["| module | mutants | killed | score |", "|---|---|---|---|"]
    for mod in sorted({r["module"] for r in results}):
        rs = [r for r in results if r["module"] == mod]
        k = sum(r["outcome"] != "survived" for r in rs)
        rows.append(f"| {mod} | {len(rs)} | {k} | {k / len(rs):.0%} |")
    k = sum(r["outcome"] != "survived" for r in results)
    rows.append(f"| all | {len(results)} | {k} | {k / max(1, len(results)):.0%} |")
    head = f"Tests: {'commit ' + tests_rev if tests_rev else 'this tree'}.\n\n"
    surv = [f"- survived: {r['name']}" for r in results if r["outcome"] == "survived"]
    return head + "\n".join(rows) + ("\n\n" + "\n".join(surv) if surv else "")


def side_by_side(before: dict, after: dict) -> str:
    """Markdown: per module, the mutants and how many each run killed (mutants matched by name)."""
    b = {r["name"]: r["outcome"] != "survived" for r in before["results"]}
    rows = [f"| module | mutants | killed, tests of {before.get('tests_rev') or 'this tree'} | killed, tests of "
            f"{after.get('tests_rev') or 'this tree'} |", "|---|---|---|---|"]
    tot = [0, 0, 0]
    for mod in sorted({r["module"] for r in after["results"]}):
        rs = [r for r in after["results"] if r["module"] == mod and r["name"] in b]
        kb, ka = sum(b[r["name"]] for r in rs), sum(r["outcome"] != "survived" for r in rs)
        rows.append(f"| {mod} | {len(rs)} | {kb} ({kb / max(1, len(rs)):.0%}) | {ka} ({ka / max(1, len(rs)):.0%}) |")
        tot = [tot[0] + len(rs), tot[1] + kb, tot[2] + ka]
    rows.append(f"| all | {tot[0]} | {tot[1]} ({tot[1] / max(1, tot[0]):.0%}) | {tot[2]} ({tot[2] / max(1, tot[0]):.0%}) |")
    return "\n".join(rows)


if __name__ == "__main__":
    sys.exit(main())
