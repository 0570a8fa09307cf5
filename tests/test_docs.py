"""The docs cannot rot: every command in a fenced ``bash`` / ``sh`` / ``console`` block of README.md
and docs/**/*.md is checked, one test per command (test id = file:line).

How a command is checked, without running it (in-process, so the whole file takes seconds):

- ``mvtn-train ...`` (also inside ``torchrun ... $(which mvtn-train) ...``, and ``-m`` sweeps):
  the command line goes through ``config.compose.check_overrides``, the check ``mvtn-train`` itself runs
  before anything else (unknown keys and group options, wrong types, every value of every swept key,
  ``+key`` outside the schema, launchers), with ``engine.trainer.as_config`` as its validation, so
  a bad value is caught too, not only a bad key. ``--cfg job`` is dropped and the rest composed;
  ``--help`` / ``--version`` must exit 0; ``--summary DIR`` / ``--resume-sweep DIR`` take one folder.
- ``mvtn-prepare`` composes ``conf/prepare.yaml`` the same way; ``mvtn-eval`` ``conf/evaluate/eval.yaml``
  (validated by ``EvalConfig.validate``); ``mvtn-render`` ``conf/render.yaml`` (layout and renderer
  settings validated as ``render_file`` does); ``mvtn-bench`` ``conf/bench.yaml`` (its threads check);
  ``mvtn-tradeoff`` takes one folder; ``mvtn-report`` and ``mvtn-compare`` their own parsers, and with ``--run`` every side composed as ``mvtn-train`` does.
- ``make TARGET``: the target exists in the Makefile.
- ``python -m MODULE ...``: the module is found (``importlib.util.find_spec``); ``key=value``
  arguments of ``python -m mvtn_exp...`` probes are ``mvtn-train`` overrides and are composed too.
- ``python scripts/studies/NAME.py ...``: the script exists; its ``key=value`` arguments are
  ``mvtn-train`` overrides and are composed.
- Anything else fails unless ``ALLOWED`` below lists it, with the reason; repository paths it names
  must exist.

Placeholder paths (``ckpt=outputs/train/runs/RUN/best.pt``) compose like real ones: no file is
read. ``device=cuda`` composes as on a CUDA machine (CUDA is reported available while checking).
Also: the Python blocks run, internal links and their #anchors resolve, and README.md stays a
manual (Results at most 600 words in at most three tables, the held-out row first, no commit
hashes; no dated entries; a link to every docs page).
"""
from __future__ import annotations

import importlib.util
import os
import re
import shlex
import subprocess
import sys
import types
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").rglob("*.md"))
DOC_FILES = [README, *DOCS]
SHELL_LANGS = ("bash", "sh", "console")

# Commands that are not this project's CLIs. Each entry: a regular expression the whole command
# must match, and why it is not checked further. Repository paths a listed command names
# (scripts/...) must still exist.
ALLOWED = [
    (r"tensorboard --logdir \S+", "TensorBoard's own CLI (installed with the package); reads any folder"),
    (r"scripts/study_tradeoff\.sh", "the trade-off study (1.5 hours); the sweeps it runs are the "
     "+experiment=tradeoff_synthetic(_views) commands, checked on their own"),
    (r"python scripts/verify_dataset\.py \S+ \S+( --(manifest|check) \S+)?", "needs a real dataset copy"),
    (r"python scripts/device_check\.py \S+( --dry-run)?", "the prepared GPU check; its dry run is tests/test_device_check.py"),
    (r"python3 -m venv \.venv && \. \.venv/bin/activate", "the GPU quickstart's environment (make install does the same)"),
    (r"pip install (torch==2\.13\.0|-e \.)", "the GPU quickstart's install steps, as the Makefile's install target"),
    (r"python -c \"import torch; print\(torch\.cuda\.is_available\(\)\)\"", "asks torch whether it sees a GPU"),
]


