"""The keys of the trade search that exist only for some options (``+experiment=tradeoff_search``).

Hydra's Optuna sweeper samples ``hydra.sweeper.params`` for every trial; a key that only some
options have cannot be among them (``selector.num_points`` is refused with a fixed selector). The
sweeper calls ``conditional_keys(config, trial)`` after sampling those params
(``hydra.sweeper.custom_search_space``): each key of ``CONDITIONAL`` is suggested only when the
trial's chosen options use it, so no trial is refused and no trial varies a key without effect.
"""
from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from ..config.options import OPTIONS

CONF = Path(__file__).resolve().parents[1] / "conf"


def _renderer_mode(option: str) -> str:
    return str(OmegaConf.load(CONF / "renderer" / f"{option}.yaml").get("mode", ""))


# key -> (its choices, whether the trial's params use it)
CONDITIONAL = {
    # G's input points: learned selectors only (fixed ones have no G)
    "selector.num_points": ((256, 1024), lambda p: "num_points" in OPTIONS["selector"].keys_of(str(p["selector"]))),
    # faces blended per pixel: the soft renderer only (hard keeps the nearest face)
    "renderer.faces_per_pixel": ((1, 8), lambda p: _renderer_mode(str(p["renderer"])) == "soft"),
}


def conditional_keys(config, trial) -> None:
    """Suggest each ``CONDITIONAL`` key the trial's options use: sampled ones, or ones fixed on the
    command line (the sweeper keeps those as the trial's user attributes); a key whose option is in
    neither is left alone (``config``: the sweep's, unused)."""
    del config
    chosen = {**trial.user_attrs, **trial.params}
    for key, (choices, used) in CONDITIONAL.items():
        try:
            wanted = used(chosen)
        except KeyError:  # the option it depends on is neither sampled nor given
            continue
        if wanted:
            trial.suggest_categorical(key, list(choices))
