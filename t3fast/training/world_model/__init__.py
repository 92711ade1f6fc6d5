"""Stage 2: training the forecaster and planner, fine-tuning the decoder.

The encoder of a stage-1 checkpoint is frozen. Each training sample is an 11-frame window;
a rollout of ``loss.rollout_steps`` autoregressive steps starts at a random future step
``k``. Its history is what the model would have at step ``k`` at inference: the encoded
frames up to the present and the model's own predictions of steps ``0 .. k-1``, computed
without gradients (the "pushforward" trick of Brandstetter et al. 2022: training sees its
own errors, at the cost of forward passes only); later steps of the rollout see the
model's predictions with gradients. The loss of each predicted step is

    L1(next, enc(frame)) + gamma * MSE(next, enc(frame))        # triplane
    + xi * (CE + Lovasz)(decoder(next) at sampled points)      # occupancy
    + action_weight * |a - a_true|^2                            # planning

averaged over the rollout's steps. ``rollout_steps = 6`` trains the full 3 s rollout every
step; the CPU presets use shorter rollouts from random starts (the same per-step queries
and targets, a fraction of the cost).
"""