# ----------------------------------------------------------------------------- extraction
def fenced_blocks(path: Path, langs) -> list[tuple[int, str, list[tuple[int, str]]]]:
    """[(line of the opening fence, language, [(line number, text), ...])] of ``path``."""
    blocks, current, lang, start = [], None, "", 0
    for n, line in enumerate(path.read_text().splitlines(), 1):
        stripped = line.strip()
        if current is None:
            m = re.match(r"^```\s*([\w+-]*)", stripped)
            if m:
                current, lang, start = [], m.group(1).lower(), n
        elif stripped.startswith("```"):
            if lang in langs:
                blocks.append((start, lang, current))
            current = None
        else:
            current.append((n, line))
    return blocks


def doc_commands() -> list[tuple[str, str]]:
    """[(file:line, command)] of every shell command in the docs (continuation lines joined,
    console blocks: the ``$ `` lines only)."""
    out = []
    for path in DOC_FILES:
        rel = path.relative_to(ROOT).as_posix()
        for _, lang, lines in fenced_blocks(path, SHELL_LANGS):
            pending, first = "", 0
            for n, text in lines:
                if lang == "console":
                    if not text.startswith("$ ") and not pending:
                        continue
                    text = text[2:] if text.startswith("$ ") else text
                if not pending:
                    first = n
                if text.rstrip().endswith("\\"):
                    pending += text.rstrip()[:-1] + " "
                    continue
                cmd = (pending + text).strip()
                pending = ""
                if cmd and not cmd.startswith("#"):
                    out.append((f"{rel}:{first}", cmd))
    return out


COMMANDS = doc_commands()


# ----------------------------------------------------------------------------- checks
_CACHE: dict[tuple, str | None] = {}
SEED = re.compile(r"^seed=\d+$")


def _check_once(prog: str, argv: list[str], capsys, **kwargs) -> str | None:
    """``check_overrides(prog, argv=argv, ...)`` as the CLI calls it -> None if it passes, else its
    one line. First without its ``_choices`` pass (a second composition that only names the file in
    an error message: half the time); on a failure again with it, for the CLI's exact message."""
    from mvtn_exp.config import compose as common

    def attempt(fast: bool) -> str | None:
        capsys.readouterr()
        try:
            with pytest.MonkeyPatch.context() as mp:
                if fast:
                    mp.setattr(common, "_choices", lambda *a, **k: {}, raising=False)
                common.check_overrides(prog, argv=argv, **kwargs)
            return None
        except SystemExit as exc:
            return None if exc.code == 0 else (capsys.readouterr().err.strip() or f"exit {exc.code}")
        except Exception as exc:  # a check that raises instead of exiting is a failure too
            return f"{type(exc).__name__}: {exc}"
        finally:
            capsys.readouterr()

    return attempt(True) and attempt(False)


def _run_check(prog: str, argv: list[str], capsys, **kwargs) -> str | None:
    """The CLI's pre-run check of ``argv``. A ``-m`` sweep is checked as ``check_overrides`` checks
    it, one variant at a time (``sweep_variants``: the first value of every swept key, then each
    other value on its own), so that variants shared by several commands are composed once.
    ``seed=N`` does not change what composes (a top-level int, checked >= 0), so variants that differ
    only in it share one check."""
    from mvtn_exp.config.compose import MULTIRUN_FLAGS, sweep_variants

    if not any(a in MULTIRUN_FLAGS for a in argv):
        variants = [argv]
    else:
        hydra_args = [a for a in argv if a.lstrip("+~").startswith(("hydra.", "hydra/"))]
        rest = [a for a in argv if a not in MULTIRUN_FLAGS and a not in hydra_args]
        try:
            variants = [hydra_args + v for v in sweep_variants(rest)]
        except Exception as exc:
            return f"sweep overrides do not parse: {exc}"
    for variant in variants:
        key = (prog, tuple("seed=0" if SEED.match(a) else a for a in variant), os.environ.get("MVTN_CONFIGS"))
        if key not in _CACHE:
            _CACHE[key] = _check_once(prog, variant, capsys, **kwargs)
        if _CACHE[key] is not None:
            return _CACHE[key]
    return None


