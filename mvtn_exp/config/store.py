"""Hydra's ConfigStore filled from the schemas: ``train_schema``, ``eval_schema`` and every option's
schema as ``schema/<kind>/NAME`` (``register_configs``, called once by each command)."""
from __future__ import annotations

from .eval_schema import EvalConfig
from .options import OPTIONS, load
from .schema import GROUPS, OPTION_KINDS, TrainConfig


def register_configs() -> None:
    """Store ``train_schema`` and ``eval_schema`` in Hydra's ConfigStore, and each option's schema
    as ``schema/<kind>/NAME`` (its ``conf/<kind>/NAME.yaml`` starts from it). The group files are
    merged into the typed fields of ``TrainConfig``, so each is checked against its schema."""
    from hydra.core.config_store import ConfigStore

    from omegaconf import OmegaConf

    load()
    cs = ConfigStore.instance()
    train = OmegaConf.structured(TrainConfig)
    for kind in OPTION_KINDS:  # the chosen option's schema merges in (a subclass of the kind's base)
        train[kind] = OmegaConf.structured(GROUPS[kind])
    cs.store(name="train_schema", node=train)
    cs.store(name="eval_schema", node=EvalConfig)
    for kind in OPTION_KINDS:
        for name, option in OPTIONS[kind].items():
            cs.store(group=f"schema/{kind}", name=name, node=option)
