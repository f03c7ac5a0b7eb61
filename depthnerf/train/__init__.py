"""Training stage: configs and presets, batching, the training loop, checkpoints, distributed set-up."""
