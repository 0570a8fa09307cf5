"""task=segmentation through the one trainer: the head's targets and loss, G trained on the 2D
loss through the renderer, evaluation by instance / class mIoU, records, mvtn-eval and refusals."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from mvtn_exp.config.schema import as_config
from mvtn_exp.data.collate import collate_shapes
from mvtn_exp.data.datasets import build_dataset
from mvtn_exp.engine import train
from mvtn_exp.model import build_mvtn
from mvtn_exp.selectors.training import LearnedTraining, SelectorTraining
from mvtn_exp.engine.step_timer import StepTimer
from mvtn_exp.tasks import lifting, part_metrics
from mvtn_exp.tasks.heads import build_head

from conftest import tiny_config

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> str:
    return str(tmp_path_factory.mktemp("parts_cache"))


def seg(cache, **kw) -> dict:
    return tiny_config(cache, **{"task.name": "segmentation", "dataset.name": "synthetic_parts",
                                 "dataset.num_per_class": [2, 1, 1], "epochs": 1, **kw})


def model_and_batch(cache, **kw):
    cfg = as_config(seg(cache, **kw))
    ds = build_dataset(cfg.dataset, "train", progress=False)
    head = build_head(cfg.task, ds)
    torch.manual_seed(0)
    model = build_mvtn(cfg, num_classes=head.num_outputs, categories=len(ds.classes))
    return cfg, model, head, collate_shapes([ds[i] for i in range(4)])


def test_the_targets_are_the_views_label_images_with_the_background_class(cache):
    cfg, model, head, batch = model_and_batch(cache, **{"selector.name": "circular"})
    views = model.select(batch)
    t = head.targets(model, batch, views)
    B, M, S = 4, cfg.views, cfg.image_size
    assert t.pixels.shape == t.index.shape == (B, M, S, S) and len(t) == B
    assert head.num_outputs == len(head.names) + 1 == 19
    shown = t.index >= 0
    assert bool((t.pixels[~shown] == head.background).all()) and 0.05 < float(shown.float().mean()) < 0.95
    faces = lifting.per_shape(batch["face_parts"], batch["meshes"].faces_per_shape)
    b, m, y, x = [int(v) for v in shown.nonzero()[0]]
    assert int(t.pixels[b, m, y, x]) == int(faces[b, t.index[b, m, y, x]])  # a pixel takes its face's part
    for b in range(B):  # every labelled pixel is a part of the shape's own category
        own = set(head.parts_of[int(batch["labels"][b])])
        assert set(t.pixels[b][shown[b]].unique().tolist()) <= own


def test_the_loss_is_per_pixel_cross_entropy_and_the_points_loss_lifts(cache):
    _, model, head, batch = model_and_batch(cache, **{"selector.name": "circular", "task.condition": "none"})
    views = model.select(batch)
    t = head.targets(model, batch, views)
    logits = torch.randn(*t.pixels.shape[:2], head.num_outputs, *t.pixels.shape[2:])
    manual = -logits.log_softmax(2).gather(2, t.pixels[:, :, None]).mean()
    assert torch.allclose(head(logits, t), manual, atol=1e-5)
    perfect = torch.nn.functional.one_hot(t.pixels, head.num_outputs).permute(0, 1, 4, 2, 3).float() * 50
    assert float(head(perfect, t)) < 1e-6 and head.hits(perfect, t) == 1.0
    head.cfg.loss = "points"
    scores, seen = lifting.lift(logits, t.index, t.num_prims, t.prim_of_point)
    assert torch.allclose(head(logits, t), torch.nn.functional.cross_entropy(scores[seen], t.points[seen]))


def test_the_balanced_loss_weighs_each_class_by_one_over_the_root_of_its_count(cache):
    """``task.balance=inverse_sqrt``: sum_i w(y_i) * nll_i / sum_i w(y_i), w = count(y)**-0.5 in the
    batch's targets, by hand; a rare class's mistakes cost more than under the paper's loss."""
    _, model, head, batch = model_and_batch(cache, **{"selector.name": "circular", "task.condition": "none",
                                                      "task.balance": "inverse_sqrt"})
    t = head.targets(model, batch, model.select(batch))
    logits = torch.randn(*t.pixels.shape[:2], head.num_outputs, *t.pixels.shape[2:])
    y = t.pixels.reshape(-1)
    w = torch.bincount(y, minlength=head.num_outputs).float()[y].rsqrt()
    nll = -logits.log_softmax(2).permute(0, 1, 3, 4, 2).reshape(-1, head.num_outputs).gather(1, y[:, None])[:, 0]
    assert torch.allclose(head(logits, t), (w * nll).sum() / w.sum(), rtol=1e-5)
    rare = int(torch.bincount(y).masked_fill(torch.bincount(y) == 0, y.numel()).argmin())
    wrong = logits.clone()
    wrong[:, :, rare] -= 20.0 * (t.pixels == rare)  # only the rare class's pixels made wrong
    head.cfg.balance = "none"
    plain = float(head(wrong, t) - head(logits, t))
    head.cfg.balance = "inverse_sqrt"
    assert float(head(wrong, t) - head(logits, t)) > 2 * plain > 0
    head.cfg.loss = "points"
    scores, seen = lifting.lift(logits, t.index, t.num_prims, t.prim_of_point)
    counts = torch.bincount(t.points[seen], minlength=head.num_outputs).clamp_min(1).float()
    assert torch.allclose(head(logits, t), torch.nn.functional.cross_entropy(scores[seen], t.points[seen],
                                                                             weight=counts.rsqrt()), rtol=1e-5)


