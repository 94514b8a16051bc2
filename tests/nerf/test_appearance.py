"""Per-image appearance: a robot whose images are tinted learns the tint, not a tinted field."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from agent.appearance import AppearanceConfig, ColourAffine
from agent.data.loaders import load_views
from agent.data.split import estimate_scene_box
from agent.data.views import Views
from agent.geometry import box_from_center
from agent.trainer import RobotTrainer
from tests.nerf.test_end_to_end import small_config


def test_zero_parameters_are_the_identity_and_the_background_is_untouched():
    rgb, opacity, bg = torch.rand(5, 3), torch.rand(5), torch.rand(5, 3)
    assert torch.allclose(ColourAffine.apply(torch.zeros(5, 12), rgb, opacity, bg), rgb)
    gain = torch.zeros(5, 12)
    gain[:, 0] = 1.0  # red doubled
    empty = ColourAffine.apply(gain, bg, torch.zeros(5), bg)  # nothing of the field: only background
    assert torch.allclose(empty, bg)


def test_the_nearest_training_view_gives_a_held_out_view_its_transform():
    views = load_views("procedural:views=12,width=8")
    ca = ColourAffine(12, AppearanceConfig(enabled=True))
    with torch.no_grad():
        ca.params.copy_(torch.arange(12.0)[:, None].expand(12, 12))
    got = ca.nearest(views.c2w, views.c2w[[3, 7]])
    assert torch.equal(got[:, 0], torch.tensor([3.0, 7.0]))


@pytest.mark.slow
def test_a_tinted_half_of_the_views_is_explained_by_its_transforms_not_by_the_field():
    views = load_views("procedural:views=24,width=32")
    tint = torch.tensor([1.25, 1.0, 0.8])
    tinted = [i for i in range(len(views)) if i % 2]
    images = views.images.clone()
    images[tinted, ..., :3] = (images[tinted, ..., :3] * tint).clamp(0, 1)
    train = Views(images, views.c2w, views.intrinsics, views.names, views.depth, views.meta)
    center, half, _ = estimate_scene_box(views)
    box = box_from_center(center, half)
    clean = [i for i in range(len(views)) if i % 2 == 0]

    def fit(appearance: bool) -> tuple[float, RobotTrainer]:
        cfg = dataclasses.replace(small_config(500), appearance=AppearanceConfig(enabled=appearance))
        trainer = RobotTrainer(train, cfg, box)
        trainer.train(500)
        # every image as its camera saw it: through its own transform (none without appearance)
        own = trainer.appearance.params.detach() if appearance else None
        scores = trainer.evaluate(train, with_ssim=False, appearance=own)
        return sum(scores["psnr"]) / len(scores["psnr"]), trainer

    without, _ = fit(False)
    with_, trainer = fit(True)
    # gauge-free: what the tinted views' transform makes of what the clean views' transform shows
    p = trainer.appearance.params.detach()
    colours = views.images[clean][views.images[clean][..., 3] == 1][:, :3]  # [N, 3] true colours
    a_clean, a_tint = ColourAffine.matrix(p[clean].mean(0)), ColourAffine.matrix(p[tinted].mean(0))
    field_colour = torch.linalg.solve(a_clean[:3, :3], (colours - a_clean[:3, 3]).T).T
    predicted = field_colour @ a_tint[:3, :3].T + a_tint[:3, 3]
    truth = (colours * tint).clamp(0, 1)
    learnt, ignored = (predicted - truth).abs().mean(), (colours - truth).abs().mean()
    print(f"the training views: {without:.2f} dB without appearance, {with_:.2f} dB with; tint error "
          f"{float(learnt):.4f} learnt, {float(ignored):.4f} if ignored")
    assert with_ > without + 1.0
    assert learnt < 0.5 * ignored