def _train_validate(obj):
    from mvtn_exp.engine.trainer import as_config

    return as_config(obj)  # the schema merge and TrainConfig.validate: bad values, not only bad keys


def _render_validate(obj):
    from omegaconf import OmegaConf

    from mvtn_exp.cli.render import LAYOUTS
    from mvtn_exp.render.config import RendererConfig

    if obj.layout not in LAYOUTS:
        raise ValueError(f"layout={obj.layout!r}: expected one of {list(LAYOUTS)}")
    rcfg = RendererConfig(**{**OmegaConf.to_container(OmegaConf.structured(obj.renderer)), "image_size": obj.image_size})
    rcfg.validate()


def _bench_validate(obj):
    if obj.threads is not None and obj.threads < 1:
        raise ValueError(f"threads={obj.threads}: expected >= 1 or null")


INFO_WITH_VALUE = ("--cfg", "-c", "--info", "-i", "--package", "-p")
INFO_FLAGS = ("--resolve",)


def check_train(argv: list[str], capsys, prog: str = "mvtn-train", config_name: str = "train") -> str | None:
    from mvtn_exp.config.schema import TrainConfig
    from mvtn_exp.config.store import register_configs

    register_configs()
    if argv[:1] in (["--summary"], ["--resume-sweep"]):
        return None if len(argv) == 2 else f"{argv[0]} takes one sweep folder"
    kept, skip = [], False
    for a in argv:  # --cfg job etc. only print the config: check the config they would print
        if skip:
            skip = False
        elif a in INFO_WITH_VALUE:
            skip = True
        elif a not in INFO_FLAGS:
            kept.append(a)
    return _run_check(prog, kept, capsys, config_name=config_name, schema=TrainConfig, validate=_train_validate)


def check_eval(argv, capsys):
    from mvtn_exp.config.store import register_configs
    from mvtn_exp.config.eval_schema import EvalConfig

    register_configs()
    return _run_check("mvtn-eval", argv, capsys, config_name="eval", schema=EvalConfig,
                      validate=EvalConfig.validate, config_module="mvtn_exp.conf.evaluate")


def check_render(argv, capsys):
    from mvtn_exp.cli.render import RenderAppConfig  # registers render_schema

    return _run_check("mvtn-render", argv, capsys, config_name="render", schema=RenderAppConfig,
                      validate=_render_validate)


def check_bench(argv, capsys):
    from mvtn_exp.cli.bench import BenchAppConfig  # registers bench_schema

    return _run_check("mvtn-bench", argv, capsys, config_name="bench", schema=BenchAppConfig,
                      validate=_bench_validate)


def check_tradeoff(argv, capsys):
    """mvtn-tradeoff's own parser (a folder, --metric, --against)."""
    from mvtn_exp.cli.tradeoff import build_parser

    if {"--version", "-h", "--help"} & set(argv):
        return None
    try:
        build_parser().parse_args(argv)
    except SystemExit:
        return f"mvtn-tradeoff refuses {argv}: {capsys.readouterr().err.strip()}"
    return None


def check_compare(argv, capsys):
    """mvtn-compare's own parser; with --run, every side's overrides (with the common ones) as mvtn-train composes them."""
    from mvtn_exp.cli.compare import build_parser

    try:
        args = build_parser().parse_args(argv)
    except SystemExit:
        return capsys.readouterr().err.strip() or "mvtn-compare: bad arguments"
    for side in args.run or []:
        problem = check_train([*args.items, *side.split()], capsys)
        if problem:
            return problem
    return None


def check_report(argv, capsys):
    """mvtn-report's own parser."""
    from mvtn_exp.cli.report import build_parser

    try:
        build_parser().parse_args(argv)
    except SystemExit:
        return capsys.readouterr().err.strip() or "mvtn-report: bad arguments"
    return None


def makefile_targets() -> set[str]:
    return set(re.findall(r"^([A-Za-z0-9_.-]+):", (ROOT / "Makefile").read_text(), flags=re.M))


