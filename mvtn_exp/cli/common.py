"""Shared CLI plumbing: compose-time config errors as one clear line and exit code 2."""
from __future__ import annotations

import dataclasses
import sys

from omegaconf import OmegaConf

CONF_MODULE = "mvtn_exp.conf"


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


def describe(exc: Exception, schema) -> str:
    """One line: the offending key, what went wrong and, for unknown keys, the allowed ones."""
    text = str(exc).strip()
    first = text.splitlines()[0] if text else type(exc).__name__
    key = next((ln.split(":", 1)[1].strip() for ln in text.splitlines() if ln.strip().startswith("full_key:")), "")
    msg = f"{first}" + (f" (key '{key}'" if key else "")
    if key and ("not in" in first or "not a valid" in first or "Could not override" in first):
        allowed = _allowed_keys(schema, key.split(".")[:-1])
        if allowed:
            msg += f"; allowed keys here: {', '.join(allowed)}"
    if key:
        msg += ")"
    return msg


def check_overrides(prog: str, config_name: str, schema, argv: list[str]) -> None:
    """Compose ``config_name`` with the command-line overrides; on a config error print one line
    naming the key, the config file and the allowed keys, and exit with code 2 (no traceback).
    Multirun sweeps and Hydra's own flags are left to Hydra."""
    if any(a.startswith("-") for a in argv):
        return
    from hydra import compose, initialize_config_module

    overrides = [a for a in argv if not a.lstrip("+~").startswith("hydra.")]
    try:
        with initialize_config_module(version_base="1.3", config_module=CONF_MODULE):
            cfg = compose(config_name, overrides=overrides)
            OmegaConf.to_object(cfg)
    except Exception as exc:  # composition, type and validation errors
        cause = exc  # prefer the innermost error that names the key
        while cause.__cause__ is not None:
            cause = cause.__cause__
        if "full_key:" not in str(cause):
            cause = exc
        print(f"{prog}: config error in {CONF_MODULE.replace('.', '/')}/{config_name}.yaml: {describe(cause, schema)}",
              file=sys.stderr)
        sys.exit(2)
