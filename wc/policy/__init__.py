"""Policy layer: LeRobot datasets of the lift task, policy fine-tuning and closed-loop evaluation."""
