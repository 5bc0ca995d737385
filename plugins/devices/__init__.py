"""Device plugins: leaders (haptic devices) and followers (grippers)."""
