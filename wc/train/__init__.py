"""WorldContact training: windows, schedules, checkpoints, the (DDP) loop."""
