"""Training: config and presets, schedules as pure functions of progress, losses, the loop, checkpoints, outputs."""
