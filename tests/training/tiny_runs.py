"""Command-line overrides that make the training commands run in seconds on tiny data."""

TINY_AE = ["data.train_scenes=1", "data.frames_per_scene=11", "data.val_scenes=1", "data.val_stride=11",
           "loss.num_occupied=500", "loss.num_near_free=200", "loss.num_far_free=100", "train.eval_every=0"]
TINY_WM = ["model.forecaster_widths=[8,8,8]", "model.scales=3", "model.max_tokens=64", "model.flow_widths=[8,8,8]",
           "model.planner_widths=[8,8,8,8]",
           "model.d_act=20", "data.train_scenes=1", "data.frames_per_scene=12", "data.val_scenes=1",
           "data.val_windows=1", "loss.num_occupied=500", "loss.num_near_free=200", "loss.num_far_free=100",
           "train.log_every=1", "train.eval_every=2", "train.ckpt_every=1", "train.batch_size=1"]
TINY_PLAN = ["data.train_scenes=1", "data.val_scenes=1", "data.frames_per_scene=14", "data.stride=1",
             "train.batch_size=2", "train.log_every=1", "train.eval_every=2", "train.ckpt_every=1"]
TINY_MOTION = ["data.train_scenes=1", "data.val_scenes=1", "data.frames_per_scene=14", "data.stride=1",
               "train.batch_size=2", "train.log_every=1", "train.eval_every=2", "train.ckpt_every=1"]
TINY_BOX = ["data.train_scenes=1", "data.select_scenes=1", "data.frames_per_scene=14", "data.stride=1",
            "train.batch_size=16", "train.log_every=1", "train.eval_every=2", "train.ckpt_every=1"]
