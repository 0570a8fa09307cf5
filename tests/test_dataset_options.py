"""One schema per dataset option (``OPTIONS["dataset"]``, ``data/config.py``): every option validates
with its defaults, its YAML starts from its schema, a key of another dataset is refused in one line
naming the datasets that have it, and a new dataset touches only its own code (here: this file)."""
from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf
from torch.utils.data import Dataset

from mvtn_exp.config.compose import check_overrides
from mvtn_exp.config.options import OPTIONS, load
from mvtn_exp.config.schema import OPTION_KINDS, TrainConfig
from mvtn_exp.config.store import register_configs
from mvtn_exp.data.config import DatasetConfig, register
from mvtn_exp.data.datasets import build_dataset
from mvtn_exp.engine.trainer import as_config

CONF = Path(__file__).resolve().parents[1] / "mvtn_exp" / "conf" / "dataset"
register_configs()
load("dataset")
REGISTRY = OPTIONS["dataset"]
NAMES = sorted(REGISTRY)
COMMON = {f.name for f in fields(DatasetConfig)}
# (option, key of another option that this one lacks): every such pair
FOREIGN = sorted({(name, key) for name in NAMES for other in NAMES
                  for key in REGISTRY.keys_of(other) - REGISTRY.keys_of(name)})


def _owners(key: str) -> list[str]:
    return sorted(n for n in NAMES if key in REGISTRY.keys_of(n))


def test_the_registry_holds_every_dataset_and_dataset_is_an_option_kind():
    assert NAMES == ["modelnet40", "scanobjectnn", "shapenet", "shapenet_parts", "synthetic", "synthetic_parts",
                     "synthetic_views"]
    assert "dataset" in OPTION_KINDS and "dataset" in OPTIONS


@pytest.mark.parametrize("name", NAMES)
def test_every_dataset_validates_with_its_defaults_and_has_the_common_keys(name):
    cfg = REGISTRY[name]()
    assert cfg.name == name and cfg.validate() is cfg and isinstance(cfg, DatasetConfig)
    assert COMMON <= REGISTRY.keys_of(name)
    assert type(as_config({"dataset": {"name": name}}).dataset) is REGISTRY[name]


@pytest.mark.parametrize("name,key", FOREIGN, ids=[f"{n}.{k}" for n, k in FOREIGN])
def test_a_key_of_another_dataset_is_refused_naming_the_datasets_that_have_it(name, key):
    value = REGISTRY[_owners(key)[0]]().__dict__[key]
    with pytest.raises(ValueError) as err:
        as_config({"dataset": {"name": name, key: value}})
    line = str(err.value)
    assert "\n" not in line
    assert line.startswith(f"dataset.{key}: dataset={name} has no key '{key}'"), line
    assert f"dataset.{key} is a key of dataset={', '.join(_owners(key))}" in line


@pytest.mark.parametrize("argv,owner", [(["dataset=modelnet40", "dataset.rotate=y"], "synthetic, synthetic_parts, synthetic_views"),
                                        (["dataset=shapenet", "dataset.variant=obj_bg"], "scanobjectnn"),
                                        (["dataset.family=decoys"], "synthetic_views"),
                                        (["dataset=scanobjectnn", "dataset.split_csv=a.csv"], "shapenet")])
def test_the_command_line_refuses_a_foreign_key_at_compose_time_in_one_line(argv, owner, capsys):
    with pytest.raises(SystemExit) as e:
        check_overrides("mvtn-train", "train", TrainConfig, argv, validate=TrainConfig.validate)
    err = capsys.readouterr().err.strip().splitlines()
    key = argv[-1].split("=")[0]
    assert e.value.code == 2 and len(err) == 1, err
    assert f"{key}: dataset=" in err[0] and f"{key} is a key of dataset={owner}" in err[0], err[0]


@pytest.mark.parametrize("path", sorted(CONF.glob("*.yaml")), ids=lambda p: p.stem)
def test_every_dataset_file_starts_from_its_schema(path):
    """A file starts from ``/schema/dataset/NAME@_here_`` or from a sibling that does."""
    defaults = OmegaConf.load(path).get("defaults")
    first = str(defaults[0])
    assert first.startswith("/schema/dataset/") and first.endswith("@_here_") or (CONF / f"{first}.yaml").is_file()
    assert str(defaults[-1]) == "_self_"


@pytest.mark.parametrize("argv,message", [
    ({"name": "scanobjectnn", "shape": "mesh"}, "point clouds only"),
    ({"name": "scanobjectnn", "variant": "hardest"}, "dataset.variant"),
    ({"name": "modelnet40", "format": "ply_hdf5_2048"}, "point clouds only"),
    ({"name": "modelnet40", "format": "h5"}, "dataset.format"),
    ({"name": "synthetic_views", "family": ""}, "dataset.family"),
    ({"name": "synthetic", "num_per_class": [1, 0, 1]}, "dataset.num_per_class"),
    ({"name": "shapenet", "max_vertices": -1}, "dataset.max_vertices"),
    ({"name": "nope"}, "dataset='nope': expected one of modelnet40, scanobjectnn"),
])
def test_values_are_checked_by_the_options_own_validate(argv, message):
    with pytest.raises(ValueError, match=message):
        as_config({"dataset": argv})


# ------------------------------------------------------------------------------ a new dataset, here only
class ToyPoints(Dataset):
    """Two classes of point clouds: a small and a large sphere."""

    classes = ["large", "small"]

    def __init__(self, split: str, count: int, num_points: int) -> None:
        gen = torch.Generator().manual_seed({"train": 0, "val": 1, "test": 2}[split])
        self.points = torch.nn.functional.normalize(torch.randn(2 * count, num_points, 3, generator=gen), dim=-1)
        self.labels = [i % 2 for i in range(2 * count)]
        self.points[1::2] *= 0.5

    def __len__(self) -> int:
        return len(self.labels)

    def __getitem__(self, i: int) -> dict:
        return {"points": self.points[i], "label": self.labels[i], "name": f"toy_{i}"}


@dataclass
class ToyDatasetConfig(DatasetConfig):
    """Two spheres of points, built in memory."""

    name: str = "toy_test_dataset"
    shape: str = "points"
    count: int = 4

    def build(self, split: str, progress: bool = True) -> Dataset:
        return ToyPoints(split, self.count, self.num_points)


def test_a_toy_dataset_defined_here_registers_builds_and_trains(tmp_path):
    from mvtn_exp.engine import train

    register("toy_test_dataset")(ToyDatasetConfig)
    try:
        cfg = {"views": 2, "image_size": 16, "epochs": 1, "batch_size": 4, "selector": {"name": "circular"},
               "dataset": {"name": "toy_test_dataset", "num_points": 32, "count": 3},
               "logger": {"progress": False, "tensorboard": False}}
        typed = as_config(cfg)
        assert type(typed.dataset) is ToyDatasetConfig and len(build_dataset(typed.dataset, "val")) == 6
        with pytest.raises(ValueError, match="dataset=toy_test_dataset has no key 'rotate'"):
            as_config({**cfg, "dataset": {**cfg["dataset"], "rotate": "y"}})
        m = train(cfg, tmp_path / "run")
        assert m["classes"] == ToyPoints.classes and m["test_size"] == 6
    finally:
        REGISTRY.pop("toy_test_dataset", None)
