"""What a command prints about itself: ``--help`` (its groups, options and keys), ``--list KIND``
and ``--version``; a reader that closes the pipe early ends the command quietly."""
from __future__ import annotations

import dataclasses
import importlib
import os
import sys
from pathlib import Path
from typing import Optional

CONF_MODULE = "mvtn_exp.conf"


def package_conf(config_module: str) -> Path:
    """The folder of a config package (``mvtn_exp.conf`` -> ``.../mvtn_exp/conf``)."""
    return Path(importlib.import_module(config_module).__file__).parent


def _choices(compose, config_name: str, overrides: list[str]) -> dict:
    try:
        cfg = compose(config_name, overrides=overrides, return_hydra_config=True)
    except Exception:
        return {}
    return {k: v for k, v in cfg.hydra.runtime.choices.items() if not k.startswith("hydra")}


def package_version() -> str:
    """The installed ``mvtn-exp`` version (``unknown`` when the package is not installed)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("mvtn-exp")
    except PackageNotFoundError:
        return "unknown"


def out(text: str) -> None:
    """Print ``text`` to stdout; a reader that closes the pipe early (``--help | head -1``) ends the
    command quietly, exit 0, instead of a ``BrokenPipeError`` traceback."""
    try:
        print(text, flush=True)
    except BrokenPipeError:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # (nothing more reaches the closed pipe)
        sys.exit(0)


DESCRIPTIONS = {
    "mvtn-train": "train MVTN end to end: view selector G -> renderer R -> multi-view network C -> task head",
    "mvtn-eval": "evaluate a checkpoint: classification, robustness=rotation|occlusion, task=retrieval",
    "mvtn-render": "render M views of a mesh or point cloud into a run dir",
    "mvtn-prepare": "preprocess (cache) a real dataset once, reporting skipped files",
}
NOT_GROUPS = ("evaluate", "hydra", "__pycache__")  # folders of the config package that are not choosable groups


def list_kinds() -> list[str]:
    """What ``--list`` takes: the option kinds (``config/options.py``), then ``experiment``."""
    from .options import OPTIONS

    return [*OPTIONS, "experiment"]


def list_experiments(config_module: str = CONF_MODULE) -> list[tuple[str, str]]:
    """``(name, first comment line)`` of every packaged ``experiment/NAME.yaml``, sorted by name
    (Hydra's ``# @package`` line skipped)."""
    rows = []
    for path in sorted((package_conf(config_module) / "experiment").glob("*.yaml")):
        comments = (ln.lstrip("#").strip() for ln in path.read_text().splitlines() if ln.startswith("#"))
        rows.append((path.stem, next((c for c in comments if c and not c.startswith("@package")), "")))
    return rows


def print_list(prog: str, argv: list[str], config_module: str = CONF_MODULE) -> int:
    """``--list KIND`` (or ``--list=KIND``): one line ``name  summary`` per option on stdout, 0; a
    missing or unknown KIND: one line on stderr naming the kinds, 2."""
    from .options import list_options

    at = next(i for i, a in enumerate(argv) if a == "--list" or a.startswith("--list="))
    kind = argv[at].partition("=")[2] or (argv[at + 1] if at + 1 < len(argv) else "")
    if kind not in list_kinds():
        print(f"{prog}: error: --list {kind or '(no kind)'}: expected one of {', '.join(list_kinds())}",
              file=sys.stderr)
        return 2
    rows = list_experiments(config_module) if kind == "experiment" else list_options(kind)
    width = max((len(name) for name, _ in rows), default=0)
    for name, text in rows:
        out(f"{name:<{width}}  {text}".rstrip())
    return 0


def project_help(prog: str, config_name: str, schema, config_module: str = CONF_MODULE,
                 overrides: Optional[list] = None) -> str:
    """This project's ``--help``: the command, its config groups and options (defaults marked *, or
    the options chosen in ``overrides``), and the keys of the composed config (a group's keys are
    those of its chosen option: ``selector=poi --help`` lists poi's)."""
    from hydra import compose, initialize_config_module

    conf = package_conf(config_module)
    groups_only = [o for o in (overrides or []) if "=" in o and "." not in o.split("=", 1)[0]
                   and not o.startswith("-")]
    composed = None
    with initialize_config_module(version_base="1.3", config_module=config_module):
        chosen = _choices(compose, config_name, groups_only)
        try:
            composed = compose(config_name, overrides=groups_only)
        except Exception:
            composed = None
    groups = sorted(d.name for d in conf.iterdir() if d.is_dir() and d.name not in NOT_GROUPS)
    lines = [f"{prog} (mvtn-exp {package_version()}): {DESCRIPTIONS.get(prog, '')}", "",
             f"usage: {prog} " + ("[group=option ...] " if groups else "") + "[key=value ...]"
             + (" [-m key=a,b ...]" if prog == "mvtn-train" else ""), ""]
    if groups:
        lines.append("Config groups (group=option; * = default, or chosen on this command line; experiment: +experiment=NAME):")
        for g in groups:
            opts = sorted(f.stem for f in (conf / g).glob("*.yaml"))
            lines.append(f"  {g:<14} " + ", ".join(o + ("*" if chosen.get(g) == o else "") for o in opts))
        lines.append("")
    lines.append("Keys (key=value; the whole composed tree: --cfg job):")
    flat, nested = [], []
    for f in dataclasses.fields(schema):
        default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        node = composed.get(f.name) if composed is not None else None
        if dataclasses.is_dataclass(default) and hasattr(node, "keys"):
            nested.append(f"  {f.name}." + "{" + ",".join(str(k) for k in node.keys()) + "}")
        elif dataclasses.is_dataclass(default):
            nested.append(f"  {f.name}." + "{" + ",".join(x.name for x in dataclasses.fields(default)) + "}")
        else:
            flat.append(f"{f.name}={'???' if default is dataclasses.MISSING else default}")
    lines += ["  " + "  ".join(flat[i:i + 6]) for i in range(0, len(flat), 6)] + nested
    lines += ["", "Bad input is one line on stderr naming the key and what is allowed, exit code 2.",
              f"--list KIND: each option of a kind with one line on it (KIND: {', '.join(list_kinds())}).",
              "--version: the package version; --hydra-help: Hydra's own flags; README.md: the full documentation."]
    return "\n".join(lines)
