"""Stage 1: pretraining the triplane autoencoder on single occupancy frames (cross-entropy +
Lovasz-softmax at sampled query points, :mod:`t3fast.training.losses`)."""