def test_the_category_condition_scores_among_the_categorys_parts_and_the_background(cache):
    _, model, head, batch = model_and_batch(cache, **{"selector.name": "circular"})
    t = head.targets(model, batch, model.select(batch))
    logits = torch.randn(*t.pixels.shape[:2], head.num_outputs, *t.pixels.shape[2:])
    by_hand = 0.0
    for b in range(len(t)):
        cols = head.parts_of[int(batch["labels"][b])] + [head.background]
        local = torch.tensor([cols.index(int(v)) for v in t.pixels[b].reshape(-1)]).view(t.pixels[b].shape)
        by_hand += torch.nn.functional.cross_entropy(logits[b][:, cols], local, reduction="sum")
    assert torch.allclose(head(logits, t), by_hand / t.pixels.numel(), rtol=1e-5)
    other = logits.clone()
    other[:, :, head.parts_of[0]] += 100.0  # airplane parts: on shapes of other categories no part is one
    mine = batch["labels"] != 0
    assert torch.allclose(head(other[mine], _sub(t, mine)), head(logits[mine], _sub(t, mine)))
    head.cfg.condition = "none"
    assert not torch.allclose(head(other[mine], _sub(t, mine)), head(logits[mine], _sub(t, mine)))


def _sub(t, keep):
    return type(t)(t.pixels[keep], t.index[keep], t.points[keep], None if t.prim_of_point is None else
                   t.prim_of_point[keep], t.num_prims, t.categories[keep])


@pytest.mark.parametrize("loss", ["pixels", "points"])
def test_g_trains_on_the_segmentation_loss_through_the_renderer(cache, loss):
    cfg, model, head, batch = model_and_batch(cache, **{"task.loss": loss})
    training = LearnedTraining(cfg)
    training.start_epoch(model, 1, 1e-3, hold_views=False)
    out = training.train_step(model, batch, 0, head, StepTimer(torch.device("cpu")))
    out.objective.backward()
    grads = [p.grad for p in model.parameter_groups()["selector"] if p.grad is not None]
    assert grads and float(sum(g.abs().sum() for g in grads)) > 0  # the 2D loss reaches G
    assert out.labels.pixels.shape[:2] == (4, cfg.views)


