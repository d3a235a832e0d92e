"""Top and wrist camera views of trajectories (Newton SensorCamera) and the rendered-frames store."""
