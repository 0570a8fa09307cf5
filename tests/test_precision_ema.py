"""Mixed precision (C in bf16 under autocast; G and the renderer in float32) and the weight average
(``optim.ema_decay``): what runs in which type, that training and resume work, and bad settings."""
from __future__ import annotations

import pytest
import torch

from mvtn_exp.runtime import checkpoint
from mvtn_exp.engine import train
from mvtn_exp.engine.ema import ModelEMA
from mvtn_exp.engine.trainer import as_config
from mvtn_exp.model import build_mvtn

from conftest import tiny_config


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> str:
    return str(tmp_path_factory.mktemp("synthetic_cache"))


def test_bf16_runs_c_in_bfloat16_and_keeps_g_and_the_renderer_in_float32(cache):
    """Under precision=bf16 the renderer runs with autocast off and returns float32 images, G's
    views are float32, C's first convolution computes in bfloat16, and the logits come back as
    float32 (the loss is computed in float32)."""
    from mvtn_exp.data.collate import collate_shapes
    from mvtn_exp.engine.trainer import make_datasets

    cfg = as_config(tiny_config(cache, precision="bf16", views=3))
    ds = make_datasets(cfg)["train"]
    torch.manual_seed(0)
    model = build_mvtn(cfg, len(ds.classes)).train()
    seen = {}
    real_render = model.renderer.forward

    def render(*a, **kw):
        seen["render_autocast"] = torch.is_autocast_enabled("cpu")
        return real_render(*a, **kw)

    model.renderer.forward = render
    first_conv = next(m for m in model.mvnet.backbone.modules() if isinstance(m, torch.nn.Conv2d))
    first_conv.register_forward_hook(lambda m, i, o: seen.update(conv=o.dtype))  # returns None: output kept
    out = model(collate_shapes([ds[i] for i in range(4)]))
    assert seen["render_autocast"] is False and out["images"].dtype == torch.float32
    assert out["azim"].dtype == torch.float32 and seen["conv"] == torch.bfloat16
    assert out["logits"].dtype == torch.float32 and torch.isfinite(out["logits"]).all()
    out["logits"].sum().backward()
    assert all(p.grad is None or p.grad.dtype == torch.float32 for p in model.parameters())


def test_bf16_training_tracks_fp32_and_evaluates_from_its_checkpoint(cache, tmp_path):
    """Two epochs in bf16 against fp32 on the same seed: the first epoch's training loss agrees
    within 5% (bfloat16 keeps 8 bits of mantissa), and the checkpoint records the precision."""
    fp32 = train(tiny_config(cache), tmp_path / "fp32")
    bf16 = train(tiny_config(cache, precision="bf16"), tmp_path / "bf16")
    a, b = fp32["history"][0]["train_loss"], bf16["history"][0]["train_loss"]
    assert abs(a - b) <= 0.05 * a, (a, b)
    assert bf16["config"]["precision"] == "bf16" and 0.0 <= bf16["test_acc"] <= 1.0
    assert checkpoint.load(tmp_path / "bf16" / "best.pt")["config"]["precision"] == "bf16"


def test_fp16_on_cpu_and_bad_precisions_are_refused_naming_the_keys(cache):
    with pytest.raises(ValueError, match=r"precision=fp16 with device=cpu.*bf16"):
        as_config(tiny_config(cache, precision="fp16"))
    with pytest.raises(ValueError, match=r"precision.*fp32, bf16, fp16"):
        as_config(tiny_config(cache, precision="fp64"))
    for bad in (0.0, 1.0, 1.5, -0.1):
        with pytest.raises(ValueError, match=rf"optim.ema_decay={bad}.*\(0, 1\)"):
            as_config(tiny_config(cache, **{"optim.ema_decay": bad}))


def test_weight_average_follows_its_formula():
    """After updates at steps 100 and 101 (past the warm-up, d = 0.9): ema = d^2 w0 + d (1 - d) w1
    + (1 - d) w2, for the weights and the BatchNorm statistics alike; the batch counter is copied.
    The warm-up: d_0 = 0.1, d_t -> decay."""
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(3, 2), torch.nn.BatchNorm1d(2))
    ema, d = ModelEMA(net, 0.9), 0.9
    w, m = [net[0].weight.detach().clone()], [net[1].running_mean.clone()]
    assert ema.decay_at(0) == pytest.approx(0.1) and ema.decay_at(10) == pytest.approx(11 / 20)
    for step in (100, 101):
        with torch.no_grad():
            net[0].weight.add_(torch.randn_like(net[0].weight))
        net(torch.randn(4, 3))  # moves the BatchNorm statistics
        w.append(net[0].weight.detach().clone())
        m.append(net[1].running_mean.clone())
        ema.update(net, step)
    for got, x in ((ema.model[0].weight, w), (ema.model[1].running_mean, m)):
        torch.testing.assert_close(got, d * d * x[0] + d * (1 - d) * x[1] + (1 - d) * x[2])
    assert int(ema.model[1].num_batches_tracked) == int(net[1].num_batches_tracked) == 2
    assert not ema.model.training and not any(p.requires_grad for p in ema.model.parameters())


def test_ema_is_evaluated_beside_the_raw_weights_and_resumes_exactly(cache, tmp_path):
    """Every epoch records the average's validation accuracy; best.pt holds whichever was better
    (and says so); a run stopped after epoch 1 and resumed equals the run that was not stopped."""
    kw = {"optim.ema_decay": 0.5, "epochs": 2}
    full = train(tiny_config(cache, **kw), tmp_path / "full")
    assert all("val_acc_ema" in h for h in full["history"])
    best = checkpoint.load(tmp_path / "full" / "best.pt")
    h = full["history"][full["best_epoch"] - 1]
    assert best["best_val_acc"] == max(h["val_acc"], h["val_acc_ema"])
    assert best.get("ema_selected", False) == (h["val_acc_ema"] > h["val_acc"])
    assert "ema" in checkpoint.load(tmp_path / "full" / "last.pt")
    train(tiny_config(cache, **{**kw, "epochs": 1}), tmp_path / "part")
    resumed = train(tiny_config(cache, **kw, ckpt_path=str(tmp_path / "part" / "last.pt")), tmp_path / "resumed")
    for a, b in zip(resumed["history"], full["history"], strict=True):
        assert a["train_loss"] == pytest.approx(b["train_loss"], abs=1e-6)
        assert a["val_acc"] == b["val_acc"] and a["val_acc_ema"] == b["val_acc_ema"]
    assert resumed["test_acc"] == full["test_acc"]
    train(tiny_config(cache, epochs=1), tmp_path / "plain")  # no average in its checkpoint
    with pytest.raises(checkpoint.CheckpointMismatch, match="no weight average"):
        train(tiny_config(cache, **kw, ckpt_path=str(tmp_path / "plain" / "last.pt")), tmp_path / "again")