def test_oracle_logits_score_one_and_unrestricted_or_unfilled_predictions_score_less(cache):
    """C's output replaced by the true label images: every seen point right; the unseen ones take
    their nearest seen point's part, and the mIoU is that of those fills, by hand."""
    _, model, head, batch = model_and_batch(cache, **{"selector.name": "circular", "views": 4})
    model.eval()
    views = model.select(batch)
    t = head.targets(model, batch, views)
    oracle = torch.nn.functional.one_hot(t.pixels, head.num_outputs).permute(0, 1, 4, 2, 3).float()
    pred, seen = head.predict(oracle, t, batch)
    assert bool((pred[seen] == t.points[seen]).all())
    nearest = [torch.cdist(batch["points"][b][~seen[b]], batch["points"][b][seen[b]]).argmin(1) for b in range(4)]
    for b in range(4):
        assert torch.equal(pred[b][~seen[b]], t.points[b][seen[b]][nearest[b]])
    ious = [part_metrics.shape_iou(p, q, head.parts_of[int(c)]) for p, q, c in zip(pred, t.points, batch["labels"])]
    assert min(ious) > 0.5
    background_first = oracle.clone()
    background_first[:, :, head.background] += 2  # the background's logit is never a point's prediction
    assert torch.equal(head.predict(background_first, t, batch)[0], pred)


@pytest.fixture(scope="module")
def learned_run(cache, tmp_path_factory):
    run = tmp_path_factory.mktemp("seg_run")
    return run, train(seg(cache, **{"logger.tensorboard": True}), run)


def test_a_run_writes_the_segmentation_metrics_pictures_and_part_confusion(learned_run):
    run, m = learned_run
    disk = json.loads((run / "metrics.json").read_text())
    for key in ("test_instance_miou", "test_class_miou", "test_coverage", "best_val_instance_miou", "test_acc"):
        assert 0.0 <= disk[key] <= 1.0, key
    assert "best_val_acc" not in disk  # model selection was by validation instance mIoU
    per = disk["test_per_category_miou"]
    assert set(per) == {"airplane", "chair", "lamp", "mug", "table"} and sum(v["shapes"] for v in per.values()) == 5
    assert disk["test_class_miou"] == pytest.approx(sum(v["miou"] for v in per.values()) / 5)
    assert disk["test_size"] == 5 and disk["test_points"] == 5 * 1024
    conf = json.loads((run / "confusion.json").read_text())
    assert len(conf["matrix"]) == 18 and conf["classes"] == disk["part_names"] and conf["rows"] == "true part"
    assert sum(map(sum, conf["matrix"])) == 5 * 1024
    assert "val_instance_miou" in disk["history"][0] and "val_coverage" in disk["history"][0]
    for name in ("parts_views.png", "parts_points.png"):
        assert (run / name).stat().st_size > 100
    assert "test instance mIoU" in (run / "train.log").read_text()
    events = list((run / "tb").glob("events.*"))
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(events[0])).Reload()
    assert {"parts/views", "parts/points"} <= set(acc.Tags()["images"])
    assert "val/instance_mIoU" in acc.Tags()["scalars"]