def check_make(argv, capsys):
    targets = [a for a in argv if "=" not in a and not a.startswith("-")]
    missing = [t for t in targets if t not in makefile_targets()]
    return f"no Makefile target {missing}" if missing else None


def check_python(argv, capsys):
    if argv[:1] and argv[0].startswith("scripts/studies/") and argv[0].endswith(".py"):  # research probes
        if not (ROOT / argv[0]).is_file():
            return f"python {argv[0]}: no such script"
        args = [a for i, a in enumerate(argv[1:]) if not (i and argv[i].startswith("--") and "=" not in argv[i])]
        overrides = [a for a in args if "=" in a and not a.startswith("-")]  # --flag VALUE: the flag's value
        return check_train(overrides, capsys) if overrides else None
    if argv[:1] == ["scripts/mutation_check.py"]:  # its own parser
        spec = importlib.util.spec_from_file_location("mutation_check", ROOT / argv[0])
        module = importlib.util.module_from_spec(spec)
        sys.modules.setdefault("mutation_check", module)  # its dataclasses look their module up
        spec.loader.exec_module(module)
        try:
            module.build_parser().parse_args(argv[1:])
        except SystemExit:
            return capsys.readouterr().err.strip() or "mutation_check: bad arguments"
        return None
    if argv[:1] != ["-m"] or len(argv) < 2:
        return f"python {' '.join(argv)}: only `python -m MODULE` and `python scripts/studies/NAME.py` are checked; list other forms in ALLOWED"
    module = argv[1]
    try:
        found = importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:
        found = False
    if not found:
        return f"python -m {module}: no such module"
    rest = argv[2:]
    # a --flag's value is not an override (``--learned 'k=v ...'``: the learned side's, checked with the rest)
    overrides = [a for i, a in enumerate(rest) if "=" in a and not a.startswith("-")
                 and not (i and rest[i - 1].startswith("--") and "=" not in rest[i - 1])]
    learned = [v for i, v in enumerate(rest[1:]) if rest[i] == "--learned"]
    if module.startswith("mvtn_exp.") and (overrides or learned):  # probes that take mvtn-train's overrides
        return check_train(overrides + [o for v in learned for o in v.split()], capsys)
    return None


CHECKS = {"mvtn-train": check_train, "mvtn-prepare": lambda a, c: check_train(a, c, "mvtn-prepare", "prepare"),
          "mvtn-eval": check_eval, "mvtn-render": check_render, "mvtn-bench": check_bench,
          "mvtn-tradeoff": check_tradeoff, "mvtn-compare": check_compare, "mvtn-report": check_report, "make": check_make, "python": check_python}
ENV_ASSIGNMENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*=")


def split_command(cmd: str) -> tuple[dict, str, list[str]]:
    """``VAR=x prog args  # comment`` -> ({VAR: x}, prog, args); ``$(which mvtn-train)`` -> mvtn-train;
    ``.venv/bin/prog`` -> prog."""
    cmd = re.sub(r"\$\(which ([\w.-]+)\)", r"\1", cmd)
    tokens = shlex.split(cmd, comments=True)
    env = {}
    while tokens and ENV_ASSIGNMENT.match(tokens[0]):
        k, v = tokens.pop(0).split("=", 1)
        env[k] = v
    if not tokens:
        return env, "", []
    prog = tokens[0]
    if "/" in prog and Path(prog).name.startswith(("mvtn-", "python")):
        prog = Path(prog).name
    if re.fullmatch(r"python3?(\.\d+)?", prog):
        prog = "python"
    return env, prog, tokens[1:]


@pytest.fixture(scope="module")
def as_on_a_cuda_machine():
    """Commands written for a GPU machine (``device=cuda``) compose as they would there; the
    commands' config search starts in the repository root (``configs/`` first)."""
    import torch

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(torch.cuda, "is_available", lambda: True)
        mp.setattr(torch.cuda, "device_count", lambda: 8)
        mp.chdir(ROOT)
        mp.delenv("MVTN_CONFIGS", raising=False)
        yield


