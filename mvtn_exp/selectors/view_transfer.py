"""View transfer (``selector.from_ckpt=PATH``): train a multi-view network on the views of a G
trained in another run, G frozen.

The paper transfers the views an MVTN learned with one multi-view network to another. Here G's
weights come from the checkpoint (its ``selector.*`` entries), stay fixed (no gradient, no
optimizer group, BatchNorm in evaluation mode throughout) and C trains on G's views. The
checkpoint's G must be the one the config describes: ``views`` and every ``selector`` and
``point_encoder`` setting must match (a mismatch is one line naming each differing key). A
resumed run takes G from its own checkpoint and does not read ``from_ckpt`` again.
"""
from __future__ import annotations

from ..runtime import checkpoint
from .config import REGISTRY

KEYS = ("views", "selector", "point_encoder")


def _without_source(cfg: dict) -> dict:
    out = dict(cfg)
    out["selector"] = {k: v for k, v in cfg.get("selector", {}).items() if k != "from_ckpt"}
    return out


def load_frozen_selector(model, cfg_dict: dict, path) -> None:
    """Copy G's weights from the checkpoint at ``path`` into ``model.selector`` (see the module docstring)."""
    state = checkpoint.load(path)
    try:
        checkpoint.check_compatible(_without_source(state["config"]), _without_source(cfg_dict), keys=KEYS,
                                    free=REGISTRY[cfg_dict["selector"]["name"]].free_keys())
    except checkpoint.CheckpointMismatch as exc:
        raise checkpoint.CheckpointMismatch(f"selector.from_ckpt={path}: its G differs from the configured one: "
                                            f"{str(exc).split(': ', 1)[1]}") from None
    weights = {k[len("selector."):]: v for k, v in state["model"].items() if k.startswith("selector.")}
    if not weights:
        raise checkpoint.CheckpointMismatch(f"selector.from_ckpt={path}: the checkpoint holds no weights of G "
                                            "(trained with a fixed selector?)")
    model.selector.load_state_dict(weights)
    freeze_selector(model)


def freeze_selector(model) -> None:
    """G keeps its weights and its BatchNorm statistics: no gradient, evaluation mode for good."""
    for p in model.selector.parameters():
        p.requires_grad_(False)
    model.selector_frozen = True
    model.selector.eval()

