"""Controller plugins: position-force teleoperation and baselines."""