def check_command(cmd: str, capsys, monkeypatch) -> str | None:
    """None if ``cmd`` passes its check, else why not."""
    env, prog, args = split_command(cmd)
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    for pattern, _why in ALLOWED:
        if re.fullmatch(pattern, cmd.split("#")[0].strip()):
            missing = [t for t in shlex.split(cmd, comments=True) if t.startswith("scripts/") and not (ROOT / t).exists()]
            return f"names missing files {missing}" if missing else None
    if prog == "torchrun":
        if "mvtn-train" not in [Path(a).name for a in args]:
            return "torchrun must run $(which mvtn-train)"
        at = [Path(a).name for a in args].index("mvtn-train")
        prog, args = "mvtn-train", args[at + 1:]
    if prog not in CHECKS:
        return f"{prog!r} is not a command this test knows; add it to ALLOWED in tests/test_docs.py with a reason"
    return CHECKS[prog](args, capsys)


@pytest.mark.parametrize("cmd", [pytest.param(c, id=where) for where, c in COMMANDS])
def test_doc_command(cmd, capsys, monkeypatch, as_on_a_cuda_machine):
    problem = check_command(cmd, capsys, monkeypatch)
    assert problem is None, f"{cmd}\n-> {problem}"


def test_commands_were_found():
    """The extraction itself works: the README's set-up commands and a sweep are among them."""
    cmds = [c for _, c in COMMANDS]
    assert any(c.startswith("make run") for c in cmds) and any(c.startswith("make test") for c in cmds)
    assert any(" -m " in f" {c} " and c.startswith("mvtn-train") for c in cmds)
    assert len(COMMANDS) > 50


@pytest.mark.parametrize("bad", ["mvtn-train selector=circular optim.lrr=1e-3",
                                 "mvtn-train selector=nope views=1",
                                 "mvtn-train -m selector=circular,nope",
                                 "mvtn-train views=0",
                                 "mvtn-eval ckpt=x.pt robustness=twist",
                                 "mvtn-render input=builtin:torus layout=hexagonal",
                                 "mvtn-bench quick=maybe",
                                 "make no-such-target",
                                 "python -m mvtn_exp.no_such_module",
                                 "rm -rf outputs"])
def test_a_stale_command_fails(bad, capsys, monkeypatch, as_on_a_cuda_machine):
    """The checks catch a misspelled key, a nonexistent option (also in a sweep), a bad value, an
    unknown target or module, and a command nobody listed."""
    assert check_command(bad, capsys, monkeypatch) is not None


# ----------------------------------------------------------------------------- python blocks
PYTHON_BLOCKS = [(f"{p.relative_to(ROOT).as_posix()}:{start}", "\n".join(t for _, t in lines))
                 for p in DOC_FILES for start, _, lines in fenced_blocks(p, ("python",))]


@pytest.mark.parametrize("code", [pytest.param(c, id=w) for w, c in PYTHON_BLOCKS])
def test_doc_python_block_runs(code):
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    module = types.ModuleType("__doc_block__")  # a module of its own, as a user's file is (dataclasses look it up)
    sys.modules[module.__name__] = module
    try:
        exec(compile(code, "<doc block>", "exec"), module.__dict__)
    finally:
        torch.set_num_threads(threads)
        del sys.modules[module.__name__]


# ----------------------------------------------------------------------------- links
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")


def slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    in_code, out = False, set()
    for line in path.read_text().splitlines():
        if line.strip().startswith("```"):
            in_code = not in_code
        elif not in_code and re.match(r"^#{1,6} ", line):
            out.add(slug(line.lstrip("#")))
    return out


def doc_links() -> list[tuple[str, Path, str]]:
    out = []
    for path in DOC_FILES:
        in_code = False
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if line.strip().startswith("```"):
                in_code = not in_code
                continue
            if in_code:
                continue
            for target in LINK.findall(line):
                if not re.match(r"^[a-z]+://|^mailto:", target):
                    out.append((f"{path.relative_to(ROOT).as_posix()}:{n}", path, target))
    return out


