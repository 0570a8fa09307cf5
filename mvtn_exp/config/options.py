"""One schema per option: a registry per component kind, option name -> its config dataclass.

The kinds are ``selector``, ``point_encoder``, ``backbone``, ``mvnet``, ``segnet`` and ``dataset``
(``OPTIONS``). A component's own module (a dataset's: ``data/config.py``) defines its config, a
dataclass subclassing the kind's base config (an ``OptionConfig``) whose ``name`` defaults to the
option's name, and registers it:

    @OPTIONS["mvnet"].register("my_net")
    @dataclass
    class MyNetConfig(MVNetConfig):
        name: str = "my_net"
        width: int = 64

Its ``conf/<kind>/<name>.yaml`` starts from the stored schema (``defaults: [/schema/<kind>/<name>@_here_]``),
so ``mvnet=my_net mvnet.k=3`` (a key of another option) is refused at compose time, naming the
option and the key (``foreign_key_message``). Every module of a kind's packages is imported before
a registry is read (``load``), so a new option touches its own module and YAML only.

The config class is the option's one entry: it builds the component (its ``build``, a dataset's
``build(split, progress)``; a model kind's class attribute ``network`` names the constructor,
``Options.lookup`` finds it by name) and says
what the rest of the config needs to know (a backbone's ``feature_dim``). ``list_options(kind)``:
each option with the first sentence of its config's docstring (``mvtn-train --list KIND``).
"""
from __future__ import annotations

import importlib
import pkgutil
import re
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Callable, Optional

if TYPE_CHECKING:  # pragma: no cover
    from .schema import TrainConfig

# kind -> the packages whose modules register its options
PACKAGES = {"selector": ("mvtn_exp.selectors",), "point_encoder": ("mvtn_exp.models",),
            "backbone": ("mvtn_exp.models",), "mvnet": ("mvtn_exp.models",), "segnet": ("mvtn_exp.models",),
            "dataset": ("mvtn_exp.data",)}


class Options(dict):
    """``name -> config class`` of one kind."""

    def __init__(self, kind: str) -> None:
        super().__init__()
        self.kind = kind

    def register(self, name: str) -> Callable[[type], type]:
        """Class decorator: ``<kind>=name`` builds from this config class."""
        def deco(cls):
            if name in self and self[name] is not cls:
                raise ValueError(f"{self.kind} {name!r} is registered twice ({self[name].__name__}, {cls.__name__})")
            if getattr(cls, "name", None) != name:
                raise ValueError(f"{cls.__name__}: its name field defaults to {getattr(cls, 'name', None)!r}, "
                                 f"registered as {self.kind} {name!r}")
            self[name] = cls
            return cls
        return deco

    def schema(self, name: str) -> type:
        """The config class of ``<kind>=name`` (one line naming the options when unknown)."""
        load(self.kind)
        if name not in self:
            raise ValueError(f"{self.kind}={name!r}: expected one of {', '.join(sorted(self))}")
        return self[name]

    def lookup(self, name: str, noun: str) -> type:
        """The config class of ``name``, for the ``build_<kind>(name, ...)`` functions; unknown: one
        line ``unknown <noun> 'name'; allowed: ...``."""
        load(self.kind)
        if name not in self:
            raise ValueError(f"unknown {noun} {name!r}; allowed: {', '.join(sorted(self))}")
        return self[name]

    def keys_of(self, name: str) -> set[str]:
        """The keys of ``<kind>=name``."""
        return {f.name for f in fields(self.schema(name))}

    def foreign_key_message(self, name: str, key: str) -> str:
        """One line for ``<kind>.key`` given to ``<kind>=name``, which has no such key."""
        kind = self.kind
        owners = sorted(n for n in self if key in self.keys_of(n))
        where = f"; {kind}.{key} is a key of {kind}={', '.join(owners)}" if owners else ""
        return (f"{kind}.{key}: {kind}={name} has no key {key!r}{where} (keys of {kind}={name}: "
                f"{', '.join(sorted(self.keys_of(name)))})")


OPTIONS: dict[str, Options] = {kind: Options(kind) for kind in PACKAGES}
_LOADED: set[str] = set()


def load(kind: Optional[str] = None) -> None:
    """Import every module of the packages that register options (of ``kind``, or of all kinds)."""
    for package in (PACKAGES[kind] if kind else sorted({p for ps in PACKAGES.values() for p in ps})):
        if package in _LOADED:
            continue
        _LOADED.add(package)
        pkg = importlib.import_module(package)
        for info in pkgutil.iter_modules(pkg.__path__):
            importlib.import_module(f"{package}.{info.name}")


def summary(cls: type) -> str:
    """The first sentence of ``cls``'s docstring, on one line, without rST's double backquotes (a
    class without a docstring of its own: its nearest documented base's)."""
    doc = next((c.__doc__ for c in cls.__mro__ if c.__doc__ and not c.__doc__.startswith(f"{c.__name__}(")), "")
    text = " ".join(doc.split()).replace("``", "")
    m = re.match(r"(.+?[.!?])(\s|$)", text)
    return m.group(1) if m else text


def list_options(kind: str) -> list[tuple[str, str]]:
    """``(name, first sentence of its config's docstring)`` for every option of ``kind``, sorted by name."""
    if kind not in OPTIONS:
        raise ValueError(f"unknown option kind {kind!r}; expected one of {', '.join(OPTIONS)}")
    load(kind)
    return [(name, summary(cls)) for name, cls in sorted(OPTIONS[kind].items())]


@dataclass
class OptionConfig:
    """What every option's config has: ``name`` (chosen with ``<kind>=NAME``), ``validate()`` (its
    own keys) and ``check(cfg)`` (against the whole ``TrainConfig``, e.g. the image size)."""

    name: str = ""

    kind = ""  # class attribute: the option's kind (its registry in OPTIONS)

    def validate(self):
        reg = OPTIONS[self.kind]
        load(self.kind)
        if reg.get(self.name) is not type(self):
            raise ValueError(f"{self.kind}.name={self.name!r}: the option is chosen with {self.kind}=NAME, expected "
                             f"one of {', '.join(sorted(reg))}")
        return self

    def check(self, cfg: "TrainConfig") -> None:
        """Checks against the rest of the config; none by default."""
