"""The forecaster learns: on a handful of training windows a short run of the flow forecaster
gets its latent loss well below the copy forecast's and its decoded forecast (along the true
ego poses) above its own start. The papers' Delta forecaster, trained the old way, did neither
within hundreds of steps."""

from __future__ import annotations

import torch

from t3fast.data.synthetic import SyntheticDriving
from t3fast.evaluation.world_model import SharedRollout, evaluate_many, t3former_method
from t3fast.io.config import config_to_dict, load_config
from t3fast.presets import preset
from t3fast.training.configs import Stage2Config
from t3fast.training.trainer import Trainer
from t3fast.training.world_model.latent_cache import collate_aligned
from t3fast.training.world_model.motion_loss import motion_loss
from t3fast.training.world_model.task import WorldModelTask

# without the random flips: the test asks whether the path can fit its own few windows
FEW_WINDOWS = ["autoencoder_ckpt=wm-small", "data.train_scenes=1", "data.frames_per_scene=15", "data.stride=2",
               "model.flow_widths=[16,16,24,32]", "train.steps=60", "train.batch_size=3", "train.lr=3e-3",
               "train.warmup_steps=5", "train.eval_every=0", "train.ckpt_every=0", "train.log_every=10",
               "train.tensorboard=false", "data.latent_flips=false"]


def _steered_miou(model, windows: SyntheticDriving) -> tuple[float, float]:
    """(Avg mIoU, moving-class Avg mIoU) of the forecast rendered along the true future poses."""
    shared = SharedRollout(model)
    record = evaluate_many({"gt": t3former_method(model, gt_ego=True, shared=shared)}, windows, progress=False,
                           absent="skip")["gt"]
    return record["miou"]["avg"], record["miou_moving"]["avg"]


def test_flow_forecaster_learns_the_motion_of_its_training_windows(tmp_path):
    torch.manual_seed(0)
    cfg = load_config(Stage2Config, config_to_dict(preset("small", "wm")),
                      FEW_WINDOWS + [f"data.cache_dir={tmp_path / 'cache'}", f"train.out_dir={tmp_path / 'run'}"])
    task = WorldModelTask(cfg)
    trainer = Trainer(task, cfg.train)
    model = trainer.module
    windows = SyntheticDriving("train", 1, cfg.data.frames_per_scene, stride=cfg.data.stride)
    assert len(windows) == 3
    before = _steered_miou(model.eval(), windows)
    trainer.fit()
    cache = task.train_dataset()  # built by the run: every window is on disk now
    assert not cache.missing()
    batch = collate_aligned([cache[i] for i in range(len(cache))])
    with torch.no_grad():
        _, parts = motion_loss(model.eval(), batch, cfg.loss)
    assert parts["latent"] < 0.8 * parts["copy_latent"], parts
    after = _steered_miou(model, windows)
    # the gains depend on the CPU's float kernels (60 steps from one seed): moving-class above +3
    # on the AMD EPYC this test was written on, +1.7 on an Intel Xeon (family 6 model 167)
    assert after[0] > before[0] + 1.0 and after[1] > before[1] + 1.0, (before, after)
