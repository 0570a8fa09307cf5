"""Training-time rotation augmentation (``augment.rotate``), the batch rotation it uses, the
detail report of ``synthetic_views`` runs and unique run dirs."""
import math

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_module

from mvtn_exp.data import synthetic_views as sv

from mvtn_exp.data import view_detail as vd
from mvtn_exp.data.collate import collate_shapes
from mvtn_exp.data.synthetic import SyntheticShapes
from mvtn_exp.engine import train
from mvtn_exp.data.datasets import view_report as detail_report
from mvtn_exp.config.store import register_configs
from mvtn_exp.tasks.robustness import random_rotations, rotate_batch, turn_batch, y_rotation_matrix

from test_train_e2e import _assert_same_run, tiny


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> str:
    return str(tmp_path_factory.mktemp("augment_cache"))


@pytest.mark.parametrize("mode", ["none", "y", "so3"])
def test_random_rotations_are_rotations_and_seeded(mode):
    R = random_rotations(500, mode, torch.Generator().manual_seed(3))
    assert R.shape == (500, 3, 3) and R.dtype == torch.float64
    torch.testing.assert_close(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(500, 3, 3), atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(500, dtype=torch.float64), atol=1e-12, rtol=0)
    torch.testing.assert_close(R, random_rotations(500, mode, torch.Generator().manual_seed(3)), atol=0, rtol=0)
    up = R[:, :, 1]  # where +Y goes
    if mode == "so3":  # uniform over SO(3): the image of +Y is uniform on the sphere (mean ~0, E[y^2] = 1/3)
        assert float(up.mean(0).norm()) < 0.15 and abs(float((up[:, 1] ** 2).mean()) - 1 / 3) < 0.05
        assert not torch.allclose(R, random_rotations(500, mode, torch.Generator().manual_seed(4)))
    else:
        torch.testing.assert_close(up, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64).expand(500, 3), atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match="mode='x'"):
        random_rotations(2, "x")


def test_turn_batch_moves_points_meshes_and_frames_together(tmp_path):
    ds = sv.SyntheticViews(tmp_path, "test", num_per_class=(1, 1, 1), num_points=64, progress=False)
    batch = collate_shapes([ds[i] for i in range(3)])
    R = random_rotations(3, "so3", torch.Generator().manual_seed(0))
    out = turn_batch(batch, R)
    Rf = R.float()
    for b in range(3):
        torch.testing.assert_close(out["points"][b], batch["points"][b] @ Rf[b].T)
        lo, hi = int(batch["meshes"].verts_per_shape[:b].sum()), int(batch["meshes"].verts_per_shape[:b + 1].sum())
        torch.testing.assert_close(out["meshes"].verts[lo:hi], batch["meshes"].verts[lo:hi] @ Rf[b].T)
        torch.testing.assert_close(out["rotations"][b], Rf[b] @ batch["rotations"][b])
        for key in ("detail_anchor", "detail_axis"):
            torch.testing.assert_close(out[key][b], Rf[b] @ batch[key][b])
    assert torch.equal(out["detail_size"], batch["detail_size"]) and torch.equal(out["labels"], batch["labels"])
    assert torch.equal(batch["points"], collate_shapes([ds[i] for i in range(3)])["points"])  # input untouched
    # the turned frame still says what the renderer shows: a camera on the turned cup axis sees the detail
    a, e = vd.view_angles(out["detail_axis"].double().numpy())
    cams = vd.camera_positions(a, e)[:, None]
    assert vd.sees_detail(out["detail_anchor"].numpy(), out["detail_axis"].numpy(), out["detail_size"].numpy(), cams).all()
    with pytest.raises(ValueError, match="turn_batch"):
        turn_batch(batch, R[:2])


def test_rotate_batch_is_turn_batch_about_y(cache):
    ds = SyntheticShapes(cache, "val", num_per_class=[1, 1, 1], seed=0, progress=False)
    batch = collate_shapes([ds[i] for i in range(4)])
    angles = torch.tensor([0.0, 90.0, -30.0, 180.0])
    a, b = rotate_batch(batch, angles), turn_batch(batch, y_rotation_matrix(angles))
    assert torch.equal(a["points"], b["points"]) and torch.equal(a["meshes"].verts, b["meshes"].verts)
    torch.testing.assert_close(a["points"][1][:, 0], batch["points"][1][:, 2], atol=1e-6, rtol=0)  # +Z -> +X at 90


def test_training_with_rotation_augmentation_changes_training_and_resumes_exactly(cache, tmp_path):
    plain = train(tiny(cache, epochs=1), tmp_path / "plain")
    full = train(tiny(cache, **{"augment.rotate": "so3"}), tmp_path / "full")
    assert abs(full["history"][0]["train_loss"] - plain["history"][0]["train_loss"]) > 1e-6  # it did something
    assert full["config"]["augment"]["rotate"] == "so3"
    train(tiny(cache, epochs=1, **{"augment.rotate": "so3"}), tmp_path / "a")
    resumed = train(tiny(cache, epochs=2, ckpt_path=str(tmp_path / "a" / "last.pt"), **{"augment.rotate": "so3"}),
                    tmp_path / "b")
    _assert_same_run(resumed, full)


def test_detail_report_counts_views_that_see_the_detail(tmp_path):
    ds = sv.SyntheticViews(tmp_path, "test", num_per_class=(1, 1, 2), num_points=64, progress=False)
    n = len(ds)
    axis = ds._a["detail_axis"].astype(np.float64)
    a_in, e_in = vd.view_angles(axis)  # on the cup axis: sees it
    a_out, e_out = vd.view_angles(-axis)  # from below the floor: does not
    half = np.arange(n) % 2 == 0
    azim = np.where(half, a_in, a_out)[:, None].repeat(2, 1)
    elev = np.where(half, e_in, e_out)[:, None].repeat(2, 1)
    labels = torch.as_tensor(ds._a["labels"]).long()
    pred = torch.where(torch.from_numpy(half), labels, (labels + 1) % 8)  # right exactly where it sees
    res = {"azim": torch.from_numpy(azim), "elev": torch.from_numpy(elev), "dist": torch.full((n, 2), 2.2, dtype=torch.float64),
           "labels": labels, "pred": pred}
    rep = detail_report(ds, res)
    angles = ds.detail_angles(azim, elev, np.full((n, 2), 2.2))
    assert (angles[half] < 15).all() and (angles[~half] > 165).all()  # down the cup / from under its floor
    assert rep == {"detail_seen": 0.5, "acc_detail_seen": 1.0, "acc_detail_unseen": 0.0,
                   "detail_angle_median": float(np.median(angles.min(1)))}
    assert detail_report(object(), res) == {}  # datasets without a detail frame


def test_run_dirs_carry_the_process_id():
    import os

    register_configs()
    with initialize_config_module(version_base="1.3", config_module="mvtn_exp.conf"):
        cfg = compose("train", return_hydra_config=True)
    from omegaconf import OmegaConf
    run_dir = OmegaConf.to_container(cfg.hydra.run, resolve=True)["dir"]
    assert run_dir.endswith(f"-{os.getpid()}") and "/train/runs/" in run_dir
    assert math.isfinite(float(run_dir.rsplit("/", 1)[1].split("-")[0]))  # starts with the year