@pytest.mark.parametrize("path,target", [pytest.param(p, t, id=f"{w}:{t}") for w, p, t in doc_links()])
def test_internal_link_resolves(path, target):
    file_part, _, anchor = target.partition("#")
    dest = (path.parent / file_part).resolve() if file_part else path
    assert dest.exists(), f"{target}: no such file"
    if anchor and dest.suffix == ".md":
        assert anchor in anchors(dest), f"{target}: no heading with anchor #{anchor} in {dest.name}"


# ----------------------------------------------------------------------------- the README
def test_readme_is_a_manual():
    text = README.read_text()
    lines = text.splitlines()
    results = text[text.index("## Results\n"):text.index("\n## ", text.index("## Results\n") + 1)]
    words = len(results.split())
    assert words <= 600, f"README.md's Results has {words} words (at most 600: move detail to docs/results/)"
    assert len(re.findall(r"^\|---", results, flags=re.M)) <= 3, "README.md's Results: at most three tables"
    first_row = next(ln for ln in results.splitlines() if ln.startswith("| `"))
    assert "held out" in first_row, f"README.md's Results: the held-out row first, got {first_row[:60]!r}"
    assert not re.search(r"\b[0-9a-f]{7}\b", results), "README.md's Results names commits (they stay in docs/results)"
    dated = [n for n, ln in enumerate(lines, 1) if re.search(r"2026-", ln)]
    assert not dated, f"dated entries or headings on README.md lines {dated}"
    headings = [ln for ln in lines if ln.startswith("#") and re.search(r"20\d\d-\d\d", ln)]
    assert not headings, headings
    assert not re.search(r"this session|\bissue \d+", text, flags=re.I), "README.md speaks of sessions or issues"
    linked = {(README.parent / t.partition("#")[0]).resolve() for t in LINK.findall(text)}
    unlinked = [p.relative_to(ROOT).as_posix() for p in DOCS if p.resolve() not in linked]
    assert not unlinked, f"README.md does not link {unlinked}"


EXPERIMENTS = sorted((ROOT / "mvtn_exp" / "conf" / "experiment").glob("*.yaml"))


@pytest.mark.parametrize("path", EXPERIMENTS, ids=[p.stem for p in EXPERIMENTS])
def test_experiment_files_carry_a_short_header_naming_where_the_result_is(path):
    """An experiment file says in at most 5 comment lines what it reproduces and where the result
    is documented (a docs page that exists); no per-seed logs in its comments."""
    lines = path.read_text().splitlines()
    assert lines[0].startswith("# @package _global_")
    header = []
    for line in lines[1:]:
        if not line.startswith("#"):
            break
        header.append(line)
    assert 1 <= len(header) <= 5, f"{path.name}: {len(header)} header lines"
    docs = re.findall(r"docs/[\w/.-]+\.md", " ".join(header))
    assert docs and all((ROOT / d).is_file() for d in docs), f"{path.name}: names no existing docs page"
    comments = [ln for ln in lines if ln.lstrip().startswith("#")]
    assert len(comments) <= 12 and not any(re.search(r"\bseed \d+\b.*\d\.\d{3}", c) for c in comments), path.name


def test_layout_lists_every_module_with_its_role():
    """docs/layout.md's module list is what scripts/write_layout.py makes of the package's docstrings
    (a new module, or a changed first sentence, without the page rewritten fails)."""
    out = subprocess.run([sys.executable, str(ROOT / "scripts" / "write_layout.py"), "--check"], capture_output=True,
                         text=True)
    assert out.returncode == 0, out.stderr
    text = (ROOT / "docs" / "layout.md").read_text()
    for path in (ROOT / "mvtn_exp").rglob("*.py"):
        rel = path.relative_to(ROOT / "mvtn_exp")
        if path.name != "__init__.py" and len(rel.parts) > 1:
            assert f"`{Path(*rel.parts[1:]).as_posix()}`" in text, path
        elif path.name != "__init__.py":
            assert f"`mvtn_exp/{path.name}`" in text, path
