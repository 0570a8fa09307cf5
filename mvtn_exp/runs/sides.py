"""The sides of a comparison: finished runs sorted into one side per configuration (or per ``--where``
condition), each paired with the reference side on their common seeds, or refused (``CompareError``).

Keys that say where or how a run ran (``RUN_LOCAL``: device, threads, paths, ...) never make a
difference; a key another run's record has and an older run's lacks is read as its current default
(``fill_added_keys``). Two sides may differ in data, split or epochs (``PROTECTED``) only when that
key is the one under comparison.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field

import yaml

from .folders import Run, flatten
from .settings import is_local

PROTECTED = ("dataset", "epochs", "patience")  # data, its splits and the training length


class CompareError(ValueError):
    """A comparison that cannot be made as asked (mismatched sides, too few seeds, nothing to read)."""


_DEFAULTS: dict = {}


def current_defaults(settings: dict) -> dict:
    """The current code's default of every dotted key of a run with ``settings``'s options (the
    top-level ``TrainConfig`` fields, and each option kind's schema for the option it names: only
    that schema's keys, not those of the kind's default option, which a fixed selector lacks)."""
    from omegaconf import OmegaConf

    from ..config.options import OPTIONS
    from ..config.schema import OPTION_KINDS, TrainConfig

    names = tuple(settings.get(f"{kind}.name") for kind in OPTION_KINDS)
    if names not in _DEFAULTS:
        out = flatten(OmegaConf.to_container(OmegaConf.structured(TrainConfig)))
        for kind, name in zip(OPTION_KINDS, names):
            try:
                schema = OPTIONS[kind].schema(str(name))
            except ValueError:  # an option this code no longer has: nothing to fill from
                continue
            out = {k: v for k, v in out.items() if not k.startswith(f"{kind}.")}
            out.update(flatten(OmegaConf.to_container(OmegaConf.structured(schema)), kind))
        _DEFAULTS[names] = out
    return _DEFAULTS[names]


def drop_foreign_keys(run: Run) -> None:
    """Keys of an option kind that the run's option no longer has (a record from before that kind
    had one schema per option held every option's keys, e.g. ``dataset.family`` for
    ``dataset=modelnet40``): dropped, recorded in ``Run.filled`` as ``-key``."""
    from ..config.options import OPTIONS
    from ..config.schema import OPTION_KINDS

    defaults = current_defaults(run.settings)
    for kind in OPTION_KINDS:
        if str(run.settings.get(f"{kind}.name")) not in OPTIONS[kind]:
            continue  # an option this code no longer has: its keys stay as recorded
        for key in [k for k in run.settings if k.startswith(f"{kind}.") and k not in defaults]:
            del run.settings[key]
            run.filled.append(f"-{key}")


def fill_added_keys(runs: list[Run]) -> None:
    """A key some run's record has and another's lacks, and that the current code defaults: the
    lacking run gets the default (recorded in ``Run.filled``); a key without a current default
    stays absent (and still makes a difference). Keys the run's options no longer have are
    dropped first (``drop_foreign_keys``)."""
    readable = [r for r in runs if r.settings is not None]
    for r in readable:
        drop_foreign_keys(r)
    every = set().union(*(r.settings for r in readable)) if readable else set()
    for r in readable:
        missing = every - set(r.settings)
        if not missing:
            continue
        defaults = current_defaults(r.settings)
        for key in sorted(missing):
            if key in defaults and not is_local(key):
                r.settings[key] = defaults[key]
                r.filled.append(key)


def parse_condition(text: str) -> dict:
    """``"selector.name=poi views=1"`` -> ``{"selector.name": "poi", "views": 1}`` (values read as YAML)."""
    out = {}
    for part in text.split():
        key, eq, value = part.partition("=")
        if not eq or not key:
            raise CompareError(f"--where {text!r}: expected KEY=VALUE pairs separated by spaces, got {part!r}")
        if key.lstrip("+") == "seed":
            raise CompareError(f"--where {text!r}: seed is what runs are paired on, not a side's condition")
        out[key.lstrip("+")] = yaml.safe_load(value)
    return out


def _matches(settings: dict, condition: dict) -> bool:
    """``selector=poi`` reads as ``selector.name=poi`` (a group's option)."""
    return all(settings.get(k if k in settings else f"{k}.name", "<absent>") == v for k, v in condition.items())


def _show(v) -> str:
    return json.dumps(v, separators=(",", ":")) if isinstance(v, (list, dict)) else str(v)


def differing(a: dict, b: dict) -> list[str]:
    """Keys whose values differ between two flattened settings (a key missing on one side differs)."""
    return sorted(k for k in set(a) | set(b) if a.get(k, "<absent>") != b.get(k, "<absent>"))


def _protected(key: str, allowed) -> bool:
    under = any(key == p or key.startswith(p + ".") for p in PROTECTED)
    return under and not any(key == k or key.startswith(k + ".") for k in allowed)


@dataclass
class Side:
    label: str
    settings: dict
    runs: dict = field(default_factory=dict)  # seed -> finished Run
    unfinished: list = field(default_factory=list)


def _label(settings: dict, keys: list[str]) -> str:
    """The side's values of the keys that differ between sides: an option's name stands for its
    own keys (``selector.name=poi``, not every ``selector.*``)."""
    names = [k for k in keys if k.endswith(".name")]
    owners = tuple(k[: -len("name")] for k in names)
    shown = names + [k for k in keys if k not in names and not k.startswith(owners)]
    text = " ".join(f"{k}={_show(settings.get(k, '-'))}" for k in shown[:3])
    return text + (" ..." if len(shown) > 3 else "") if text else "(defaults)"


def _by_option(keys: list[str]) -> list[str]:
    """Differing keys, an option whose name differs shown once as ``selector.*``."""
    owners = tuple(k[: -len("name")] for k in keys if k.endswith(".name"))
    return [f"{o}*" for o in owners] + [k for k in keys if not k.startswith(owners)]


def _add(side: Side, run: Run) -> None:
    if run.status != "ok":
        side.unfinished.append(run)
    elif run.seed in side.runs:
        raise CompareError(f"seed={run.seed}: two finished runs of side '{side.label}' ({side.runs[run.seed].path}, "
                           f"{run.path}); pass the folders of one of them")
    else:
        side.runs[run.seed] = run


def make_sides(runs: list[Run], where: list[str] | None = None, group: str | None = None,
               reference: str | None = None) -> dict:
    """``{group value: [Side, ...]}``: runs sorted into sides, by ``where`` conditions (one side
    each, in their order) or, without them, one side per distinct configuration (first seen first;
    the one matching the ``reference`` condition first of all)."""
    readable = [r for r in runs if r.settings is not None]
    if not any(r.status == "ok" for r in readable):
        raise CompareError(f"no finished run (a run dir with metrics.json) among the {len(runs)} found")
    groups: dict = {}
    for r in readable:
        groups.setdefault(r.settings.get(group) if group else None, []).append(r)

    def key_of(settings: dict) -> tuple:
        return tuple(sorted((k, _show(v)) for k, v in settings.items() if k != group))

    ref = parse_condition(reference) if reference else None
    rank = {}
    for r in sorted(readable, key=lambda r: not (ref and _matches(r.settings, ref))):
        rank.setdefault(key_of(r.settings), len(rank))
    out = {}
    for g, members in groups.items():
        if where:
            sides, order = _where_sides(members, where, ref)
        else:
            sides = {}
            for r in members:
                sides.setdefault(key_of(r.settings), []).append(r)
            order = sorted(sides, key=rank.get)
        out[g] = _built_sides(sides, order, where, group)
    return out


def _where_sides(members: list[Run], where: list[str], ref: dict | None) -> tuple[dict, list]:
    """The runs of each ``where`` condition (a run matching two is refused) and the conditions'
    order: theirs, the one matching the ``ref`` condition first."""
    sides: dict = {}
    conditions = [parse_condition(w) for w in where]
    for r in members:
        hit = [i for i, c in enumerate(conditions) if _matches(r.settings, c)]
        if len(hit) > 1:
            raise CompareError(f"{r.path}: matches --where {where[hit[0]]!r} and {where[hit[1]]!r}; "
                               "make the conditions exclusive")
        if hit:
            sides.setdefault(hit[0], []).append(r)
    order = [i for i in range(len(where)) if i in sides]
    if ref:  # the side matching the reference condition first (the others keep their order)
        order.sort(key=lambda i: not _matches(sides[i][0].settings, ref))
    return sides, order


def _built_sides(sides: dict, order: list, where: list[str] | None, group: str | None) -> list[Side]:
    """One ``Side`` per entry of ``order`` with a finished run, labelled by its ``where`` condition
    or its values of the keys that differ between the sides."""
    built = []
    finished = {i: [r for r in sides[i] if r.status == "ok"] for i in order}
    order = [i for i in order if finished[i]]  # a side none of whose runs finished: listed under not finished
    reference_settings = {i: finished[i][0].settings for i in order}
    keys = sorted({k for i in order for j in order for k in differing(reference_settings[i], reference_settings[j])
                   if k != group})
    for i in order:
        ok = finished[i]
        if where and ok:
            for r in ok[1:]:
                diff = [k for k in differing(ok[0].settings, r.settings) if k != group]
                if diff:
                    raise CompareError(f"--where {where[i]!r}: its runs differ in {diff[0]} ({_show(ok[0].settings.get(diff[0]))} "
                                       f"in {ok[0].path}, {_show(r.settings.get(diff[0]))} in {r.path}); add {diff[0]}=... "
                                       f"to the condition{' or --group ' + diff[0] if not group else ''}")
        side = Side(where[i] if where else _label(reference_settings[i], keys), reference_settings[i])
        for r in sides[i]:
            _add(side, r)
        built.append(side)
    return built


def _check_pair(ref: Side, side: Side, allowed, group_text: str) -> list[str]:
    diff = differing(ref.settings, side.settings)
    bad = [k for k in diff if _protected(k, allowed)]
    if bad:
        k = bad[0]
        raise CompareError(f"{k}: '{ref.label}' has {_show(ref.settings.get(k, '(absent)'))}, '{side.label}' has "
                           f"{_show(side.settings.get(k, '(absent)'))}{group_text}: the sides differ in data, split or "
                           f"epochs; pass --key {k} if that is the key under comparison")
    return diff


def _common_seeds(ref: Side, side: Side, group_text: str) -> tuple[list, list]:
    a, b = set(ref.runs), set(side.runs)
    unfinished = {r.seed for r in ref.unfinished + side.unfinished}
    if a != b and not (a ^ b) <= unfinished:
        raise CompareError(f"seed: '{ref.label}' has seeds {_seeds(a)}, '{side.label}' has {_seeds(b)}{group_text}; "
                           "run the same seeds on both sides")
    common = sorted(a & b)
    if len(common) < 2:
        raise CompareError(f"seed: '{ref.label}' and '{side.label}'{group_text} share {len(common)} finished seed(s) "
                           f"({_seeds(set(common)) or 'none'}); a paired comparison needs at least 2")
    return common, sorted(a ^ b)


def _seeds(s: set) -> str:
    return ", ".join(map(str, sorted(s, key=lambda x: (str(type(x)), x))))


def _only_one(side: Side, runs: list[Run], group, g, group_text: str) -> str:
    """The refusal when one configuration has finished runs; it names the runs of other
    configurations that have not finished (a side still running or failed), if any."""
    other = [r for r in runs if r.status != "ok" and r.settings is not None
             and (not group or r.settings.get(group) == g)
             and [k for k in differing(side.settings, r.settings) if k != group]]
    waiting = (f"; {len(other)} run(s) of another configuration not finished ({other[0].path}: {other[0].status}"
               + (", ..." if len(other) > 1 else "") + ")") if other else ""
    return (f"only one configuration{group_text} with finished runs ('{side.label}' ...): nothing to compare{waiting} "
            "(give the folders of both sides, or --where one condition per side)")
