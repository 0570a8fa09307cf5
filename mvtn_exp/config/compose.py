"""A command's config, checked before Hydra runs: the user's overrides against the schemas (one
line naming the key, the file and the allowed keys, exit 2), ``--help``, ``--version`` and ``--list
KIND`` (the options of a kind, one line each) of the project, and ``compose_train_config`` for entry
points outside Hydra's app."""
from __future__ import annotations

import dataclasses
import re
import sys
from pathlib import Path
from typing import Callable, Optional

from omegaconf import OmegaConf

from .help_text import (CONF_MODULE, _choices, out, package_conf, package_version, print_list,  # noqa: F401
                        project_help)

CONF_DIR = CONF_MODULE.replace(".", "/")
# Hydra flags after which we let Hydra handle the command line itself (help, config printing, ...)
HYDRA_INFO_FLAGS = ("--help", "-h", "--hydra-help", "--cfg", "-c", "--info", "-i", "--resolve", "--version",
                    "--shell-completion", "-sc", "--package", "-p", "--config-path", "-cp", "--config-name", "-cn",
                    "--config-dir", "-cd", "--experimental-rerun")
MULTIRUN_FLAGS = ("-m", "--multirun")


def _allowed_keys(node_type, path: list[str]) -> list[str]:
    """Field names of the schema node at ``path`` (a dataclass type), or [] if unknown."""
    for part in path:
        fields = {f.name: f for f in dataclasses.fields(node_type)} if dataclasses.is_dataclass(node_type) else {}
        if part not in fields:
            return []
        node_type = fields[part].type if not isinstance(fields[part].type, str) else None
        if node_type is None:
            default = fields[part].default_factory() if fields[part].default_factory is not dataclasses.MISSING else None
            node_type = type(default) if dataclasses.is_dataclass(default) else None
        if node_type is None:
            return []
    return sorted(f.name for f in dataclasses.fields(node_type)) if dataclasses.is_dataclass(node_type) else []


def describe(exc: Exception, schema) -> tuple[str, str]:
    """(offending key or group, one line: what went wrong and the allowed keys or options)."""
    text = str(exc).strip()
    lines = text.splitlines()
    first = lines[0] if lines else type(exc).__name__
    missing = re.search(r"Could not find '([^']+)'", first)
    if missing:  # an unknown group option: list the available ones
        group = missing.group(1).rsplit("/", 1)[0]
        start = next((i for i, ln in enumerate(lines) if ln.startswith("Available options")), len(lines))
        options = []
        for ln in lines[start + 1:]:
            if not ln.startswith("\t"):
                break
            options.append(ln.strip())
        msg = first.split(": ", 1)[-1] if first.startswith("In '") else first
        return missing.group(1), msg + (f"; available options for {group}: {', '.join(options)}" if options else "")
    key = next((ln.split(":", 1)[1].strip() for ln in lines if ln.strip().startswith("full_key:")), "")
    if not key:  # our own validation errors start with "key=value: ..."
        m = re.match(r"([A-Za-z_][\w.]*)=", first)
        key = m.group(1) if m else ""
    msg = first
    unknown = "not in" in text or "Could not override" in first
    if key and unknown:  # a key of another option (config/options.py)
        from .options import OPTIONS, load

        load()
        option = re.search(r"not in '(\w+)'", text)
        kind, _, sub = key.partition(".")
        name = next((n for n, c in OPTIONS.get(kind, {}).items() if option and c.__name__ == option.group(1)), None)
        if name and sub:
            return key, OPTIONS[kind].foreign_key_message(name, sub)
        if kind in OPTIONS and sub and option:  # a group file that does not start from an option's schema
            return key, (f"{key}: a {kind} file sets the keys of one option and starts from its schema: "
                         f"defaults: [/schema/{kind}/NAME@_here_, _self_] (NAME one of "
                         f"{', '.join(sorted(OPTIONS[kind]))}; configs/README.md)")
    if key and ("not in" in first or "not a valid" in first or "Could not override" in first):
        allowed = _allowed_keys(schema, key.split(".")[:-1])
        if allowed:
            msg += f" (allowed keys here: {', '.join(allowed)})"
    elif key and "full_key" in text:
        msg += f" (key '{key}')"
    return key, msg


def _config_file(key: str, choices: dict, config_name: str, conf_dir: str = CONF_DIR) -> str:
    """The file a key's value comes from: its group's chosen option file, else the primary config."""
    group = key.split(".")[0] if key else ""
    if group in choices and choices[group]:
        return f"{conf_dir}/{group}/{choices[group]}.yaml"
    if "/" in key:  # "experiment/nope"
        return f"{conf_dir}/{key}.yaml"
    return f"{conf_dir}/{config_name}.yaml"