def _cli(args, cwd):
    return subprocess.run([sys.executable, "-m", "mvtn_exp.cli.eval", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=300)


def test_mvtn_eval_scores_a_segmentation_checkpoint_and_refuses_another_task(learned_run, tmp_path):
    run, m = learned_run
    out = _cli([f"ckpt={run / 'best.pt'}", "progress=false", f"hydra.run.dir={tmp_path / 'e'}"], tmp_path)
    assert out.returncode == 0, out.stderr
    disk = json.loads((tmp_path / "e" / "metrics.json").read_text())
    assert disk["test_instance_miou"] == pytest.approx(m["test_instance_miou"])
    assert "| instance mIoU | class mIoU |" in (tmp_path / "e" / "results.md").read_text()
    assert (tmp_path / "e" / "parts_views.png").is_file()
    for task in ("classification", "retrieval"):
        bad = _cli([f"ckpt={run / 'best.pt'}", f"task={task}", f"hydra.run.dir={tmp_path / task}"], tmp_path)
        assert bad.returncode == 2 and "Traceback" not in bad.stderr
        assert bad.stderr.strip().splitlines()[-1].endswith(
            f"was trained with task=segmentation: it cannot be evaluated with task={task} (leave task unset to "
            "evaluate its own task)")


@pytest.mark.parametrize("overrides, expected", [
    (["task=segmentation"], "task=segmentation: dataset=synthetic has no part labels; the datasets that have them: "
                            "shapenet_parts, synthetic_parts"),
    (["task=segmentation", "dataset=synthetic_parts", "mvnet=viewgcn"], "mvnet=viewgcn with task=segmentation"),
    (["task=segmentation", "dataset=synthetic_parts", "selector=poi"], "selector=poi with task=segmentation: its "
                                                                        "training strategies"),
    (["task=segmentation", "dataset=synthetic_parts", "task.fuse=max"], "task.fuse"),
])
def test_a_task_the_config_cannot_serve_is_one_line(tmp_path, overrides, expected):
    out = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.train", *overrides, f"hydra.run.dir={tmp_path / 'r'}"],
                         cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1 and expected in out.stderr
    assert not (tmp_path / "r").exists()


def test_a_classifier_checkpoint_is_refused_by_segmentation_evaluation(learned_run, tmp_path):
    run, _ = learned_run
    payload = torch.load(run / "best.pt", weights_only=False)
    payload["config"]["task"]["name"] = "classification"  # (refused before any weight is read)
    torch.save(payload, tmp_path / "cls.pt")
    bad = _cli([f"ckpt={tmp_path / 'cls.pt'}", "task=segmentation", f"hydra.run.dir={tmp_path / 'e'}"], tmp_path)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
    assert "was trained with task=classification: it cannot be evaluated with task=segmentation" in bad.stderr


def test_g_can_read_the_shapes_category_and_learns_from_it(cache):
    cfg, model, head, batch = model_and_batch(cache, **{"selector.category_input": True})
    assert model.selector.categories == 5  # built from the dataset's category count (the trainer's)
    last = model.selector.regressor[-1]
    torch.nn.init.normal_(last.weight, std=0.5)  # (at init G sits exactly at u0 whatever its input)
    model.eval()
    same = dict(batch, points=batch["points"][:1].expand(2, -1, -1), labels=torch.tensor([0, 3]))
    azim, elev, _ = model.select(same)
    assert not torch.allclose(azim[0], azim[1])  # one point cloud, two categories: two sets of views
    model.train()
    training = LearnedTraining(cfg)
    training.start_epoch(model, 1, 1e-3, hold_views=False)
    training.train_step(model, batch, 0, head, StepTimer(torch.device("cpu"))).objective.backward()
    category_columns = model.selector.regressor[0].weight.grad[:, -5:]  # (the input's last 5: the one-hot)
    assert float(category_columns.abs().sum()) > 0  # the loss reaches the category's weights


def test_a_run_with_gs_category_input_trains_tests_and_reloads(cache, tmp_path):
    from mvtn_exp.config.eval_schema import EvalConfig
    from mvtn_exp.evaluation.evaluate import evaluate_checkpoint

    m = train(seg(cache, **{"selector.category_input": True}), tmp_path / "run")
    again = evaluate_checkpoint(EvalConfig(ckpt=str(tmp_path / "run" / "best.pt"), progress=False), tmp_path / "eval")
    assert again["test_instance_miou"] == pytest.approx(m["test_instance_miou"])


def test_g_never_reads_the_label_of_a_classification(tmp_path):
    out = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.train", "selector.category_input=true",
                          f"hydra.run.dir={tmp_path / 'r'}"], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "selector.category_input=true with task=classification: G would read the label it is to predict" in out.stderr


def test_an_unknown_balance_is_refused_naming_the_key():
    from mvtn_exp.tasks.config import TaskConfig

    with pytest.raises(ValueError, match=r"task\.balance.*inverse_sqrt"):
        TaskConfig(name="segmentation", balance="median").validate()