def override_key(override: str) -> str:
    """The dotted key of one command-line override: ``+a.b@pkg=1`` -> ``a.b`` (``+``, ``++``, ``~``
    and a ``@package`` dropped; a flag without ``=`` is its own key)."""
    return override.lstrip("+~").split("=", 1)[0].split("@", 1)[0]


def given(argv: list[str]) -> dict[str, str]:
    """The ``key=value`` overrides of a command line, ``{dotted key: value as typed}`` in order (the
    last of a repeated key wins; one pair of matching quotes around a value removed, as Hydra does)."""
    out = {}
    for a in argv:
        if "=" in a and not a.startswith("-"):
            value = a.split("=", 1)[1]
            if len(value) > 1 and value[0] == value[-1] and value[0] in "'\"":
                value = value[1:-1]
            out[override_key(a)] = value
    return out


def sweep_variants(overrides: list[str]) -> list[list[str]]:
    """The override lists to check for a multirun: the first value of every swept key, and each
    other value of each swept key on its own (so a bad value anywhere is caught, in linear time)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parsed = OverridesParser.create().parse_overrides(overrides)
    base, swept = [], []
    for o in parsed:
        prefix = o.get_key_element()
        if o.is_sweep_override():
            values = list(o.sweep_string_iterator())
            base.append(f"{prefix}={values[0]}")
            swept.append((len(base) - 1, prefix, values[1:]))
        else:
            base.append(o.input_line)
    variants = [base]
    for idx, prefix, rest in swept:
        for v in rest:
            variant = list(base)
            variant[idx] = f"{prefix}={v}"
            variants.append(variant)
    return variants


def unknown_added_key(override: str, schema, conf_dir: Path) -> Optional[str]:
    """The one-line message when ``+key=value`` / ``++key=value`` adds a key the schema does not
    have (Hydra would accept it silently), else None. ``+group=option`` for a config group is fine."""
    if not override.startswith("+"):
        return None
    key = override_key(override)
    if key.startswith(("hydra.", "hydra/")) or key == "hydra":
        return None
    parts = key.split(".")
    if len(parts) == 1 and ((conf_dir / key).is_dir() or "/" in key):
        return None  # a config group (e.g. +experiment=NAME)
    allowed = _allowed_keys(schema, parts[:-1])
    top = [f.name for f in dataclasses.fields(schema)] if len(parts) == 1 else allowed
    if top and parts[-1] not in top:
        return f"{override!r} adds key '{key}', which is not in the schema (allowed keys here: {', '.join(sorted(top))})"
    return None


def check_overrides(prog: str, config_name: str, schema, argv: list[str],
                    validate: Optional[Callable] = None, config_module: str = CONF_MODULE) -> None:
    """Compose ``config_name`` with the command-line overrides (each value of a ``-m`` sweep) and
    run ``validate(cfg_object)``; on a config error print one line naming the key, the config
    file and the allowed keys / options / values, and exit with code 2 (no traceback)."""
    if "--version" in argv:
        out(f"{prog} (mvtn-exp) {package_version()}")
        sys.exit(0)
    if "--help" in argv or "-h" in argv:
        out(project_help(prog, config_name, schema, config_module, overrides=argv))
        sys.exit(0)
    if any(a == "--list" or a.startswith("--list=") for a in argv):
        sys.exit(print_list(prog, argv, config_module))
    _refuse_shadowed_main_config(prog, config_name)
    info = [a for a in argv if a in HYDRA_INFO_FLAGS or a.split("=")[0] in HYDRA_INFO_FLAGS]
    if info and any(a in MULTIRUN_FLAGS for a in argv):
        print(f"{prog}: error: {info[0]} prints one composed config and cannot be combined with -m/--multirun; "
              "drop -m (and give one value per key) to see a sweep job's config", file=sys.stderr)
        sys.exit(2)
    if info:
        return
    from hydra import compose, initialize_config_module

    hydra_groups = [a for a in argv if a.lstrip("+~").startswith("hydra/")]
    if hydra_groups:  # hydra/launcher=..., hydra/sweeper=...: an option that is not installed
        try:
            with initialize_config_module(version_base="1.3", config_module=config_module):
                compose(config_name, overrides=hydra_groups, return_hydra_config=True)
        except Exception as exc:
            _, msg = describe(exc, schema)
            print(f"{prog}: config error in {' '.join(hydra_groups)}: {msg} (launchers are Hydra plugins; mvtn-exp "
                  "installs hydra-joblib-launcher and hydra-submitit-launcher)", file=sys.stderr)
            sys.exit(2)
    overrides = [a for a in argv if a not in MULTIRUN_FLAGS and not a.lstrip("+~").startswith(("hydra.", "hydra/"))]
    conf_dir = config_module.replace(".", "/")
    for o in overrides:
        bad = unknown_added_key(o, schema, package_conf(config_module))
        if bad:
            print(f"{prog}: config error in {conf_dir}/{config_name}.yaml: {bad}", file=sys.stderr)
            sys.exit(2)
    choices: dict = {}
    try:
        variants = sweep_variants(overrides) if any(a in MULTIRUN_FLAGS for a in argv) else [overrides]
        with initialize_config_module(version_base="1.3", config_module=config_module):
            for variant in variants:
                # the group options chosen (to name the file of a bad key), from the group overrides alone
                groups_only = [o for o in variant if "." not in o.split("=", 1)[0]]
                choices = _choices(compose, config_name, groups_only)
                cfg = compose(config_name, overrides=variant)
                OmegaConf.set_struct(cfg, False)
                obj = OmegaConf.to_object(cfg)
                if validate is not None:
                    validate(obj)
    except Exception as exc:  # composition, type and validation errors
        cause, link = exc, exc  # prefer the innermost error that names the key
        while link is not None:
            cause = link if "full_key:" in str(link) else cause
            link = link.__cause__ or link.__context__
        key, msg = describe(cause, schema)
        source, yaml_error = _source_file(exc, key, config_module), _yaml_mark(exc)
        if yaml_error is not None:  # a file that is not YAML: its parser's words
            msg = "; ".join(ln.strip() for ln in str(yaml_error).splitlines() if not ln.strip().startswith("in \""))
        where = source or _config_file(key, choices, config_name, conf_dir)
        print(f"{prog}: config error in {where}: {msg}", file=sys.stderr)
        sys.exit(2)


def user_configs() -> Path:
    """The user's config folder the commands search first (``MVTN_CONFIGS``, else ``./configs``;
    ``hydra_plugins/mvtn_exp_project_configs``)."""
    import os

    return Path(os.environ.get("MVTN_CONFIGS", "configs"))


def _refuse_shadowed_main_config(prog: str, config_name: str) -> None:
    """A user's ``configs/<main config>.yaml`` (e.g. ``configs/train.yaml``) would replace the command's
    whole config (Hydra searches ``configs/`` first): one line, exit 2."""
    shadow = user_configs() / f"{config_name}.yaml"
    if shadow.is_file():
        print(f"{prog}: config error in {shadow}: a file named like {prog}'s main config would replace all of it; "
              f"rename it (a setup of your own: configs/experiment/NAME.yaml, used with +experiment=NAME)",
              file=sys.stderr)
        sys.exit(2)


def _yaml_mark(exc):
    """The YAML parser's error in ``exc``'s chain (it carries ``problem_mark``: file and line), or None."""
    while exc is not None:
        if getattr(exc, "problem_mark", None) is not None:
            return exc
        exc = exc.__cause__ or exc.__context__
    return None


def _source_file(exc, key: str, config_module: str) -> Optional[str]:
    """``path:line`` of the config file an error arose in, when Hydra names one (``In 'experiment/x'``)
    or YAML could not parse it: a user's ``configs/`` file (``MVTN_CONFIGS``) before the packaged
    one of that name, the line of ``key``'s last part in it when found."""
    yaml_error = _yaml_mark(exc)
    if yaml_error is not None:
        mark = yaml_error.problem_mark
        return f"{mark.name}:{mark.line + 1}"
    m = re.match(r"In '([\w./-]+)'", str(exc))
    if not m:
        return None
    rel = f"{m.group(1)}.yaml"
    user = user_configs() / rel
    path, shown = (user, str(user)) if user.is_file() else (package_conf(config_module) / rel,
                                                             f"{config_module.replace('.', '/')}/{rel}")
    leaf = key.rsplit(".", 1)[-1] if key else ""
    if leaf and path.is_file():
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if re.match(rf"\s*{re.escape(leaf)}\s*:", line):
                return f"{shown}:{n}"
    return shown


def compose_train_config(overrides: list[str], prog: str = "mvtn-train"):
    """``mvtn-train``'s config from ``overrides``, for entry points that train outside Hydra's app
    (``scripts/studies/axis_views.py``): a bad key is refused as ``mvtn-train`` refuses it (one line, exit 2)."""
    from hydra import compose, initialize_config_module

    from .schema import TrainConfig, as_config
    from .store import register_configs

    register_configs()
    check_overrides(prog, "train", TrainConfig, overrides, validate=TrainConfig.validate)
    with initialize_config_module(version_base="1.3", config_module=CONF_MODULE):
        cfg = compose("train", overrides=overrides)
    plain = OmegaConf.to_container(cfg, resolve=False)
    plain.pop("hydra", None)
    return as_config(plain)
